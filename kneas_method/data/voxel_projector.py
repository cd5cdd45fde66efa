"""Ray-marching projector of a voxel volume along the SPEC §1 rays (torch, CPU or CUDA).

The volume is interpolated trilinearly, with its samples at the voxel centres of
:meth:`Geometry.voxel_axes` and zero outside (the value fades to 0 over the half
voxel beyond the outermost centres). Each ray is sampled at the midpoints of equal
steps between the geometry's near and far, the step being at most
``voxel / samples_per_voxel`` in length, and the line integral is
``Σ mu_data(x_k) · step_k`` with lengths in metres, i.e. the same unit as the
projections of a NAF scene.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from ..errors import SceneError
from ..geometry import Geometry

# Sample points evaluated per batch when ``chunk`` is not given (bounds memory to ~0.5 GB on CPU).
POINTS_PER_BATCH = 1 << 22


def _normalise_axis_params(geometry: Geometry, device, dtype):
    """Per axis (x, y, z): the affine map model units -> grid_sample coordinate.

    The volume is padded with one zero voxel on every side (so a single-voxel axis
    works too); with ``align_corners=True`` the padded grid's outermost centres,
    at ``±(n + 1)·d/2`` from the volume centre, map to ``±1``.
    """
    scale, shift = [], []
    for n, d, o in zip(geometry.n_voxel, geometry.d_voxel, geometry.off_origin):
        half_span = (n + 1) * d / 2
        scale.append(1.0 / half_span)
        shift.append(-o / half_span)
    return torch.tensor(scale, device=device, dtype=dtype), torch.tensor(shift, device=device, dtype=dtype)


def project_volume(
    volume,
    geometry: Geometry,
    angles,
    samples_per_voxel: float = 2.0,
    chunk: int | None = None,
    device: str | torch.device | None = None,
    progress=None,
) -> np.ndarray:
    """Line integrals of a voxel volume along every detector pixel's ray.

    Args:
        volume: [nx, ny, nz] attenuation in data units (1/m), numpy or torch;
            ``volume[a, b, c]`` sits at voxel centre ``(x_a, y_b, z_c)``; shape must equal
            ``geometry.n_voxel``.
        geometry: the scan geometry (model units).
        angles: [N] view angles in radians.
        samples_per_voxel: samples per (smallest) voxel length along a ray; the step is
            ``min(d_voxel) / samples_per_voxel`` or shorter (default 2: half a voxel).
        chunk: rays per batch (default: as many as keep ~4M sample points per batch).
        device: torch device (default: the volume's device if a tensor, else CPU).
        progress: optional callable ``progress(done_views, total_views)``.

    Returns:
        [N, nV, nU] float32 line integrals ``∫ mu_data dl`` (l in metres).
    """
    if samples_per_voxel <= 0:
        raise SceneError(f"samples_per_voxel is {samples_per_voxel}; it must be positive (2 = half-voxel steps)")
    if device is None:
        device = volume.device if isinstance(volume, torch.Tensor) else "cpu"
    device = torch.device(device)
    vol = torch.as_tensor(np.asarray(volume) if not isinstance(volume, torch.Tensor) else volume)
    if tuple(vol.shape) != tuple(geometry.n_voxel):
        raise SceneError(f"volume has shape {tuple(vol.shape)} but the geometry's nVoxel is {tuple(geometry.n_voxel)}; they must be equal")
    vol = vol.to(device=device, dtype=torch.float32)
    # grid_sample wants [B, C, D, H, W] with grid (x, y, z) -> (W, H, D): put x last.
    grid_input = F.pad(vol.permute(2, 1, 0)[None, None], (1, 1, 1, 1, 1, 1))

    angles = np.asarray(angles, dtype=np.float64).reshape(-1)
    n_u, n_v = geometry.n_detector
    near, far = geometry.near_far
    step_len = min(geometry.d_voxel) / samples_per_voxel  # model units
    scale_t, shift_t = _normalise_axis_params(geometry, device, torch.float32)
    out = np.zeros((len(angles), n_v, n_u), dtype=np.float32)

    for v_idx, angle in enumerate(angles):
        origins, dirs = geometry.rays([angle], device=device, dtype=torch.float32)
        origins, dirs = origins.reshape(-1, 3), dirs.reshape(-1, 3)
        dnorm = dirs.norm(dim=-1)  # [R]
        # One t-grid for the view: the longest direction sets the step in t.
        dt = step_len / float(dnorm.max())
        n_samples = max(1, math.ceil((far - near) / dt))
        dt = (far - near) / n_samples
        t = near + (torch.arange(n_samples, device=device, dtype=torch.float32) + 0.5) * dt  # [S]
        rays_per_batch = chunk or max(1, POINTS_PER_BATCH // n_samples)
        sums = []
        for start in range(0, origins.shape[0], rays_per_batch):
            o = origins[start : start + rays_per_batch]
            d = dirs[start : start + rays_per_batch]
            pts = o[:, None, :] + t[None, :, None] * d[:, None, :]  # [R, S, 3] model units
            grid = (pts * scale_t + shift_t)[None, :, :, None, :]  # [1, R, S, 1, 3]
            mu = F.grid_sample(grid_input, grid, mode="bilinear", padding_mode="zeros", align_corners=True)
            sums.append(mu[0, 0, :, :, 0].sum(-1))  # [R]
        line = torch.cat(sums) * dnorm * (dt / geometry.scale)  # model units -> metres
        out[v_idx] = line.reshape(n_v, n_u).cpu().numpy()
        if progress is not None:
            progress(v_idx + 1, len(angles))
    return out
