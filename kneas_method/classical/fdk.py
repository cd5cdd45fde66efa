"""Feldkamp–Davis–Kress (FDK) cone-beam reconstruction, and FBP for parallel beam.

The classical analytic baseline, in torch (CPU or CUDA), for the SPEC §1
geometry (:class:`~kneas_method.geometry.Geometry`).

Algorithm (Kak & Slaney ch. 3; Feldkamp et al. 1984), in model units:

1. **Cosine (Feldkamp) weight.** Each detector pixel ``(u, v)`` (detector
   coordinates of :meth:`Geometry.detector_uv`) is multiplied by
   ``DSD / sqrt(DSD² + u² + v²)``, which equals ``DSO / sqrt(DSO² + u'² + v'²)``
   with ``u' = u·DSO/DSD``, ``v' = v·DSO/DSD`` the coordinates scaled to the
   isocentre (virtual detector through the rotation axis).
2. **Redundancy / angular weight** ``w(β, γ)·Δβ``. ``Δβ`` is the angular width
   each view stands for (half-way to its neighbours). A line is measured by the
   ray ``(β, γ)`` (``γ = atan(u/DSD)`` the fan angle) and by its conjugate
   ``(β + π − 2γ, −γ)``. The weight is ``w = c(β) / Σ c(β_o)``, the sum running
   over every occurrence ``β_o`` of the same line inside the scanned arc, where
   ``c`` is 1 in the arc's interior and tapers as ``sin²`` to 0 at its ends
   (taper length ``max(2γ_max, scan − π)``, at most a quarter of the arc).
   Hence the weights of every measured line add up to exactly 1, smoothly
   (this reduces to ``w = 1/2`` for a full 360° scan and is a Parker-type
   weighting for a short scan ``π + 2γ_max``). For a scan shorter than that —
   the NAF scenes cover 180° — lines with no conjugate keep weight 1, so each
   measured line counts once and the scale of the result stays right; lines
   never measured cannot be recovered and give the usual limited-angle
   artefacts off-centre. Parallel beam: conjugate ``(β + π, −u)``, i.e. ``γ = 0``.
   An offset cone-beam detector (``offU`` not 0: a half-fan scan) sees a conjugate only where
   ``−γ`` is on it; each occurrence also counts as :func:`column_presence` says, a ``sin²`` taper
   from the detector's shorter edge across the part seen on both sides of the centre, so that
   the weights fall smoothly to 0 at that edge before the ramp filter (Wang's weighting); the
   weighted rows are padded with zeros to a centred detector before filtering, since the ramp
   filter spreads them beyond the shorter edge, where the backprojection reads them.
3. **Ramp filter** along detector rows ``u``, using the discrete spatial ramp
   kernel (``h(0) = 1/(4τ²)``, ``h(n odd) = −1/(π² n² τ²)``, ``τ`` the pixel
   pitch on the virtual detector, ``dU·DSO/DSD``), zero-padded to at least
   twice the row length and applied by FFT, optionally apodised by a
   Shepp–Logan, cosine or Hann window.
4. **Backprojection** (voxel-driven): for voxel ``x`` and view ``θ`` the depth
   along the central ray is ``λ = DSO − (x cos θ + y sin θ)``; it projects to
   ``u = DSD (−x sin θ + y cos θ)/λ``, ``v = −DSD z/λ``, read bilinearly from the
   filtered view and weighted by ``(DSO/λ)²``.

Units: a projection value is ``∫ mu_data dl`` with ``l`` in metres, which equals
``∫ mu_model dl_model``; filtering and backprojecting in model units gives
``mu_model`` and the result is returned in **data units** (1/m):
``mu_data = mu_model · geometry.scale``.
"""

from __future__ import annotations

import math
from typing import Optional

import numpy as np
import torch
import torch.nn.functional as F

from ..device import resolve_device
from ..errors import ConfigError, KneasError
from ..geometry import Geometry

__all__ = ["fdk_reconstruct", "ramp_filter", "redundancy_weights", "column_presence", "angular_widths", "FILTERS"]

FILTERS = ("ram-lak", "shepp-logan", "cosine", "hann")


# -------------------------------------------------------------------- filter
def _ramp_response(n: int, window: str, device, dtype=torch.float64) -> tuple[torch.Tensor, int]:
    """Frequency response (real, length ``P``) of the discrete ramp kernel times the window,
    for rows of ``n`` samples zero-padded to ``P = next pow2 >= 2n``; unit pixel pitch."""
    if window not in FILTERS:
        raise ConfigError(f"FDK filter {window!r} is not known; choose one of {', '.join(FILTERS)}")
    size = 1 << max(6, int(math.ceil(math.log2(2 * n))))
    k = torch.arange(size, device=device, dtype=dtype)
    k = torch.where(k <= size // 2, k, k - size)  # signed circular index
    h = torch.zeros(size, device=device, dtype=dtype)
    h[0] = 0.25
    odd = (k.abs() % 2) == 1
    h[odd] = -1.0 / (math.pi**2 * k[odd] ** 2)
    resp = torch.fft.fft(h).real
    f = torch.fft.fftfreq(size, device=device, dtype=dtype)  # cycles / sample in [-0.5, 0.5)
    if window == "shepp-logan":
        resp = resp * torch.sinc(f)
    elif window == "cosine":
        resp = resp * torch.cos(math.pi * f)
    elif window == "hann":
        resp = resp * 0.5 * (1 + torch.cos(2 * math.pi * f))
    return resp, size


def ramp_filter(rows: torch.Tensor, pitch: float, window: str = "ram-lak") -> torch.Tensor:
    """Ramp-filter along the last axis: ``rows [..., n]`` sampled at ``pitch``
    (length unit L) -> ``[..., n]`` in (input unit)/L, i.e. the convolution
    ``pitch · Σ_k h((n−k)·pitch) rows[k]`` with the discrete ramp kernel ``h``."""
    n = rows.shape[-1]
    resp, size = _ramp_response(n, window, rows.device)
    spec = torch.fft.rfft(rows.to(torch.float64), n=size, dim=-1) * resp[: size // 2 + 1]
    return (torch.fft.irfft(spec, n=size, dim=-1)[..., :n] / pitch).to(rows.dtype)


# ------------------------------------------------------------------- weights
def angular_widths(angles: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Angular width each view stands for.

    Args:
        angles: ``[N]`` radians, any order.

    Returns:
        ``(widths [N] rad, arc_start rad, arc_length rad)``: a view's width is half
        the distance to each neighbour (the full spacing at the ends); the arc is
        ``[first − w_first/2, last + w_last/2]`` in sorted order.
    """
    a = np.asarray(angles, dtype=np.float64).reshape(-1)
    n = len(a)
    if n == 0:
        raise KneasError("FDK needs at least one projection; pass a scene or views with projections")
    if n == 1:
        return np.array([math.pi]), float(a[0] - math.pi / 2), math.pi
    order = np.argsort(a)
    s = a[order]
    d = np.diff(s)
    if np.any(d <= 0):
        raise KneasError("FDK got two projections at the same angle; remove duplicate views")
    w = np.empty(n)
    w[1:-1] = 0.5 * (d[:-1] + d[1:])
    w[0], w[-1] = d[0], d[-1]
    start = s[0] - w[0] / 2
    length = float(s[-1] - s[0] + w[0] / 2 + w[-1] / 2)
    out = np.empty(n)
    out[order] = w
    return out, float(start), length


def column_presence(gammas, fan: tuple[float, float]) -> np.ndarray:
    """How much a ray at fan angle ``gammas`` [...] counts on a detector spanning the fan angles
    ``fan = (lo, hi)`` (rad, its edges): 0 off the detector; on an offset detector, whose shorter
    side ends at ``lo < 0 < hi``, a ``sin²`` taper over ``2 min(-lo, hi)`` from each edge, so that a
    line seen on both sides of the centre (``|γ| < min(-lo, hi)``) is shared smoothly between its
    two rays (Wang's weighting) and one seen once counts once; no taper where the detector does not
    cross the centre. A symmetric detector gives every ray and its conjugate the same value."""
    g = np.asarray(gammas, dtype=np.float64)
    lo, hi = fan
    inside = ((g >= lo) & (g <= hi)).astype(np.float64)
    if not lo < 0.0 < hi:
        return inside
    width = 2.0 * min(-lo, hi)
    t_lo, t_hi = np.clip((g - lo) / width, 0.0, 1.0), np.clip((hi - g) / width, 0.0, 1.0)
    return inside * np.sin(0.5 * math.pi * t_lo) ** 2 * np.sin(0.5 * math.pi * t_hi) ** 2


def redundancy_weights(angles: np.ndarray, gammas: np.ndarray, gamma_max: float,
                       arc: Optional[tuple[float, float]] = None, fan: Optional[tuple[float, float]] = None) -> np.ndarray:
    """Normalised redundancy weights ``w [N, G]`` (see module docstring, step 2).

    Args:
        angles: ``[N]`` view angles (rad).
        gammas: ``[G]`` fan angles of the detector columns (rad); zeros for parallel beam.
        gamma_max: largest fan half-angle (rad), sets the taper length.
        arc: ``(start, length)`` of the scanned arc (rad); default from
            :func:`angular_widths` of ``angles``.
        fan: ``(lo, hi)``, the fan angles of the detector's edges where it is offset (not symmetric
            about the central ray): a conjugate ray counts as :func:`column_presence` says, so a
            line whose conjugate falls off the detector keeps weight 1. None: every conjugate is
            on the detector (a centred one).
    """
    a = np.asarray(angles, dtype=np.float64).reshape(-1, 1)
    g = np.asarray(gammas, dtype=np.float64).reshape(1, -1)
    if arc is None:
        _, start, arc = angular_widths(angles)
    else:
        start, arc = float(arc[0]), float(arc[1])
    two_pi = 2 * math.pi
    if arc >= two_pi * (1 - 1e-9):
        taper = 0.0  # full (or over-) scan: no taper, occurrences are simply counted
    else:
        taper = min(max(2 * gamma_max, arc - math.pi), arc / 4)

    def c(beta):
        r = np.mod(beta - start, two_pi)
        inside = r < arc
        if taper > 0:
            t = np.clip(np.minimum(r, arc - r) / taper, 0.0, 1.0)
            val = np.sin(0.5 * math.pi * t) ** 2
        else:
            val = np.ones_like(r)
        return np.where(inside, val, 0.0)

    own = c(a + 0 * g)
    total = np.zeros_like(own)
    n_wrap = int(math.ceil(arc / two_pi)) + 1
    presence = (None, None) if fan is None else (column_presence(g, fan), column_presence(-g, fan))
    for base, e in zip((a + 0 * g, a + math.pi - 2 * g), presence):
        r0 = np.mod(base - start, two_pi)
        for m in range(n_wrap):
            r = r0 + m * two_pi
            counted = np.where(r < arc, c(start + r), 0.0) if taper > 0 else (r < arc).astype(np.float64)
            total += counted if e is None else counted * e
    if taper == 0.0:
        own = np.ones_like(own)
    if fan is not None:
        own = own * presence[0]
    return np.where(total > 0, own / np.maximum(total, 1e-30), 1.0)


# -------------------------------------------------------------- reconstruct
def _resolve_inputs(source, angles, projections):
    from ..data.scene import Scene, Views

    if isinstance(source, Scene):
        geometry = source.geometry
        views = angles if isinstance(angles, Views) else source.train
        if angles is not None and not isinstance(angles, Views):
            views = Views(np.asarray(angles), np.asarray(projections))
        angles, projections = views.angles, views.projections
    elif isinstance(source, Geometry):
        geometry = source
        if isinstance(angles, Views):
            angles, projections = angles.angles, angles.projections
        if angles is None or projections is None:
            raise KneasError("fdk_reconstruct(geometry, ...) needs angles and projections (or a Views); or pass a Scene")
    else:
        raise KneasError(f"fdk_reconstruct expects a Scene or a Geometry, got {type(source).__name__}")
    return geometry, angles, projections


def fdk_reconstruct(
    source,
    angles=None,
    projections=None,
    *,
    filter: str = "ram-lak",
    device: str | torch.device = "cpu",
    chunk: int = 1 << 22,
    redundancy: bool = True,
    return_tensor: bool = False,
) -> np.ndarray | torch.Tensor:
    """FDK (cone) / FBP (parallel) reconstruction on the geometry's voxel grid.

    Args:
        source: a :class:`~kneas_method.data.scene.Scene` (its training views are
            used unless ``angles`` is a ``Views``) or a :class:`Geometry`.
        angles: ``[N]`` view angles (rad), or a ``Views``; needed with a Geometry.
        projections: ``[N, nV, nU]`` line integrals ``∫ mu_data dl`` (l in m),
            numpy or torch, indexed ``[view, j (row, v), i (column, u)]``.
        filter: ``"ram-lak"`` (plain ramp), ``"shepp-logan"``, ``"cosine"`` or ``"hann"``.
        device: torch device for the work (``"cpu"``, ``"cuda"``).
        chunk: largest number of voxel samples (voxels × views) processed at
            once; lower it to save memory.
        redundancy: apply the redundancy weights of step 2 (default). ``False``
            uses the plain full-scan factor 1/2, which is right only for 360°.

    Returns:
        ``[nx, ny, nz]`` float32 attenuation in data units (1/m), numpy (or a
        torch tensor on ``device`` with ``return_tensor=True``).
    """
    geometry, angles, projections = _resolve_inputs(source, angles, projections)
    dev = resolve_device(device)
    ang = np.asarray(angles.detach().cpu() if hasattr(angles, "detach") else angles, dtype=np.float64).reshape(-1)
    proj = torch.as_tensor(projections, dtype=torch.float32).to(dev)
    nu, nv = geometry.n_detector
    if proj.ndim != 3 or proj.shape[0] != len(ang) or tuple(proj.shape[1:]) != (nv, nu):
        raise KneasError(f"projections have shape {tuple(proj.shape)} but {len(ang)} angles and a {nv}x{nu} (nV x nU) detector "
                         "need [N, nV, nU]; check the scene's nDetector order")
    if not torch.isfinite(proj).all():
        raise KneasError("projections contain NaN or infinite values; clean the data before reconstructing")
    cone = geometry.mode == "cone"
    (du, dv), (ou, ov) = geometry.d_detector, geometry.off_detector
    dsd, dso = geometry.dsd, geometry.dso

    # 1. cosine weights, 2. redundancy x angular width
    u, v = geometry.detector_uv(device=dev, dtype=torch.float64)  # [nV, nU]
    if cone:
        proj = proj * (dsd / torch.sqrt(dsd**2 + u**2 + v**2)).to(proj.dtype)
        gam = np.arctan(u[0].cpu().numpy() / dsd)
        fan = (float(np.arctan((-nu / 2 * du + ou) / dsd)), float(np.arctan((nu / 2 * du + ou) / dsd)))
        gmax = max(abs(fan[0]), abs(fan[1]))
        if abs(fan[0] + fan[1]) <= 1e-9 * (fan[1] - fan[0]):
            fan = None  # centred: every conjugate ray is on the detector
    else:
        gam, gmax, fan = np.zeros(1), 0.0, None
    widths, _, _ = angular_widths(ang)
    if redundancy:
        w = redundancy_weights(ang, gam, gmax, fan=fan)  # [N, nU] or [N, 1]
    else:
        w = np.full((len(ang), 1), 0.5)
    w = torch.as_tensor(w * widths[:, None], dtype=proj.dtype, device=dev)
    proj = proj * w[:, None, :]

    if fan is not None:  # an offset detector: rows padded with zeros to a centred one, so that the filtered rows reach
        # the mirror of the shorter side, as a centred detector's rows whose weights are 0 there would
        extra = int(math.ceil(2.0 * abs(ou) / du - 1e-6))
        proj = F.pad(proj, (extra, 0) if ou > 0 else (0, extra))
        ou, nu = ou - math.copysign(extra * du / 2, ou), nu + extra

    # 3. ramp filter on the virtual detector at the isocentre
    pitch = du * dso / dsd if cone else du
    q = ramp_filter(proj, pitch, filter)  # [N, nV, nU]

    # 4. backprojection
    xs, ys, zs = geometry.voxel_axes(device=dev, dtype=torch.float32)
    nx, ny, nz = len(xs), len(ys), len(zs)
    X = xs[:, None].expand(nx, ny).reshape(-1)  # [nx*ny]
    Y = ys[None, :].expand(nx, ny).reshape(-1)
    cos = torch.as_tensor(np.cos(ang), dtype=torch.float32, device=dev)
    sin = torch.as_tensor(np.sin(ang), dtype=torch.float32, device=dev)
    vol = torch.zeros(nx * ny, nz, dtype=torch.float32, device=dev)
    n_views = len(ang)
    cols = max(1, min(nx * ny, chunk // max(1, nz)))  # xy columns per chunk (one view)
    views_per = max(1, min(n_views, chunk // max(1, cols * nz)))
    scale_i, scale_j = 2.0 / max(nu - 1, 1), 2.0 / max(nv - 1, 1)
    for c0 in range(0, nx * ny, cols):
        xc, yc = X[c0:c0 + cols], Y[c0:c0 + cols]
        acc = torch.zeros(len(xc), nz, dtype=torch.float32, device=dev)
        for b0 in range(0, n_views, views_per):
            cb, sb = cos[b0:b0 + views_per, None], sin[b0:b0 + views_per, None]  # [B,1]
            s_perp = -xc[None] * sb + yc[None] * cb  # [B, C]
            if cone:
                lam = dso - (xc[None] * cb + yc[None] * sb)  # [B, C] depth along the central ray
                mag = dsd / lam
                ud = s_perp * mag
                vd = -zs[None, None, :] * mag[..., None]  # [B, C, nz]
                weight = (dso / lam) ** 2
            else:
                ud = s_perp
                vd = (-zs)[None, None, :].expand(len(cb), len(xc), nz)
                weight = None
            fi = (ud - ou) / du + nu / 2 - 0.5  # [B, C] column index
            fj = (vd - ov) / dv + nv / 2 - 0.5  # [B, C, nz] row index
            gx = (fi * scale_i - 1.0)[..., None].expand_as(fj) if nu > 1 else torch.zeros_like(fj)
            gy = fj * scale_j - 1.0 if nv > 1 else torch.zeros_like(fj)
            grid = torch.stack([gx, gy], -1)  # [B, C, nz, 2]
            sampled = F.grid_sample(q[b0:b0 + views_per, None], grid, mode="bilinear", padding_mode="zeros",
                                    align_corners=True)[:, 0]  # [B, C, nz]
            if weight is not None:
                sampled = sampled * weight[..., None]
            acc += sampled.sum(0)
        vol[c0:c0 + cols] = acc
    vol = (vol * geometry.scale).reshape(nx, ny, nz)
    return vol if return_tensor else vol.cpu().numpy().astype(np.float32)
