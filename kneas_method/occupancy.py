"""Empty space from the projections alone: a conservative occupancy grid (the visual hull).

A point can hold material only if every training ray through it measured something:
a ray that crossed material has a line integral above the noise in air. So the cells
of a coarse grid over the volume box whose centre projects onto an air pixel of
any training view are empty (space carving). To stay conservative the object masks
are dilated on the detector (a cell is wider than the point at its centre; grazing
rays near an object's edge read little) and the carved grid is dilated by a cell.
Nothing is learned, no reconstruction is needed, and material is never carved away
as long as air pixels are recognised (noise-aware threshold, see
``datamanagers.ct.noise_air_threshold``, on noisy views averaged over a few pixels first, see
``engine.visual_hull.air_test_views``); cavities inside the object stay occupied.

Used by :class:`~kneas_method.model.CTModel` (``model.occupancy_grid``) to put every
sample of a ray inside the occupied stretch of the ray (:func:`ray_intervals`) and to
make ``mu`` zero outside the grid (:func:`occupancy_at`), so training, evaluation
and export see the same empty space.

Shapes: grids ``[Gx, Gy, Gz]`` (index order x, y, z); points ``[P, 3]``, rays
``[R, 3]``, model units. The grid's cells split the volume box
``[lo, hi]`` (model units) into ``G`` equal parts per axis.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F


def grid_centres(lo, hi, shape) -> list[torch.Tensor]:
    """Cell-centre coordinates per axis (model units), float64: ``[Gx]``, ``[Gy]``, ``[Gz]``."""
    return [torch.tensor(l_ + (np.arange(n) + 0.5) * (h_ - l_) / n, dtype=torch.float64) for l_, h_, n in zip(lo, hi, shape)]


def box_of(geometry) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """The volume box ``(lo, hi)`` of a geometry, model units."""
    half = geometry.volume_half_size
    lo = tuple(o - h for o, h in zip(geometry.off_origin, half))
    hi = tuple(o + h for o, h in zip(geometry.off_origin, half))
    return lo, hi


def visual_hull(geometry, angles, projections, *, resolution: int = 64, air_threshold: float = 0.0,
                dilate_pixels: int = 2, dilate_cells: int = 1) -> torch.Tensor:
    """The occupancy grid ``[G, G, G]`` (bool) carved from the training views.

    Args:
        geometry: the scan geometry (cone or parallel beam).
        angles: ``[N]`` view angles (rad).
        projections: ``[N, nV, nU]`` line integrals.
        resolution: G, cells per axis over the volume box.
        air_threshold: line integrals at or below it are air.
        dilate_pixels: object masks are dilated by this many detector pixels.
        dilate_cells: the carved grid is dilated by this many cells.
    """
    G = int(resolution)
    lo, hi = box_of(geometry)
    xs, ys, zs = grid_centres(lo, hi, (G, G, G))
    X, Y, Z = torch.meshgrid(xs, ys, zs, indexing="ij")
    p = torch.as_tensor(np.asarray(projections), dtype=torch.float32)
    obj = (p > air_threshold).float()[:, None]
    if dilate_pixels > 0:
        k = 2 * int(dilate_pixels) + 1
        obj = F.max_pool2d(obj, k, stride=1, padding=int(dilate_pixels))
    obj = obj[:, 0] > 0  # [N, nV, nU]
    (nu, nv), (du, dv), (ou, ov) = geometry.n_detector, geometry.d_detector, geometry.off_detector
    occupied = torch.ones(G, G, G, dtype=torch.bool)
    for k, angle in enumerate(np.asarray(angles, dtype=np.float64).reshape(-1)):
        c, s = math.cos(angle), math.sin(angle)
        across = -X * s + Y * c  # coordinate along the detector's u direction
        if geometry.mode == "cone":
            mag = geometry.dsd / (geometry.dso - (X * c + Y * s))
            u, v = across * mag, -Z * mag
        else:
            u, v = across, -Z
        i = torch.floor((u - ou) / du + nu / 2).long()
        j = torch.floor((v - ov) / dv + nv / 2).long()
        seen = (i >= 0) & (i < nu) & (j >= 0) & (j < nv)
        hit = torch.ones_like(occupied)  # cells outside this view's detector are not carved by it
        hit[seen] = obj[k][j[seen], i[seen]]
        occupied &= hit
    if dilate_cells > 0:
        k = 2 * int(dilate_cells) + 1
        occupied = F.max_pool3d(occupied.float()[None, None], k, stride=1, padding=int(dilate_cells))[0, 0] > 0
    return occupied


def occupancy_at(occupied: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """``[P]`` (points' dtype): 1 where a point lies in an occupied cell, 0 elsewhere (also outside the box).

    Args:
        occupied: ``[Gx, Gy, Gz]`` bool or 0/1.
        lo, hi: ``[3]`` the box, model units.
        points: ``[P, 3]`` model units.
    """
    shape = torch.tensor(occupied.shape, device=points.device)
    cell = torch.floor((points - lo) / (hi - lo) * shape).long()
    inside = ((cell >= 0) & (cell < shape)).all(-1)
    cell = torch.minimum(torch.clamp(cell, min=0), shape - 1)
    flat = (cell[:, 0] * shape[1] + cell[:, 1]) * shape[2] + cell[:, 2]
    return (occupied.reshape(-1)[flat].to(torch.bool) & inside).to(points.dtype)


def ray_intervals(occupied: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor, origins: torch.Tensor, directions: torch.Tensor,
                  near: float, far: float, n_probe: int = 256) -> tuple[torch.Tensor, torch.Tensor]:
    """The stretch ``[t0, t1]`` (model units along the unnormalised directions) of each ray that
    holds every occupied cell it crosses: the ray is probed at ``n_probe`` even steps in
    ``[near, far]`` (steps shorter than a cell), and the first and last occupied probes are
    widened by one step. A ray through no occupied cell gets ``t0 == t1`` (nothing to integrate).
    Only a sliver of a cell shorter than one step (a ray grazing a cell's corner) can be
    stepped over; material there adds at most ``mu`` x one step to the line integral.

    Returns ``(t0 [R], t1 [R])``.
    """
    R = origins.shape[0]
    dt = (far - near) / n_probe
    t = near + (torch.arange(n_probe, device=origins.device, dtype=origins.dtype) + 0.5) * dt  # [C]
    pts = origins[:, None, :] + t[None, :, None] * directions[:, None, :]
    hit = occupancy_at(occupied, lo, hi, pts.reshape(-1, 3)).reshape(R, n_probe) > 0
    any_hit = hit.any(1)
    first = torch.argmax(hit.to(torch.int8), 1)
    last = n_probe - 1 - torch.argmax(hit.flip(1).to(torch.int8), 1)
    t0 = torch.where(any_hit, torch.clamp(t[first] - dt, min=near), torch.full_like(t[first], near))
    t1 = torch.where(any_hit, torch.clamp(t[last] + dt, max=far), torch.full_like(t[first], near))
    return t0, t1

