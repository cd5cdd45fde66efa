"""Matched forward / back projector pair (Joseph's method), torch, CPU and CUDA.

Model
-----
``A`` maps a volume ``x`` [nx, ny, nz] (attenuation in data units, 1/m, with
``x[a, b, c]`` at the voxel centre ``(x_a, y_b, z_c)`` of
:meth:`Geometry.voxel_axes`) to line integrals ``A x`` [N, nV, nU] along the
SPEC §1 rays of :meth:`Geometry.rays` (cone or parallel beam, detector and
volume offsets included), in the units of a scene's projections
(``∫ mu_data dl`` with ``l`` in metres).

Joseph (1982): every ray picks its **dominant axis** ``a`` (the one it crosses
the most voxel slices of, largest ``|d_a| / voxel_a``) and takes one sample
where it crosses each voxel-centre plane of that axis; the sample is the
bilinear interpolation of that slice in the other two axes (zero outside the
volume, so the value fades to 0 over the half voxel beyond the box), weighted
by the ray length per slice, ``voxel_a · |d| / |d_a|`` (metres). A volume of
ones therefore integrates to exactly the box length along the dominant axis.

Each ray is clipped to the box (grown by the half voxel the interpolation
reaches): rays that miss it are skipped, and the others are sampled only on the
blocks of ``BLOCK`` slices that their chord overlaps (the samples skipped
this way are exactly zero, so clipping changes no value).

``back`` is the exact adjoint ``Aᵀ``: the same bilinear weights, transposed
(scatter-added by ``grid_sampler_2d_backward``), so ``⟨A x, y⟩ = ⟨x, Aᵀ y⟩``
to rounding. The slices of the dominant axis are the batch dimension of a 2-D
``grid_sample``, which keeps both directions parallel over slices on CPU.

Inputs may be numpy arrays or torch tensors; outputs are of the same kind
(numpy float32 / float64, or a tensor on the work device). Work is done in
float64 when the input is float64, otherwise float32.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from ..device import resolve_device
from ..errors import KneasError
from ..geometry import Geometry

__all__ = ["Projector", "VoxelBackprojector", "forward", "back", "check_volume", "check_projections"]

# Samples (rays x slices) per grid_sample call: bounds the grid to ~64 MB in float32.
MAX_SAMPLES = 1 << 23
# Slices per block: the slices of the dominant axis are cut in blocks of this many and a
# ray is sampled on the blocks its chord overlaps (each block's adjoint fills its own slab).
BLOCK = 16
# Cached ray tables of at most this many bytes are kept between calls (50 views of a 256^2
# detector on a 128^3 grid need 327 MB: with all of them kept a projection and its adjoint take
# 2.9 s instead of 3.4 s on 2 cores).
CACHE_BYTES = 512 << 20

# transverse axes (b, c) for each dominant axis a: the slice of axis a is indexed [b, c]
_TRANSVERSE = {0: (1, 2), 1: (0, 2), 2: (0, 1)}


# ---------------------------------------------------------------- checks
def _work_dtype(x) -> torch.dtype:
    dt = x.dtype if isinstance(x, (torch.Tensor, np.ndarray)) else None
    return torch.float64 if dt in (torch.float64, np.float64, np.dtype("float64")) else torch.float32


def check_volume(volume, geometry: Geometry, *, device=None, dtype=None) -> torch.Tensor:
    """``volume`` [nx, ny, nz] (numpy or torch) as a finite tensor on ``device``; one-line error otherwise."""
    vol = volume if isinstance(volume, torch.Tensor) else torch.as_tensor(np.asarray(volume))
    if tuple(vol.shape) != tuple(geometry.n_voxel):
        raise KneasError(f"volume has shape {tuple(vol.shape)} but the geometry's nVoxel is {tuple(geometry.n_voxel)}; "
                         "pass a [nx, ny, nz] volume on the scene's grid")
    vol = vol.to(device=device, dtype=dtype or _work_dtype(volume))
    if not torch.isfinite(vol).all():
        raise KneasError("volume contains NaN or infinite values; clean it before projecting")
    return vol


def check_projections(projections, geometry: Geometry, n_views: int, *, device=None, dtype=None) -> torch.Tensor:
    """``projections`` [N, nV, nU] (numpy or torch) as a finite tensor on ``device``; one-line error otherwise."""
    proj = projections if isinstance(projections, torch.Tensor) else torch.as_tensor(np.asarray(projections))
    nu, nv = geometry.n_detector
    if proj.ndim != 3 or proj.shape[0] != n_views or tuple(proj.shape[1:]) != (nv, nu):
        raise KneasError(f"projections have shape {tuple(proj.shape)} but {n_views} angles and a {nv}x{nu} (nV x nU) "
                         "detector need [N, nV, nU]; pass one projection per angle, indexed [view, row, column]")
    proj = proj.to(device=device, dtype=dtype or _work_dtype(projections))
    if not torch.isfinite(proj).all():
        raise KneasError("projections contain NaN or infinite values; clean the data before reconstructing")
    return proj


def _angles(angles) -> np.ndarray:
    a = np.asarray(angles.detach().cpu() if isinstance(angles, torch.Tensor) else angles, dtype=np.float64).reshape(-1)
    if a.size == 0:
        raise KneasError("no view angles given; pass at least one angle (radians)")
    if not np.all(np.isfinite(a)):
        raise KneasError("view angles contain NaN or infinite values; pass finite angles in radians")
    return a


# ------------------------------------------------------------ ray tables
@dataclass
class _RayBlock:
    """Rays of a view chunk with dominant axis ``axis`` whose chord overlaps the slice block ``lo..hi-1``.

    Attributes:
        axis: dominant axis (0, 1, 2 = x, y, z).
        lo, hi: slice range (``hi`` exclusive).
        index: [R] flat index into the chunk's [n_views * nV * nU] projections.
        start: [R, 2] grid_sample coordinates (c, b) of the ray at slice ``lo``.
        step: [R, 2] change of those coordinates per slice.
        weight: [R] ray length per slice [metres].
    """

    axis: int
    lo: int
    hi: int
    index: torch.Tensor
    start: torch.Tensor
    step: torch.Tensor
    weight: torch.Tensor

    @property
    def nbytes(self) -> int:
        return sum(t.numel() * t.element_size() for t in (self.index, self.start, self.step, self.weight))

    def grid(self) -> torch.Tensor:
        """Sample coordinates [hi - lo, R, 1, 2] for ``grid_sample`` (align_corners=False)."""
        k = torch.arange(self.hi - self.lo, device=self.start.device, dtype=self.start.dtype)
        return torch.addcmul(self.start[None], k[:, None, None], self.step[None])[:, :, None, :]


def _clip_to_box(o: torch.Tensor, d: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Ray parameters ``(t_in, t_out)`` [R] of rays ``o + t d`` ([R, 3] each) in the box ``lo..hi`` [3],
    ``t >= 0``; ``t_out <= t_in`` for a ray that misses."""
    moving = d != 0
    safe = torch.where(moving, d, torch.ones_like(d))
    ta, tb = (lo - o) / safe, (hi - o) / safe
    inside = (o >= lo) & (o <= hi)
    inf = torch.full_like(ta, math.inf)
    t_min = torch.where(moving, torch.minimum(ta, tb), torch.where(inside, -inf, inf))
    t_max = torch.where(moving, torch.maximum(ta, tb), torch.where(inside, inf, -inf))
    return t_min.amax(-1).clamp_min(0.0), t_max.amin(-1)


def _ray_blocks(geometry: Geometry, angles: np.ndarray, device, dtype, block: int = BLOCK) -> list[_RayBlock]:
    """Joseph ray tables for the views ``angles`` [V] (one chunk), one per (dominant axis, slice block):
    see :class:`_RayBlock`. Rays missing the box (grown by half a voxel) are left out."""
    origins, dirs = geometry.rays(angles, device=device, dtype=torch.float64)
    o, d = origins.reshape(-1, 3), dirs.reshape(-1, 3)
    n = torch.tensor(geometry.n_voxel, device=device, dtype=torch.float64)
    vox = torch.tensor(geometry.d_voxel, device=device, dtype=torch.float64)
    centre = torch.tensor(geometry.off_origin, device=device, dtype=torch.float64)
    box_lo = centre - n * vox / 2
    t_in, t_out = _clip_to_box(o, d, box_lo - vox / 2, box_lo + n * vox + vox / 2)
    hit = t_out > t_in
    axis = (d.abs() / vox).argmax(-1)
    first = box_lo + vox / 2  # first voxel centre per axis
    out: list[_RayBlock] = []
    for a in range(3):
        idx = torch.nonzero(hit & (axis == a)).reshape(-1)
        if idx.numel() == 0:
            continue
        b, c = _TRANSVERSE[a]
        oa, da = o[idx, a], d[idx, a]
        # slice range each ray crosses (its box chord, in slice-index units of axis a)
        s_in, s_out = (oa + t_in[idx] * da - first[a]) / vox[a], (oa + t_out[idx] * da - first[a]) / vox[a]
        k_lo = torch.minimum(s_in, s_out).ceil().clamp(0, geometry.n_voxel[a] - 1).long()
        k_hi = torch.maximum(s_in, s_out).floor().clamp(0, geometry.n_voxel[a] - 1).long() + 1
        keep = k_hi > k_lo  # a ray between two slice planes, crossing none, integrates to 0
        idx, oa, da, k_lo, k_hi = idx[keep], oa[keep], da[keep], k_lo[keep], k_hi[keep]
        if idx.numel() == 0:
            continue
        # grid coordinates (c -> W, b -> H), affine in the slice position: g = A + B * x_a
        coeff_a, coeff_b = [], []
        for ax in (c, b):
            slope = d[idx, ax] / da  # d(position_ax) / d(position_a)
            base = o[idx, ax] - oa * slope
            coeff_a.append(2 * (base - box_lo[ax]) / (n[ax] * vox[ax]) - 1)
            coeff_b.append(2 * slope / (n[ax] * vox[ax]))
        g0, gk = torch.stack(coeff_a, -1), torch.stack(coeff_b, -1)  # at x_a = 0, per unit x_a
        weight = (vox[a] * d[idx].norm(dim=-1) / da.abs() / geometry.scale).to(dtype)
        # slice blocks: each ray is sampled on the blocks its slice range overlaps
        n_a = geometry.n_voxel[a]
        for lo in range(0, n_a, block):
            hi = min(n_a, lo + block)
            sel = torch.nonzero((k_lo < hi) & (k_hi > lo)).reshape(-1)
            if sel.numel() == 0:
                continue
            x_lo = first[a] + lo * vox[a]
            out.append(_RayBlock(
                axis=a, lo=lo, hi=hi, index=idx[sel],
                start=(g0[sel] + x_lo * gk[sel]).to(dtype), step=(gk[sel] * vox[a]).to(dtype), weight=weight[sel],
            ))
    return out


def _split(table: _RayBlock, max_rays: int) -> list[_RayBlock]:
    """``table`` in pieces of at most ``max_rays`` rays."""
    if table.index.numel() <= max_rays:
        return [table]
    return [
        _RayBlock(table.axis, table.lo, table.hi, table.index[i:i + max_rays], table.start[i:i + max_rays],
                table.step[i:i + max_rays], table.weight[i:i + max_rays])
        for i in range(0, table.index.numel(), max_rays)
    ]


# -------------------------------------------------------------- projector
class Projector:
    """The matched pair ``A`` / ``Aᵀ`` for one geometry and one set of view angles.

    Args:
        geometry: the scan geometry (model units).
        angles: [N] view angles (radians).
        device: torch device for the work (default CPU).
        dtype: ``torch.float32`` (default) or ``torch.float64``.
        max_samples: ray samples per ``grid_sample`` call (memory bound, default 2^23).
        views_per_chunk: views whose rays are tabled together (default: as many as fit
            ``max_samples`` at one full detector per view).

    Ray tables are cached per chunk of views (up to ``CACHE_BYTES``, 512 MB), so repeated calls
    with the same ``views`` (as the iterative algorithms make) do not recompute them.
    """

    def __init__(self, geometry: Geometry, angles, *, device=None, dtype: torch.dtype = torch.float32,
                 max_samples: int = MAX_SAMPLES, views_per_chunk: Optional[int] = None):
        if dtype not in (torch.float32, torch.float64):
            raise KneasError(f"projector dtype {dtype} is not supported; use torch.float32 or torch.float64")
        self.geometry = geometry
        self.angles = _angles(angles)
        self.device = resolve_device(device)
        self.dtype = dtype
        self.max_samples = int(max_samples)
        if self.max_samples < 1:
            raise KneasError(f"max_samples is {max_samples}; it must be a positive number of samples per call")
        nu, nv = geometry.n_detector
        self.n_pixels = nu * nv
        per_view = self.n_pixels * max(geometry.n_voxel)
        self.views_per_chunk = int(views_per_chunk or max(1, self.max_samples // max(1, per_view)))
        self._cache: dict[tuple, list[_RayBlock]] = {}
        self._cache_bytes = 0

    @property
    def n_views(self) -> int:
        return len(self.angles)

    def _views(self, views) -> np.ndarray:
        if views is None:
            return np.arange(self.n_views)
        v = np.asarray(views, dtype=np.int64).reshape(-1)
        if v.size and (v.min() < 0 or v.max() >= self.n_views):
            raise KneasError(f"view index out of range 0..{self.n_views - 1}; pick views of this projector's angles")
        return v

    def _chunks(self, views: np.ndarray):
        """Yield ``(position, tables)``: consecutive pieces of ``views`` and their ray tables."""
        for s in range(0, len(views), self.views_per_chunk):
            chunk = views[s:s + self.views_per_chunk]
            key = tuple(int(i) for i in chunk)
            tables = self._cache.get(key)
            if tables is None:
                tables = _ray_blocks(self.geometry, self.angles[chunk], self.device, self.dtype)
                size = sum(w.nbytes for w in tables)
                if self._cache_bytes + size <= CACHE_BYTES:
                    self._cache[key] = tables
                    self._cache_bytes += size
            yield slice(s, s + len(chunk)), tables

    def _slices(self, volume: torch.Tensor, axis: int) -> torch.Tensor:
        """The volume as a batch of slices of ``axis``: [n_a, 1, n_b, n_c]."""
        b, c = _TRANSVERSE[axis]
        return volume.permute(axis, b, c).contiguous()[:, None]

    def forward(self, volume: torch.Tensor, views=None) -> torch.Tensor:
        """``A x``: volume [nx, ny, nz] (data units, on the device) -> [len(views), nV, nU] (metres · data units)."""
        views = self._views(views)
        nu, nv = self.geometry.n_detector
        volume = volume.to(self.dtype)
        slabs = [None, None, None]
        out = torch.zeros(len(views) * self.n_pixels, device=self.device, dtype=self.dtype)
        for pos, tables in self._chunks(views):
            base = pos.start * self.n_pixels
            for blk in tables:
                if slabs[blk.axis] is None:
                    slabs[blk.axis] = self._slices(volume, blk.axis)
                for part in _split(blk, max(1, self.max_samples // (blk.hi - blk.lo))):
                    s = F.grid_sample(slabs[blk.axis][part.lo:part.hi], part.grid(), mode="bilinear",
                                      padding_mode="zeros", align_corners=False)  # [k, 1, R, 1]
                    out.index_add_(0, base + part.index, s.sum(0).reshape(-1) * part.weight)
        return out.reshape(len(views), nv, nu)

    def back(self, projections: torch.Tensor, views=None) -> torch.Tensor:
        """``Aᵀ y``: projections [len(views), nV, nU] (or [C, len(views), nV, nU], C channels
        back-projected together at little extra cost) -> volume [nx, ny, nz] (or [C, nx, ny, nz])."""
        views = self._views(views)
        single = projections.ndim == 3
        y = (projections[None] if single else projections).to(self.dtype)
        n_ch = y.shape[0]
        y = y.reshape(n_ch, -1)
        shape = self.geometry.n_voxel
        acc = [None, None, None]
        for pos, tables in self._chunks(views):
            base = pos.start * self.n_pixels
            for blk in tables:
                a = blk.axis
                b, c = _TRANSVERSE[a]
                if acc[a] is None:
                    acc[a] = torch.zeros(shape[a], n_ch, shape[b], shape[c], device=self.device, dtype=self.dtype)
                for part in _split(blk, max(1, self.max_samples // (blk.hi - blk.lo))):
                    k = part.hi - part.lo
                    vals = y[:, base + part.index] * part.weight  # [C, R]
                    grad_out = vals[None, :, :, None].expand(k, n_ch, vals.shape[1], 1)
                    dummy = torch.zeros((), device=self.device, dtype=self.dtype).expand(k, n_ch, shape[b], shape[c])
                    g_in = torch.ops.aten.grid_sampler_2d_backward(grad_out, dummy, part.grid(), 0, 0, False,
                                                                   [True, False])[0]
                    acc[a][part.lo:part.hi] += g_in
        vol = torch.zeros(n_ch, *shape, device=self.device, dtype=self.dtype)
        for a in range(3):
            if acc[a] is not None:
                b, c = _TRANSVERSE[a]
                where = {a: 0, b: 2, c: 3}  # acc[a] is indexed (a, channel, b, c)
                vol += acc[a].permute(1, where[0], where[1], where[2])
        return vol[0] if single else vol


# ------------------------------------------------ voxel-driven back-projection
class VoxelBackprojector:
    """Voxel-driven back-projection: every voxel centre is projected onto each view and the
    view is read there by bilinear interpolation (zero off the detector), no distance weight.

    This is **not** the adjoint of :class:`Projector` (it is the unmatched back-projector
    that RTK's SART uses by default); it smooths each view's correction over the
    detector pixels around a voxel's projection, which avoids the ray-spacing pattern
    a ray-driven adjoint leaves when detector pixels are larger than the magnified
    voxels. The SART family offers it as ``backprojector="voxel"``.

    Args:
        geometry: the scan geometry; angles: [N] radians.
        device, dtype: work device and float dtype.
    """

    def __init__(self, geometry: Geometry, angles, *, device=None, dtype: torch.dtype = torch.float32):
        self.geometry = geometry
        self.angles = _angles(angles)
        self.device = resolve_device(device)
        self.dtype = dtype
        xs, ys, zs = geometry.voxel_axes(device=self.device, dtype=torch.float64)
        self._x = xs[:, None].expand(len(xs), len(ys)).reshape(-1)  # [nx*ny]
        self._y = ys[None, :].expand(len(xs), len(ys)).reshape(-1)
        self._z = zs  # [nz]

    def _grid(self, view: int) -> torch.Tensor:
        """Detector coordinates of every voxel centre for ``view``: [1, nx*ny, nz, 2] (align_corners=False)."""
        g = self.geometry
        ang = torch.tensor([self.angles[view]], dtype=torch.float64, device=self.device)
        rot, src = g.rotations(ang)[0], g.source_positions(ang)[0]  # [3, 3], [3]
        rel_x, rel_y = self._x - src[0], self._y - src[1]
        rel_z = self._z - src[2]
        (nu, nv), (du, dv), (ou, ov) = g.n_detector, g.d_detector, g.off_detector
        # R^T (p - t) per axis: a per-column part [nx*ny] plus a per-z part [nz]
        col = [rel_x * rot[0, k] + rel_y * rot[1, k] for k in range(3)]
        zpart = [rel_z * rot[2, k] for k in range(3)]
        if g.mode == "cone":
            if float(rot[2, 0].abs() + rot[2, 2].abs()) == 0.0:  # untilted: u and depth do not depend on z
                mag = g.dsd / col[2]  # [nx*ny]
                gx = (2 * (col[0] * mag - ou) / (nu * du)).to(self.dtype)[:, None].expand(-1, len(self._z))
                gy = torch.addcmul((col[1] * mag - ov).to(self.dtype)[:, None], (mag * 1.0).to(self.dtype)[:, None],
                                   zpart[1].to(self.dtype)[None, :]) * (2 / (nv * dv))
            else:
                depth = col[2][:, None] + zpart[2][None, :]
                gx = (2 * (g.dsd * (col[0][:, None] + zpart[0][None, :]) / depth - ou) / (nu * du)).to(self.dtype)
                gy = (2 * (g.dsd * (col[1][:, None] + zpart[1][None, :]) / depth - ov) / (nv * dv)).to(self.dtype)
        else:
            gx = (2 * (col[0][:, None] + zpart[0][None, :] - ou) / (nu * du)).to(self.dtype)
            gy = (2 * (col[1][:, None] + zpart[1][None, :] - ov) / (nv * dv)).to(self.dtype)
        return torch.stack([gx.expand_as(gy), gy], -1)[None]

    def back(self, projections: torch.Tensor, views=None) -> torch.Tensor:
        """Back-project [len(views), nV, nU] (or [C, len(views), nV, nU]) -> [nx, ny, nz] (or [C, nx, ny, nz])."""
        views = np.arange(len(self.angles)) if views is None else np.asarray(views, dtype=np.int64).reshape(-1)
        single = projections.ndim == 3
        y = (projections[None] if single else projections).to(self.dtype)
        n_ch = y.shape[0]
        nx, ny, nz = self.geometry.n_voxel
        vol = torch.zeros(n_ch, nx * ny, nz, device=self.device, dtype=self.dtype)
        for k, view in enumerate(views):
            vol += F.grid_sample(y[:, k][None], self._grid(int(view)), mode="bilinear", padding_mode="zeros",
                                 align_corners=False)[0]
        vol = vol.reshape(n_ch, nx, ny, nz)
        return vol[0] if single else vol


# ------------------------------------------------------- plain functions
def _to_kind(result: torch.Tensor, like):
    if isinstance(like, torch.Tensor):
        return result
    return result.cpu().numpy()


def forward(volume, geometry: Geometry, angles, *, device=None, max_samples: int = MAX_SAMPLES, progress=None):
    """Forward projection ``A x`` along every detector pixel's ray.

    Args:
        volume: [nx, ny, nz] attenuation in data units (1/m), numpy or torch, shape
            ``geometry.n_voxel``; ``volume[a, b, c]`` sits at voxel centre ``(x_a, y_b, z_c)``.
        geometry: the scan geometry (model units; cone or parallel beam).
        angles: [N] view angles (radians).
        device: torch device (default: the volume's, if a tensor, else CPU).
        max_samples: ray samples per batch (bounds memory).
        progress: optional ``progress(done_views, total_views)``, called after each chunk of views.

    Returns:
        [N, nV, nU] line integrals ``∫ mu_data dl`` (l in metres), numpy (float32, or
        float64 for a float64 volume) for a numpy volume, else a tensor on ``device``.
    """
    dev = resolve_device(device, volume)
    vol = check_volume(volume, geometry, device=dev)
    proj = Projector(geometry, angles, device=dev, dtype=vol.dtype, max_samples=max_samples)
    if progress is None:
        return _to_kind(proj.forward(vol), volume)
    parts, n = [], proj.n_views
    for s in range(0, n, proj.views_per_chunk):
        parts.append(proj.forward(vol, np.arange(s, min(n, s + proj.views_per_chunk))))
        progress(min(n, s + proj.views_per_chunk), n)
    return _to_kind(torch.cat(parts), volume)


def back(projections, geometry: Geometry, angles, *, device=None, max_samples: int = MAX_SAMPLES):
    """Back projection ``Aᵀ y``, the exact adjoint of :func:`forward`.

    Args:
        projections: [N, nV, nU] values per ray (numpy or torch), indexed ``[view, row j, column i]``.
        geometry: the scan geometry.
        angles: [N] view angles (radians).
        device: torch device (default: the projections', if a tensor, else CPU).
        max_samples: ray samples per batch (bounds memory).

    Returns:
        [nx, ny, nz] volume (same kind as ``projections``): each voxel gets
        ``Σ_rays y_ray · w_ray,voxel`` with the weights of :func:`forward`.
    """
    dev = resolve_device(device, projections)
    ang = _angles(angles)
    y = check_projections(projections, geometry, len(ang), device=dev)
    proj = Projector(geometry, ang, device=dev, dtype=y.dtype, max_samples=max_samples)
    return _to_kind(proj.back(y), projections)
