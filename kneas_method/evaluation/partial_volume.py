"""Partial-volume shells: thin layers of an intermediate material at the edge of two others.

Where a low and a high material meet, a voxel-averaged or blurred attenuation passes
through every level in between, so a model (or a threshold) can call that edge an
intermediate material: a shell about one voxel thick between, say, soft tissue and cortical
bone, labelled cancellous bone. The shell is not that material; its surface lies far from
the material's true surface and adds surfaces that are not there (abdomen: a cancellous shell
on the spinous process's faces, 10-24 mm from the vertebral body's cancellous bone).

**The rule** (labels 0 = air, 1..K materials; ``levels [K]`` their attenuations, air at 0).
A binary opening of ``k``'s region by a cube ``max(2, round(1.5 f))`` cells wide (``f`` = cells
per voxel) keeps ``k``'s *core*, its parts at least about 1.5 voxels thick. A cell of ``k`` is
a *shell cell* when

* it is more than one voxel (``f`` cells, a cube) from ``k``'s core: the rim of a thick body
  of ``k`` stays ``k``, since at that scale partial volume and a true thin layer look alike
  and the body beside it says which it is;
* a higher label lies within one voxel of it, and a lower one: a lower *material* for a thin
  part of a body of ``k``; any lower label, air included, when the cell's piece of ``k``
  (26-connected) is nowhere thick (under 5 % of it in the core). At the object's surface a
  thin layer over a denser one is common anatomy (skin over bone), so a body's thin part
  there stays; a whole piece with no body is the edge of the object.

A shell cell takes the label, among the labels other than ``k`` whose core lies within one
voxel of it (the bodies the edge lies between), whose level is nearest the attenuation at the
cell: a mix of a low and a high material whose attenuation is past their midpoint is mostly
the high one. With no such body beside it, the cell stays ``k``. A thin layer with nothing denser
beside it stays. Needs no ground truth: only the labels, the attenuation and the materials'
levels.

The naive, cell-by-cell version of the rule is ``tests/test_partial_volume.py``'s oracle.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
from scipy import ndimage

#: A material's core: its parts at least this many voxels thick (an opening by a cube this wide).
SHELL_VOXELS = 1.5
#: A piece of a material (26-connected) with fewer than this share of its cells in the
#: core is nowhere thick: all of it is an edge.
CORE_SHARE = 0.05


def opening_width(cells_per_voxel: int) -> int:
    """Side (cells) of the cube whose binary opening removes parts thinner than ``SHELL_VOXELS``."""
    return max(2, int(round(SHELL_VOXELS * int(cells_per_voxel))))


def _cube_max(mask: np.ndarray, width: int) -> np.ndarray:
    """Binary dilation by a ``width`` cube (separable maximum filter); cells past the border repeat the edge."""
    return ndimage.maximum_filter(mask.view(np.uint8), size=width, mode="nearest").astype(bool)


def _opening(mask: np.ndarray, width: int) -> np.ndarray:
    """Binary opening by a ``width`` cube: the cells some ``width`` cube inside ``mask`` covers.
    The grid's edge cells are repeated outwards, so a region running out of the grid is not thin there."""
    m = np.pad(mask.view(np.uint8), width, mode="edge")
    eroded = ndimage.minimum_filter(m, size=width)
    # the dilation mirrors the erosion's origin, so that the opening is a union of whole cubes
    origin = 0 if width % 2 else -1
    opened = ndimage.maximum_filter(eroded, size=width, origin=origin)
    return opened[(slice(width, -width),) * mask.ndim].astype(bool)


def relabel_shells(labels: np.ndarray, mu: np.ndarray, levels: Sequence[float], cells_per_voxel: int = 1) -> np.ndarray:
    """Labels with partial-volume shell cells relabelled (module docs).

    Args:
        labels: ``[X, Y, Z]`` integers, 0 = air, ``k`` = material ``k`` (1..K).
        mu: ``[X, Y, Z]`` attenuation at the same cells (data units).
        levels: ``[K]`` attenuation of each material (data units); air's is 0.
        cells_per_voxel: grid cells per voxel along an axis (1: the scene grid; 2: the
            evaluation's surface grid).
    Returns:
        ``[X, Y, Z]`` labels, same dtype; equal to ``labels`` where no shell is found.
    """
    lab = np.asarray(labels)
    mu = np.asarray(mu, dtype=np.float32)
    if lab.shape != mu.shape:
        raise ValueError(f"labels {lab.shape} and attenuation {mu.shape} differ in shape")
    f = max(1, int(cells_per_voxel))
    lv = np.concatenate([[0.0], np.asarray(levels, dtype=np.float64)])  # index = label
    K = len(lv) - 1
    present = [j for j in range(K + 1) if (lab == j).any()]
    reach = 2 * f + 1
    width = opening_width(f)
    near: dict[int, np.ndarray] = {}

    def near_of(j: int) -> np.ndarray:  # cells within one voxel of label j (computed once)
        if j not in near:
            near[j] = _cube_max(lab == j, reach)
        return near[j]

    core: dict[int, np.ndarray] = {}
    body: dict[int, np.ndarray] = {}

    def core_of(j: int) -> np.ndarray:  # label j's parts at least SHELL_VOXELS thick (computed once)
        if j not in core:
            core[j] = _opening(lab == j, width)
        return core[j]

    def body_of(j: int) -> np.ndarray:  # cells within one voxel of label j's core (computed once)
        if j not in body:
            body[j] = _cube_max(core_of(j), reach)
        return body[j]

    out = lab.copy()
    for k in present:
        lower = [j for j in present if j != k and lv[j] < lv[k]]
        higher = [j for j in present if j != k and lv[j] > lv[k]]
        if k == 0 or not lower or not higher:
            continue
        region = lab == k
        thin = region & ~body_of(k)  # more than one voxel from k's core
        if not thin.any():
            continue
        pieces, n = ndimage.label(region, structure=np.ones((3, 3, 3), bool))
        coreless = np.bincount(pieces[core_of(k)], minlength=n + 1) < CORE_SHARE * np.bincount(pieces.ravel(), minlength=n + 1)
        coreless[0] = False
        coreless = coreless[pieces]
        above = np.logical_or.reduce([near_of(j) for j in higher])
        below_material = [j for j in lower if j != 0]
        inside = np.logical_or.reduce([near_of(j) for j in below_material]) if below_material else np.zeros_like(region)
        below = (inside | near_of(0)) if 0 in lower else inside
        # a piece with no core: between any lower and higher label; a thin part of a thick body:
        # between two materials only (at the object's surface a thin layer over a denser one is common)
        shell = thin & above & ((coreless & below) | inside)
        idx = np.nonzero(shell)
        if not idx[0].size:
            continue
        cell_mu = mu[idx]
        best = np.full(cell_mu.shape, -1, dtype=np.int64)
        gap = np.full(cell_mu.shape, np.inf)
        for j in present:
            if j == k:
                continue
            d = np.where(body_of(j)[idx], np.abs(cell_mu - lv[j]), np.inf)
            better = d < gap
            best[better] = j
            gap[better] = d[better]
        out[idx] = np.where(best >= 0, best, k).astype(lab.dtype)
    return out


def field_step(fields: np.ndarray) -> float:
    """Median change of the fields ``[X, Y, Z, K]`` from a cell to its neighbour across their
    zero sets (where the sign changes along an axis): one cell for signed distances, the
    attenuation's jump per cell for threshold fields. 0 when no field changes sign."""
    e = np.asarray(fields, dtype=np.float32)
    steps = []
    for axis in range(3):
        a = np.moveaxis(e, axis, 0)
        lo, hi = a[:-1], a[1:]
        cross = (lo < 0) != (hi < 0)
        steps.append(np.abs(hi - lo)[cross])
    allsteps = np.concatenate(steps) if steps else np.zeros(0)
    return float(np.median(allsteps)) if allsteps.size else 0.0


def relabel_fields(fields: np.ndarray, labels: np.ndarray, relabelled: np.ndarray, margin: float | None = None) -> np.ndarray:
    """Visible-region fields ``[X, Y, Z, K]`` (negative where material k is the label) made to
    agree with ``relabelled``: where a cell moved from ``k`` to ``j``, ``e_k >= margin`` and
    ``e_j <= -margin`` (``j = 0``, air: no field goes negative). Other cells are unchanged.
    ``margin`` defaults to half the fields' :func:`field_step`: a moved cell's centre lies half a
    cell inside its new region, as an unmoved cell's does."""
    e = np.array(fields, dtype=np.float32, copy=True)
    moved = np.asarray(labels) != np.asarray(relabelled)
    if not moved.any():
        return e
    if margin is None:
        margin = 0.5 * field_step(e)
    margin = max(float(margin), 1e-6)
    idx = np.nonzero(moved)
    old = np.asarray(labels)[idx].astype(np.int64)
    new = np.asarray(relabelled)[idx].astype(np.int64)
    cells = e[idx]  # [n, K]
    rows = np.arange(len(old))
    src = old > 0
    cells[rows[src], old[src] - 1] = np.maximum(cells[rows[src], old[src] - 1], margin)
    dst = new > 0
    cells[rows[dst], new[dst] - 1] = np.minimum(cells[rows[dst], new[dst] - 1], -margin)
    e[idx] = cells
    return e


def shell_counts(labels: np.ndarray, relabelled: np.ndarray) -> dict[int, int]:
    """Cells moved out of each material ``{k: n}`` (only materials that lost cells)."""
    moved = np.asarray(labels) != np.asarray(relabelled)
    ks, n = np.unique(np.asarray(labels)[moved], return_counts=True)
    return {int(k): int(c) for k, c in zip(ks, n)}
