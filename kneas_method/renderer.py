"""Beer–Lambert renderer (SPEC §3) as small pure functions.

``I = exp(−Σ_n mu(x_n) · δ_n)`` with ``δ_n = (t_{n+1} − t_n) · ‖d‖`` and the
last ``δ = 0``. Ray parameters ``t`` and directions ``d`` are in model units;
attenuation ``mu`` is in data units (1/m), so lengths are converted to metres
with ``δ_m = δ_model / scale`` (``scale`` = model units per metre, from the
geometry). The line integral then equals the data projection value ``p``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class RenderOutput:
    """Rendered rays.

    Attributes:
        intensity: [R] ``exp(−line_integral)``.
        line_integral: [R] ``Σ mu·δ`` (unit-free; compare with projections ``p``).
    """

    intensity: torch.Tensor
    line_integral: torch.Tensor


def sample_points(origins: torch.Tensor, directions: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Points [R, S, 3] = origins [R, 3] + t [R, S] · directions [R, 3] (model units)."""
    return origins[:, None, :] + t[..., None] * directions[:, None, :]


def segment_lengths(t: torch.Tensor, directions: torch.Tensor, scale: float = 1.0) -> torch.Tensor:
    """``δ`` [R, S] in metres: ``(t_{n+1} − t_n)·‖d‖ / scale``, last entry 0."""
    dt = torch.cat([t[:, 1:] - t[:, :-1], torch.zeros_like(t[:, :1])], dim=-1)
    return dt * directions.norm(dim=-1, keepdim=True) / scale


def beer_lambert(mu: torch.Tensor, delta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """mu [R, S] (1/m), delta [R, S] (m) -> (intensity [R], line_integral [R])."""
    line = (mu * delta).sum(-1)
    return torch.exp(-line), line


def voxel_plane_samples(origins: torch.Tensor, directions: torch.Tensor, near: torch.Tensor, far: torch.Tensor,
                        lo: torch.Tensor, hi: torch.Tensor, counts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Joseph's quadrature on a voxel grid: one sample where a ray crosses each voxel-centre
    plane of its **dominant axis** (the axis ``a`` with the largest ``|d_a| / voxel_a``), for
    the planes with ``near <= t <= far``; each sample stands for the ray length between two
    planes, ``voxel_a · |d| / |d_a|``. A field equal to the trilinear interpolation of a voxel
    volume then integrates to exactly that volume's Joseph projection (the classical projector
    of :mod:`kneas_method.classical.projector`), and the samples lie where the volume's voxel
    centres are compared with the truth.

    Args:
        origins, directions: [R, 3] rays (model units; directions unnormalised).
        near, far: [R] ray-parameter range to sample (e.g. the visual-hull stretch).
        lo, hi: [3] the voxel box (model units); counts: [3] voxels per axis (int).

    Returns ``(ray [P] long, t [P], length [R])``: the ray of each sample (rays in order, each
    ray's samples ascending along its axis), its ray parameter, and the length per sample of
    each ray (model units). Rays crossing no plane in range get no sample.
    """
    R = origins.shape[0]
    dtype = origins.dtype
    counts_f = counts.to(dtype)
    vox = (hi.to(dtype) - lo.to(dtype)) / counts_f
    first = lo.to(dtype) + vox / 2
    axis = (directions.abs() / vox).argmax(-1, keepdim=True)  # [R, 1]
    oa, da = origins.gather(1, axis)[:, 0], directions.gather(1, axis)[:, 0]
    fa, va, na = first[axis[:, 0]], vox[axis[:, 0]], counts[axis[:, 0]]
    s0, s1 = (oa + near * da - fa) / va, (oa + far * da - fa) / va  # plane index at near / far
    k_lo = torch.clamp(torch.ceil(torch.minimum(s0, s1)), min=0).long()
    k_hi = torch.minimum(torch.floor(torch.maximum(s0, s1)).long(), na - 1)
    n = torch.clamp(k_hi - k_lo + 1, min=0)
    ray = torch.repeat_interleave(torch.arange(R, device=origins.device), n)
    start = torch.cumsum(n, 0) - n
    k = k_lo[ray] + torch.arange(ray.numel(), device=origins.device) - start[ray]
    t = (fa[ray] + k.to(dtype) * va[ray] - oa[ray]) / da[ray]
    length = va * directions.norm(dim=-1) / da.abs()
    return ray, t, length


def integrate_samples(mu: torch.Tensor, ray: torch.Tensor, delta: torch.Tensor, n_rays: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Ragged Beer–Lambert: mu [P] (1/m) at samples of rays ``ray`` [P], each standing for
    ``delta`` [P] metres -> (intensity [R], line_integral [R]); rays with no sample give 1 and 0."""
    line = torch.zeros(n_rays, device=mu.device, dtype=mu.dtype).index_add(0, ray, mu * delta)
    return torch.exp(-line), line
