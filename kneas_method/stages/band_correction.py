"""Band correction: what the training views still say about a trained surface model's volume.

After training, the model's volume ``v`` (its attenuation at the voxel centres) still leaves a
residual on the training projections ``b``. Almost all of ``v``'s error lies in a thin band
around its edges (``benchmarks/visible_error.py`` measures it), and confined
to that band the views determine much of it. The correction is ``x``, from CGLS on
``(A M) x = r`` started at 0, with:

- ``A`` the Joseph projector of the scene grid (``classical.projector.Projector``);
- ``M`` the band: voxels within ``dilate`` voxels of a place where ``v``'s central-difference
  gradient exceeds ``gradient`` times ``v``'s 99.5th percentile per voxel, from ``v`` alone
  (:func:`edge_band`; relative, so the band is the same whatever the data's units), as
  weights, so ``x = M z`` with CGLS on ``(A M) z = r`` (column scaling: a voxel of weight ``w``
  moves as if its unknown were ``w`` times less free): by default 1 at the steep voxels
  themselves and ``ring`` on the rest of the band (its outer ring: ``ring`` 1 solves in the whole
  band alike, 0 at the steep voxels only); or (``weighting="gradient"``) the square root of
  ``v``'s gradient magnitude over its median on the steep voxels, at most 2
  (:func:`gradient_weights`: the correction goes where the edges are steepest);
- ``r = b - d - A v``, where ``d`` is the scene grid's **discretisation error**, the part of ``b``
  that no voxel volume on this grid reproduces: ``d = A_f w - A box(w)``, ``w`` the model's
  field on a grid ``fine`` times finer (in the band: its smooth fields, signed distances and
  per-material attenuations, queried on a grid ``coarse`` times finer and interpolated, then
  composed with the edges ``sharpen`` times sharper; the trilinear upsampling of ``v``
  elsewhere), ``A_f`` the projector there and ``box`` the mean over each voxel's ``fine^3``
  sub-voxels (:func:`discretisation_error`).

The iterations stop at ``iterations`` or earlier, by the **discrepancy principle**, once the
residual's mean square is within ``noise_factor`` times the data's noise variance, estimated from
the residual itself (:func:`noise_variance`): on a noisy scan the residual is mostly noise and
the correction stops before fitting it (at 0 iterations when it starts there; when ``b - A v`` is
already at the noise level, the discretisation error is not even computed).

The result is a voxel grid (data units, 0 outside the band); the run's correction stage
(:mod:`kneas_method.engine.correction_stage`) fits the model to ``v + x`` and repeats.

The pure functions take and return tensors; :func:`band_correction` ties them together.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Callable, Optional

import torch
import torch.nn.functional as F

from ..errors import KneasError

__all__ = ["grow", "gradient_magnitude", "edge_band", "gradient_weights", "box_mean", "noise_variance", "NOISE_FACTOR", "at_noise", "volume_at_noise", "band_cgls", "band_fields", "interpolate_fields",
           "requery_band",
           "discretisation_error",
           "band_correction", "Correction"]

MAD_TO_STD = 1.4826  # median absolute deviation -> standard deviation, normal noise
# A residual within this factor of the noise variance is at the data's noise (the passes' default stop).
NOISE_FACTOR = 1.5
QUERY_CHUNK = 32768  # points per model query: 2x faster on a CPU than 262144 (cache)
INTERPOLATION_CHUNK = 1 << 18  # fine points per interpolation of the queried fields
FINE_VOXELS_AT_MOST = 1 << 27  # the finer grid's voxels (512^3: 0.5 GB in float32)
RING_WEIGHT = 0.5  # the ring rule's weight of the band's outer ring: half as free as the steep voxels
GRADIENT_WEIGHT_CAP = 4.0  # gradient weights: at most sqrt(4) = 2, at 4x the steep voxels' median gradient


def grow(mask: torch.Tensor, voxels: int = 1) -> torch.Tensor:
    """bool [nx, ny, nz] -> bool [nx, ny, nz]: every voxel within ``voxels`` voxels (a cube) of a
    voxel of ``mask``."""
    if voxels <= 0:
        return mask
    return F.max_pool3d(mask.float()[None, None], 2 * voxels + 1, 1, voxels)[0, 0] > 0


def gradient_magnitude(volume: torch.Tensor) -> torch.Tensor:
    """[nx, ny, nz] -> [nx, ny, nz]: the central-difference gradient's magnitude, per voxel."""
    gx, gy, gz = torch.gradient(volume)
    return (gx * gx + gy * gy + gz * gz).sqrt()


def edge_band(volume: torch.Tensor, gradient: float = 0.02, dilate: int = 1) -> torch.Tensor:
    """[nx, ny, nz] -> bool [nx, ny, nz]: within ``dilate`` voxels of a central-difference
    gradient magnitude above ``gradient`` times the volume's 99.5th percentile, per voxel."""
    level = float(torch.quantile(volume.flatten()[::max(1, volume.numel() // 1_000_000)].float(), 0.995))
    return grow(gradient_magnitude(volume) > gradient * level, dilate)


def gradient_weights(volume: torch.Tensor, steep: torch.Tensor, cap: float = GRADIENT_WEIGHT_CAP) -> torch.Tensor:
    """[nx, ny, nz] -> [nx, ny, nz]: ``sqrt(min(g / m, cap))``, ``g`` the volume's gradient magnitude
    (:func:`gradient_magnitude`) and ``m`` its median over the ``steep`` [nx, ny, nz] (bool) voxels:
    1 at a typical steep voxel, up to ``sqrt(cap)`` at the steepest edges, less where the volume is
    flatter (all 0 where nothing is steep). Relative, so the same whatever the data's units."""
    g = gradient_magnitude(volume.float())
    if not bool(steep.any()):
        return torch.zeros_like(g)
    m = float(g[steep].median())
    return (g / m).clamp(max=float(cap)).sqrt() if m > 0 else torch.zeros_like(g)


def box_mean(volume: torch.Tensor, f: int) -> torch.Tensor:
    """Mean over ``f^3`` blocks: [f nx, f ny, f nz] -> [nx, ny, nz]."""
    nx, ny, nz = (n // f for n in volume.shape)
    return volume.reshape(nx, f, ny, f, nz, f).mean((1, 3, 5))


def noise_variance(residual: torch.Tensor) -> float:
    """The per-pixel white-noise variance of projections ``residual [N, nV, nU]``.

    The residual is high-passed by the 5-point Laplacian scaled to unit gain on white noise
    (``(4 p - p_up - p_down - p_left - p_right) / sqrt(20)``) and its spread taken from the
    median absolute value over the pixels where the residual is not exactly 0 (rays that cross
    the object): robust to the few pixels where edges leave a structured residual.
    """
    r = residual
    h = (4 * r[:, 1:-1, 1:-1] - r[:, :-2, 1:-1] - r[:, 2:, 1:-1] - r[:, 1:-1, :-2] - r[:, 1:-1, 2:]) / math.sqrt(20)
    h = h[h != 0]
    if h.numel() == 0:
        return 0.0
    return float((MAD_TO_STD * h.abs().median()) ** 2)


def at_noise(residual: torch.Tensor, noise_factor: float = NOISE_FACTOR) -> tuple[bool, float, float]:
    """Whether projections ``residual [N, nV, nU]`` are at the data's noise: their mean square within
    ``noise_factor`` times :func:`noise_variance` (the discrepancy principle). Returns that, the mean
    square and the noise variance."""
    sigma2, mean_square = noise_variance(residual), float((residual * residual).mean())
    return mean_square <= noise_factor * sigma2, mean_square, sigma2


def volume_at_noise(volume, projections: torch.Tensor, projector, noise_factor: float = NOISE_FACTOR) -> tuple[bool, float, float]:
    """:func:`at_noise` of the residual of ``volume [nx, ny, nz]`` (numpy or torch, the projector's grid)
    against ``projections [N, nV, nU]``: whether the volume fits them to their noise (the test by which a
    run's classical start is found at the views' noise, ``classical_start.start_fit``)."""
    v = torch.as_tensor(volume, dtype=torch.float32, device=projections.device)
    with torch.no_grad():
        return at_noise(projections - projector.forward(v), noise_factor)


def band_cgls(A, r: torch.Tensor, weights: torch.Tensor, iterations: int,
              stop: Optional[Callable[[torch.Tensor], bool]] = None,
              iterates: Optional[Callable[[int, torch.Tensor], None]] = None) -> tuple[torch.Tensor, list[float]]:
    """CGLS on ``(A M) z = r`` from ``z = 0``, returning ``x = M z``; ``M`` the diagonal of
    ``weights [nx, ny, nz]`` (a 0/1 band mask, or weights >= 0: column scaling, so a voxel of
    weight ``w`` moves as if its unknown were ``w`` times less free).

    ``A`` has ``forward(volume [nx, ny, nz]) -> [N, nV, nU]`` and its adjoint ``back``. Before
    each iteration ``stop(residual)`` may end it; after iteration ``i`` (from 1),
    ``iterates(i, x)`` sees the iterate (as the classical algorithms' ``iterates``). Returns ``(x [nx, ny, nz], mean squared residual
    before the first iteration and after each)``; ``x`` is 0 where the weight is 0.
    """
    m = weights.to(r.dtype)
    r = r.clone()
    x = torch.zeros(weights.shape, dtype=r.dtype, device=r.device)
    history = [float((r * r).mean())]
    s = A.back(r) * m
    p, g = s.clone(), float((s * s).sum())
    for _ in range(iterations):
        if g == 0.0 or (stop is not None and stop(r)):
            break
        mp = m * p
        q = A.forward(mp)
        a = g / float((q * q).sum())
        x += a * mp
        r -= a * q
        history.append(float((r * r).mean()))
        if iterates is not None:
            iterates(len(history) - 1, x)
        if len(history) - 1 == iterations:  # the next direction would go unused: skip its back-projection
            break
        s = A.back(r) * m
        gn = float((s * s).sum())
        p, g = s + (gn / g) * p, gn
    return x, history


def _centres(axes, ijk: torch.Tensor) -> torch.Tensor:
    """The centres [P, 3] (model units) of the cells ``ijk`` [P, 3] of a grid with ``axes``
    (``Geometry.voxel_axes``)."""
    return torch.stack([axes[0][ijk[:, 0]], axes[1][ijk[:, 1]], axes[2][ijk[:, 2]]], -1)


def band_fields(model, geometry, band: torch.Tensor, coarse: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The surface ``model``'s smooth fields on a grid ``coarse`` times finer than the scene's, where
    they are needed to interpolate anywhere in the ``band`` [nx, ny, nz] (its refinement, dilated
    by one of the finer voxels): ``(index [c nx, c ny, c nz] int32, -1 where not queried; table
    [P, 2K]: the distances then the per-material attenuations, ``CTModel.material_fields``)``."""
    c = int(coarse)
    grid = band.repeat_interleave(c, 0).repeat_interleave(c, 1).repeat_interleave(c, 2)
    grid = grow(grid)
    cells = grid.nonzero()
    if len(cells) >= 2 ** 31:
        raise KneasError(f"the band correction's {c}x grid would hold {len(cells):,} band cells, more than an int32 index "
                         "holds; use --skip-stages correction or a coarser reconstruction grid")
    index = torch.full(grid.shape, -1, dtype=torch.int32, device=band.device)  # half of int64's memory (0.5 GB at 512^3)
    index[grid] = torch.arange(len(cells), dtype=torch.int32, device=band.device)
    axes = geometry.refined(c).voxel_axes(device=band.device)
    table = []
    for i in range(0, len(cells), QUERY_CHUNK):
        j = cells[i:i + QUERY_CHUNK]
        distances, mu_materials = model.material_fields(_centres(axes, j))
        table.append(torch.cat([distances, mu_materials], -1).float())
    return index, (torch.cat(table) if table else torch.zeros(0, 0, device=band.device))


@torch.no_grad()
def requery_band(model, geometry, volume: torch.Tensor, band: torch.Tensor) -> torch.Tensor:
    """``volume`` [nx, ny, nz] with the model's attenuation ``mu`` queried afresh at the centres of
    the voxels in ``band`` [nx, ny, nz] (bool) and kept elsewhere: the model's volume after a fit
    that moved it in the band, at the band's share of a whole query's cost. With every voxel in
    the band it equals ``engine.evaluate.sample_volume``."""
    was_training = model.training
    model.eval()
    try:
        cells = band.nonzero()
        out = volume.clone()
        axes = geometry.voxel_axes(device=volume.device)
        values = [model.query(_centres(axes, cells[i:i + QUERY_CHUNK]))["mu"].to(volume.dtype)
                  for i in range(0, len(cells), QUERY_CHUNK)]
        if values:
            out[band] = torch.cat(values)
    finally:
        model.train(was_training)
    return out


def interpolate_fields(index: torch.Tensor, table: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
    """Trilinear interpolation of a sparse grid (``band_fields``) at ``coords`` [P, 3] (continuous
    grid indices, cell centres at integers; corners beyond the grid clamped to its edge) -> [P, C].
    Every corner used must have been queried.

    The corners' rows come from one flat gather each (the axes' clamped ends and weights computed
    once per axis), the same values bit for bit as indexing ``index`` by each corner's clamped
    ``ijk`` (the test's oracle) and 2.5-3.4x faster on 2 cores (abdomen's 15 million fine points of
    an estimate: 4.5 s instead of 11-15 s)."""
    n = index.shape
    flat = index.reshape(-1)
    low = coords.floor()
    t = coords - low
    low = low.long()
    strides = (n[1] * n[2], n[2], 1)
    ends, weights = [], []
    for a in range(3):
        ends.append((low[:, a].clamp(0, n[a] - 1) * strides[a], (low[:, a] + 1).clamp(0, n[a] - 1) * strides[a]))
        weights.append((1 - t[:, a], t[:, a]))
    out = torch.zeros(len(coords), table.shape[1], dtype=table.dtype, device=coords.device)
    for corner in range(8):
        i, j, k = (corner >> 2) & 1, (corner >> 1) & 1, corner & 1
        rows = flat.index_select(0, ends[0][i] + ends[1][j] + ends[2][k])
        if bool((rows < 0).any()):
            raise RuntimeError("interpolate_fields: a corner outside the queried band")
        out += (weights[0][i] * weights[1][j] * weights[2][k])[:, None] * table.index_select(0, rows.long())
    return out


@torch.no_grad()
def discretisation_error(model, geometry, volume: torch.Tensor, band: torch.Tensor, A, A_fine, *, fine: int,
                         sharpen: float, coarse: int = 2) -> torch.Tensor:
    """``d = A_f w - A box(w)`` [N, nV, nU]: the projections' part that no volume on the scene grid gives.

    ``w`` [f nx, f ny, f nz] is the model's attenuation at the fine grid's centres inside the band
    (its surfaces ``sharpen`` times sharper: ``s`` scaled, restored after) and the trilinear
    upsampling of ``volume`` [nx, ny, nz] elsewhere. In the band the model's smooth fields (signed
    distances, per-material attenuations) are queried on a grid ``coarse`` times the scene's
    (``band_fields``; ``coarse`` <= ``fine``), interpolated trilinearly to the fine centres and
    composed there (``CTModel.compose``): the sharp edges come from the selector, not from the
    query, so it takes ``(coarse / fine)^3`` of the queries of every fine point, with the same error
    against the truth's (measured on jaw and abdomen; an estimating pass on abdomen 14 s instead of
    23-29 s, 2 cores).
    """
    coarse = min(int(coarse), int(fine))
    w = F.interpolate(volume[None, None], scale_factor=fine, mode="trilinear", align_corners=False)[0, 0]
    fine_band = band.repeat_interleave(fine, 0).repeat_interleave(fine, 1).repeat_interleave(fine, 2)
    idx = fine_band.nonzero()
    index, table = band_fields(model, geometry, band, coarse)
    K = table.shape[1] // 2
    axes = geometry.refined(fine).voxel_axes(device=volume.device)
    boundary = model.boundary
    saved = boundary.log_s.data.clone()
    boundary.log_s.data += math.log(sharpen) / boundary.LOG_SCALE
    try:
        values = []
        for i in range(0, len(idx), INTERPOLATION_CHUNK):
            j = idx[i:i + INTERPOLATION_CHUNK]
            fields = interpolate_fields(index, table, (j.float() + 0.5) * (coarse / fine) - 0.5)
            values.append(model.compose(_centres(axes, j), fields[:, :K], fields[:, K:])["mu"].float())
    finally:
        boundary.log_s.data = saved
    if values:
        w[fine_band] = torch.cat(values).to(w.dtype)
    return A_fine.forward(w) - A.forward(box_mean(w, fine))


@dataclass
class Correction:
    """A band correction: ``grid`` [nx, ny, nz] (data units, 0 outside the band), the ``band``
    [nx, ny, nz] (bool), the mean squared residuals (before, after each iteration), the noise
    variance of the stop rule and the seconds it took."""

    grid: torch.Tensor
    band: torch.Tensor
    residuals: list[float]
    noise_variance: float
    seconds: float = 0.0
    discretisation: Optional[torch.Tensor] = None  # d [N, nV, nU] used (None: not needed)
    reused: bool = False  # d came from an earlier pass

    @property
    def band_fraction(self) -> float:
        return float(self.band.float().mean())

    @property
    def iterations(self) -> int:
        return len(self.residuals) - 1

    def to_json(self) -> dict:
        return {"iterations": self.iterations, "residual_mean_square": self.residuals,
                "noise_variance": self.noise_variance, "band_fraction": round(self.band_fraction, 4),
                "discretisation": None if self.discretisation is None else ("reused" if self.reused else "computed"),
                "seconds": round(self.seconds, 2)}


@torch.no_grad()
def band_correction(model, volume: torch.Tensor, projections: torch.Tensor, geometry, angles, *, iterations: int,
                    noise_factor: float = NOISE_FACTOR, fine: int = 3, sharpen: float = 2.0,
                    gradient: float = 0.02, dilate: int = 1, weighting: str = "ring", ring: Optional[float] = None,
                    discretisation: Optional[torch.Tensor] = None,
                    projectors: Optional[dict] = None, progress: Optional[Callable[[str], None]] = None) -> Correction:
    """The band correction of a surface ``model`` whose volume at the voxel centres is
    ``volume`` [nx, ny, nz], against the training ``projections`` [N, nV, nU] at ``angles`` [N].

    See the module docstring. ``discretisation``: ``d`` [N, nV, nU] of an earlier pass
    (``Correction.discretisation``), used instead of computing it again. ``fine`` is lowered (to 2
    at least) where the finer grid would hold more than ``FINE_VOXELS_AT_MOST`` voxels.
    ``weighting``: the CGLS column weights in the band, ``gradient`` (:func:`gradient_weights`)
    or ``ring`` (1 at the steep voxels, ``ring`` on the rest of the band).
    ``ring`` (None: ``RING_WEIGHT``, 0.5): the CGLS weight of the band's voxels that are not steep themselves (from 0, the
    steep voxels only, to 1, the whole band alike); the discretisation estimate and the returned
    ``band`` (where the stage fits) are the whole band whatever it is.
    ``projectors``: a dict the caller keeps between passes (empty at first), in which the scene
    grid's and the finer grid's projectors are kept with their ray tables (``{1: A, fine: A_f}``),
    so later passes do not build them again.
    ``progress(message)`` is told each phase.
    """
    import time

    from ..classical.projector import Projector

    t0 = time.perf_counter()
    say = progress or (lambda message: None)
    voxels = math.prod(geometry.n_voxel)
    fine = max(2, min(int(fine), int((FINE_VOXELS_AT_MOST / voxels) ** (1 / 3) + 1e-9)))  # memory: a 256^3 grid gets 2x
    volume = volume.float()
    b = projections.float()
    ring = RING_WEIGHT if ring is None else float(ring)
    if not 0.0 <= ring <= 1.0:
        raise KneasError(f"the correction's ring weight is {ring!r}; give --stages.correction.ring a number from 0 (the steep "
                         "voxels only) to 1 (the whole band)")
    if weighting not in ("gradient", "ring"):
        raise KneasError(f"the correction's weighting is {weighting!r}; give --stages.correction.weights gradient or ring")
    steep = edge_band(volume, gradient, 0)
    band = grow(steep, dilate)
    if weighting == "gradient":
        weights = band.float() * gradient_weights(volume, steep)
    else:
        weights = steep.float() + float(ring) * (band & ~steep).float()
    projectors = {} if projectors is None else projectors

    def projector(f: int):
        if f not in projectors:
            projectors[f] = Projector(geometry.refined(f), angles, device=volume.device)
        return projectors[f]

    A = projector(1)
    r = b - A.forward(volume)
    level, mean_square, sigma2 = at_noise(r, noise_factor)
    if level:  # at the noise level already, discretisation error and all: no need to model it
        say(f"residual {mean_square:.3g} (mean square) is at the data's noise ({sigma2:.3g}); nothing to correct")
        return Correction(torch.zeros_like(volume), band, [mean_square], sigma2, time.perf_counter() - t0)
    reused = discretisation is not None
    if reused:
        say(f"band: {float(band.float().mean()):.1%} of the voxels; the discretisation error of the last pass")
        d = discretisation
    else:
        say(f"band: {float(band.float().mean()):.1%} of the voxels; discretisation error on the {fine}x grid "
            "(the model queried in the band, the fine grid projected: the dearest part of a pass)")
        t_estimate = time.perf_counter()
        d = discretisation_error(model, geometry, volume, band, A, projector(fine), fine=fine, sharpen=sharpen)
        say(f"discretisation error estimated in {time.perf_counter() - t_estimate:.0f} s")
    r = r - d
    sigma2 = noise_variance(r)
    where = ("band, weighted by its gradient" if weighting == "gradient" else "band" if ring == 1.0
             else f"band's steep voxels ({float(steep.float().mean()):.1%} of the voxels)" if ring == 0.0
             else f"band, its outer ring weighted {ring:g}")
    say(f"residual {float((r * r).mean()):.3g} (mean square), noise {sigma2:.3g}; CGLS in the {where}")
    x, residuals = band_cgls(A, r, weights, iterations, stop=lambda res: float((res * res).mean()) <= noise_factor * sigma2)
    return Correction(x, band, residuals, sigma2, time.perf_counter() - t0, d, reused)
