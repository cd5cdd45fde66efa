"""Smoothing a reconstructed volume as far as its own noise says, chosen by SURE.

A model trained on noisy projections carries their noise into its volume: on the noisy held-out
jaw, soft tissue (0.18) comes out with a spread of 0.07, in blobs about a voxel across. The band
correction stops there (the residual is at the noise level) and nothing else takes it out. This
module picks, among a few smoothings ``f`` of the volume ``v`` (none, Gaussians, edge-preserving
bilateral filters), the one that minimises Stein's unbiased estimate of its squared error against
the noise-free volume ``u`` (SURE), for noise ``n = v - u`` that is **correlated** between
neighbouring voxels, as a network's noise is, with autocovariance ``C``:

    SURE(f) = |f(v) - v|^2 - R c(0) + 2 tr(J_f C)

with ``R`` the voxels where the volume carries noise (``mask``) and ``J_f`` the filter's Jacobian.
For a Gaussian ``G_s`` (linear) ``tr(J C) = R sum_k h_s(k) c(k)`` exactly (:func:`sure`), ``h_s`` its
taps and ``c(k)`` the noise's autocovariance at the 27 offsets ``k`` in ``{-1, 0, 1}^3`` (0 beyond).
For the bilateral filter (:func:`bilateral`, not linear) it is estimated by Monte Carlo
(:func:`monte_carlo_sure`): ``tr(J C) = E[p . J p]`` for a probe ``p`` of covariance ``C``
(:func:`correlated_noise`), with ``J p`` a finite difference.

``c`` is estimated from the volume itself (:func:`noise_autocovariance`): the robust spread (median
absolute value) of the differences ``v(x) - v(x + k)``, which is ``2 (c(0) - c(k))`` for noise and
barely moved by the few voxels at edges, and ``c(0)`` from differences ``far`` voxels apart, where
the noise is taken as uncorrelated. The white-noise SURE (``c(k) = 0`` off the centre) under-smooths
such noise (jaw-noisy: s 0.4 against the best 0.8).

The bilateral filter averages a voxel with its neighbours along each axis in turn, each weighted by
distance (a Gaussian of ``sigma`` voxels) and by how close its value is in a lightly smoothed guide
(a Gaussian of ``range_std``, a multiple of the noise's standard deviation): it averages the noise
out inside each material over several voxels without carrying one material across an edge, which
a Gaussian cannot (jaw-noisy 36.5 dB against the best Gaussian's 34.8).

Where no smoothing lowers the estimate (a clean scan: the differences are edges and texture, and
every filter costs more than it removes) :func:`sure_smoothing` returns the volume as it is.

The noise estimate is a floor: the robust spread sees the bulk of the voxels, and noise that is
stronger in part of the volume, or correlated further than ``FAR`` voxels, is larger than it says
(on the noisy knee wider than the field of view, its choice, a Gaussian of 0.4 voxel, left 4.5 times
the estimated error). The projections tell: a volume whose projections fit the measured ones closer
than their own noise still holds noise. :func:`discrepancy_smoothing` takes SURE's choice and, while
that choice's projections still fit the data closer than the data's noise variance (the
**discrepancy principle**, as the band correction stops by), raises the noise estimate by the steps
of ``NOISE_SCALES`` and chooses again. On a scan where the choice already reaches the noise, nothing
changes; on a clean scan (SURE chooses none) the projections are not even compared.

The whole misfit can hide it: a model trained on a real scan misses the smoothest part of the data
(its residual's power at the lowest detector frequencies, under a twentieth of a cycle a pixel, is 3-6 times the
noise), which lifts the whole misfit over the noise while the same volume fits the finer bands closer
than their noise (0.91-0.95 of it at 5e4-1e5 photons). So the choice must also reach
``BAND_FLOOR`` of the noise in every band of ``BAND_EDGES`` (:func:`band_power_ratios`), where a
voxel's noise shows on the detector; white noise reads 1 in each.

The projections also tell when SURE takes signal for noise: texture that varies from voxel to voxel
(real anatomy) looks like correlated noise to the robust spread. Taking noise out of a volume can
worsen its fit to the data by at most the data's noise variance (the noise it had fitted); a filter
whose projections fit worse than the unsmoothed volume's by more than that (``GIVE_UP``) takes out
what the data hold, and is refused, as is every stronger choice after it. Measured on the default
runs (2026-12-05): noisy scans give up 0.01-0.15 of the noise variance, clean real anatomy 2.4-2.9.

The pure functions take and return tensors; :func:`gaussian_blur` is separable (three 1-D passes,
the volume's border repeated); ``tests/test_denoise.py`` has naive versions as oracles.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field
from typing import Callable, Optional, Sequence

import torch
import torch.nn.functional as F

from .band_correction import MAD_TO_STD

__all__ = ["OFFSETS", "SIGMAS", "BILATERALS", "gaussian_taps", "gaussian_blur", "bilateral", "shifted_pairs",
           "robust_variance", "noise_autocovariance", "correlated_noise", "sure", "monte_carlo_sure", "sure_smoothing",
           "discrepancy_smoothing", "band_power_ratios", "Denoising", "NOISE_SCALES", "GIVE_UP", "BAND_EDGES", "BAND_FLOOR"]

OFFSETS = [k for k in itertools.product((-1, 0, 1), repeat=3)]  # the 27 offsets of c(k), (0, 0, 0) among them
SIGMAS = tuple(round(0.4 + 0.1 * i, 1) for i in range(12))  # 0.4 .. 1.5 voxels: the candidates besides 0
FAR = 3  # voxels: c(0) from differences this far apart, where the noise is taken as uncorrelated
BILATERALS = tuple((s, k) for k in (1.0, 1.5) for s in (1.5, 2.2, 3.0, 4.5))  # (sigma voxels, range in noise stds)
BILATERAL_TRUNCATE = 2.5  # the bilateral's taps reach this many sigmas
GUIDE_SIGMA = 0.8  # voxels: the Gaussian that smooths the bilateral's guide (its range weights compare the guide's values)
PROBE_STEP = 0.1  # the Monte Carlo divergence's finite difference, in the probe's (the noise's) standard deviations
NOISE_SCALES = (1.0, 1.5, 2.0, 3.0, 4.0)  # the noise estimate's factors discrepancy_smoothing tries in turn
GIVE_UP = 1.0  # data noise variances of fit a smoothing may give up over the unsmoothed volume's misfit
BAND_EDGES = (0.15, 0.25, 0.35, 0.5)  # cycles per voxel's footprint on the detector: the bands where a volume's noise shows
BAND_FLOOR = 0.98  # a band of the residual under this share of the data's noise holds noise the volume fitted
MEDIAN_VALUES_AT_MOST = 1 << 21  # a median of more values takes every n-th (a 256^3 grid: 8x fewer, 3x faster)


def gaussian_taps(sigma: float, dtype=torch.float32) -> torch.Tensor:
    """The normalised 1-D Gaussian of standard deviation ``sigma`` voxels, out to ``r = int(4 sigma + 0.5)``
    voxels (as ``scipy.ndimage.gaussian_filter``): ``[2 r + 1]``; ``sigma`` 0 gives ``[1]``."""
    if sigma <= 0:
        return torch.ones(1, dtype=dtype)
    r = max(1, int(4.0 * sigma + 0.5))
    x = torch.arange(-r, r + 1, dtype=torch.float64)
    g = torch.exp(-0.5 * (x / sigma) ** 2)
    return (g / g.sum()).to(dtype)


def gaussian_blur(volume: torch.Tensor, sigma: float) -> torch.Tensor:
    """``volume`` [nx, ny, nz] smoothed by a Gaussian of ``sigma`` voxels (separable, the border
    voxels repeated outwards): [nx, ny, nz]. ``sigma`` 0 returns the volume."""
    if sigma <= 0:
        return volume
    taps = gaussian_taps(sigma, volume.dtype).to(volume.device)
    r = (len(taps) - 1) // 2
    out = volume[None, None]
    for axis in range(3):
        shape = [1, 1, 1, 1, 1]
        shape[2 + axis] = len(taps)
        pad = [0, 0, 0, 0, 0, 0]
        pad[2 * (2 - axis)] = pad[2 * (2 - axis) + 1] = r  # F.pad lists the last axis first
        out = F.conv3d(F.pad(out, pad, mode="replicate"), taps.reshape(shape))
    return out[0, 0]


def bilateral(volume: torch.Tensor, sigma: float, range_std: float, guide: Optional[torch.Tensor] = None) -> torch.Tensor:
    """``volume`` [nx, ny, nz] smoothed by a separable cross-bilateral filter: along each axis in
    turn (x, then y, then z, each pass filtering the last one's output), voxel ``x`` becomes the
    average of ``out(x + j e)`` for ``|j| <= r = max(1, int(BILATERAL_TRUNCATE sigma + 0.5))``,
    weighted by ``exp(-j^2 / (2 sigma^2)) exp(-(g(x + j e) - g(x))^2 / (2 range_std^2))``, ``g`` the
    ``guide`` [nx, ny, nz] (None: ``gaussian_blur(volume, GUIDE_SIGMA)``); the border voxels repeated
    outwards: [nx, ny, nz]. ``range_std`` <= 0 or ``sigma`` <= 0 returns the volume."""
    if sigma <= 0 or range_std <= 0:
        return volume
    guide = gaussian_blur(volume, GUIDE_SIGMA) if guide is None else guide
    r = max(1, int(BILATERAL_TRUNCATE * sigma + 0.5))
    out = volume
    for axis in range(3):
        pad = [0, 0, 0, 0, 0, 0]
        pad[2 * (2 - axis)] = pad[2 * (2 - axis) + 1] = r  # F.pad lists the last axis first
        padded = F.pad(out[None, None], pad, mode="replicate")[0, 0]
        padded_guide = F.pad(guide[None, None], pad, mode="replicate")[0, 0]
        total = torch.zeros_like(volume)
        weights = torch.zeros_like(volume)
        for j in range(-r, r + 1):
            w = math.exp(-0.5 * (j / sigma) ** 2) * torch.exp(
                -0.5 * ((padded_guide.narrow(axis, r + j, volume.shape[axis]) - guide) / range_std) ** 2)
            total += w * padded.narrow(axis, r + j, volume.shape[axis])
            weights += w
        out = total / weights
    return out


def shifted_pairs(volume: torch.Tensor, mask: torch.Tensor, k: Sequence[int]) -> torch.Tensor:
    """``v(x) - v(x + k)`` for every ``x`` with both ``x`` and ``x + k`` inside the grid and in ``mask``:
    a flat tensor. ``k``: an integer offset per axis."""
    a = tuple(slice(max(0, -o), n - max(0, o)) for o, n in zip(k, volume.shape))
    b = tuple(slice(max(0, o), n - max(0, -o)) for o, n in zip(k, volume.shape))
    both = mask[a] & mask[b]
    return (volume[a] - volume[b])[both]


def robust_variance(values: torch.Tensor) -> float:
    """The variance of zero-mean normal ``values`` from their median absolute value (robust to a
    small share of large ones: edges), over every n-th value where there are more than
    ``MEDIAN_VALUES_AT_MOST``. 0 for no values."""
    if values.numel() == 0:
        return 0.0
    step = -(-values.numel() // MEDIAN_VALUES_AT_MOST)
    return float((MAD_TO_STD * values[::step].abs().median()) ** 2)


def noise_autocovariance(volume: torch.Tensor, mask: torch.Tensor, far: int = FAR) -> torch.Tensor:
    """The autocovariance of ``volume``'s noise inside ``mask`` at the offsets ``{-1, 0, 1}^3``:
    [3, 3, 3], ``c[1 + kx, 1 + ky, 1 + kz]`` (data units squared).

    ``c(0)`` is half the robust variance of differences ``far`` voxels apart along each axis (their
    mean over the three axes), ``c(k) = c(0) - var(v(x) - v(x + k)) / 2`` for the other 26 (each
    measured once for ``k`` and ``-k``, whose pairs are the same); each is kept within
    ``[-c(0), c(0)]``."""
    volume = volume.float()
    mask = mask.bool()
    c0 = sum(robust_variance(shifted_pairs(volume, mask, tuple(far if a == axis else 0 for a in range(3))))
             for axis in range(3)) / 6.0
    c = torch.zeros(3, 3, 3, dtype=torch.float64)
    c[1, 1, 1] = c0
    for k in OFFSETS[: len(OFFSETS) // 2]:  # the first 13 offsets; c(-k) = c(k): the same pairs, negated
        value = min(c0, max(-c0, c0 - robust_variance(shifted_pairs(volume, mask, k)) / 2.0))
        c[1 + k[0], 1 + k[1], 1 + k[2]] = c[1 - k[0], 1 - k[1], 1 - k[2]] = value
    return c


def sure(volume: torch.Tensor, smoothed: torch.Tensor, sigma: float, region: int, c: torch.Tensor) -> float:
    """SURE of ``smoothed = gaussian_blur(volume, sigma)`` (module docstring): ``region`` voxels
    carry noise of autocovariance ``c`` [3, 3, 3] (0 beyond one voxel). Squared data units, summed
    over the volume; ``sigma`` 0 gives ``region * c(0)``."""
    g = gaussian_taps(sigma, torch.float64)
    r = (len(g) - 1) // 2
    near = torch.zeros(3, dtype=torch.float64)  # the taps at offsets -1, 0, 1
    for i, o in enumerate((-1, 0, 1)):
        if abs(o) <= r:
            near[i] = g[r + o]
    h = near[:, None, None] * near[None, :, None] * near[None, None, :]
    fit = float(((smoothed.double() - volume.double()) ** 2).sum())
    return fit - region * float(c[1, 1, 1]) + 2.0 * region * float((h * c).sum())


def correlated_noise(c: torch.Tensor, shape: Sequence[int], generator: torch.Generator) -> torch.Tensor:
    """Normal noise of autocovariance ``c`` [3, 3, 3] (at the offsets ``{-1, 0, 1}^3``, 0 beyond),
    periodic over a grid of ``shape``: white noise filtered by the square root of ``c``'s power
    spectrum (its negative parts, where ``c`` is not a valid covariance, set to 0): float32 [shape]."""
    kernel = torch.zeros(tuple(shape), dtype=torch.float64)
    for k in OFFSETS:
        kernel[k[0] % shape[0], k[1] % shape[1], k[2] % shape[2]] = c[1 + k[0], 1 + k[1], 1 + k[2]]
    power = torch.fft.fftn(kernel).real.clamp_min(0)
    white = torch.randn(tuple(shape), generator=generator, dtype=torch.float64)
    return torch.fft.ifftn(torch.fft.fftn(white) * power.sqrt()).real.float()


def monte_carlo_sure(volume: torch.Tensor, smoother, smoothed: torch.Tensor, probe: torch.Tensor, region: int,
                     c0: float) -> float:
    """SURE (module docstring) of ``smoothed = smoother(volume)`` for any ``smoother`` (a function of
    a [nx, ny, nz] volume), its ``tr(J C)`` estimated from one ``probe`` [nx, ny, nz] of the noise's
    covariance (0 outside the noisy voxels) by a finite difference of ``PROBE_STEP`` times it; the
    ``region`` voxels carry noise of variance ``c0``. Squared data units, summed over the volume."""
    divergence = float((probe.double() * (smoother(volume + PROBE_STEP * probe) - smoothed).double()).sum()) / PROBE_STEP
    return float(((smoothed.double() - volume.double()) ** 2).sum()) - region * c0 + 2.0 * divergence


def band_power_ratios(residual: torch.Tensor, noise_variance: float, footprint: float,
                      edges: Sequence[float] = BAND_EDGES) -> list[float]:
    """The mean power of projections ``residual`` [N, nV, nU] in each band of detector frequency between
    consecutive ``edges`` (cycles per ``footprint``, a voxel's width on the detector in pixels; the
    radial frequency of each view's 2-D DFT), over ``noise_variance`` (per pixel): ``[len(edges) - 1]``.
    White noise of that variance gives 1 in every band; a volume that fitted part of the data's noise
    leaves less than 1 where it did. A band that holds no frequency gives ``nan``."""
    power = torch.fft.fft2(residual.double()).abs().pow(2) / (residual.shape[-2] * residual.shape[-1])
    fv = torch.fft.fftfreq(residual.shape[-2], dtype=torch.float64, device=residual.device)[:, None]
    fu = torch.fft.fftfreq(residual.shape[-1], dtype=torch.float64, device=residual.device)[None, :]
    per_voxel = torch.sqrt(fu * fu + fv * fv) * float(footprint)
    ratios = []
    for low, high in zip(edges[:-1], edges[1:]):
        band = (per_voxel >= low) & (per_voxel < high)
        ratios.append(float(power[:, band].mean()) / float(noise_variance) if bool(band.any()) and noise_variance > 0
                      else float("nan"))
    return ratios


def _label(kind: str, sigma: float = 0.0, range_stds: float = 0.0) -> str:
    """A candidate's name: ``none``, ``gaussian 0.8``, ``bilateral 3 x1.5`` (sigma, range in noise stds)."""
    return {"none": "none", "gaussian": f"gaussian {sigma:g}"}.get(kind, f"bilateral {sigma:g} x{range_stds:g}")


@dataclass
class Denoising:
    """The choice :func:`sure_smoothing` made: the ``filter`` (``none``, ``gaussian`` or
    ``bilateral``), its ``sigma`` (voxels) and, for a bilateral, its range in noise standard
    deviations; SURE of every candidate (``{label: value}``, :func:`_label`), the noise's standard
    deviation (its estimate times ``noise_scale``) and its correlation with the six face neighbours
    (their mean), and the ``region``'s voxel count; from :func:`discrepancy_smoothing`, the
    ``misfit`` of each choice it tried (its projections' mean-square misfit over the data's noise
    variance, in the order of ``NOISE_SCALES``), the unsmoothed volume's own misfit in the same unit
    (``own_misfit``), the first choice refused for giving up more fit than the noise (``refused``, its
    label; empty when none was) and, for each accepted choice, its residual's smallest band power ratio
    (``band_fit``, None where not asked)."""

    filter: str
    sigma: float = 0.0
    range_stds: float = 0.0
    sure: dict = field(default_factory=dict)
    noise_std: float = 0.0
    neighbour_correlation: float = 0.0
    region: int = 0
    seconds: float = 0.0
    noise_scale: float = 1.0
    misfit: list = field(default_factory=list)
    own_misfit: Optional[float] = None
    refused: str = ""
    band_fit: list = field(default_factory=list)

    def to_json(self) -> dict:
        return {"filter": self.filter, "sigma_voxels": self.sigma, "range_noise_stds": self.range_stds,
                "noise_std": self.noise_std, "neighbour_correlation": round(self.neighbour_correlation, 4),
                "region_voxels": self.region, "sure": dict(self.sure), "noise_scale": self.noise_scale,
                "misfit": [{"noise_scale": m, "choice": label, "misfit_over_noise": round(r, 4)} for m, label, r in self.misfit],
                "own_misfit_over_noise": None if self.own_misfit is None else round(self.own_misfit, 4),
                "band_fit_over_noise": [None if b is None else round(b, 4) for b in self.band_fit],
                "refused": self.refused, "seconds": round(self.seconds, 2)}

    @property
    def label(self) -> str:
        return _label(self.filter, self.sigma, self.range_stds)


@torch.no_grad()
def sure_smoothing(volume: torch.Tensor, mask: Optional[torch.Tensor] = None, sigmas: Sequence[float] = SIGMAS,
                   bilaterals: Sequence[tuple[float, float]] = BILATERALS, seed: int = 0, noise_scale: float = 1.0,
                   autocovariance: Optional[torch.Tensor] = None) -> tuple[torch.Tensor, Denoising]:
    """The smoothing of ``volume`` [nx, ny, nz] with the lowest SURE (module docstring) among none,
    a Gaussian of each of ``sigmas`` voxels (exact SURE) and the bilateral filter of each
    ``(sigma voxels, range in noise standard deviations)`` in ``bilaterals`` (SURE by Monte Carlo,
    one probe drawn from ``seed`` shared by all): ``(smoothed [nx, ny, nz], Denoising)``; the volume
    itself where none wins. ``mask`` [nx, ny, nz] bool: the voxels that carry noise (None: where the
    volume is not exactly 0, i.e. inside the model's occupancy grid)."""
    import time

    t0 = time.perf_counter()
    volume = volume.float()
    mask = (volume != 0) if mask is None else mask.bool()
    region = int(mask.sum())
    c = (noise_autocovariance(volume, mask) if autocovariance is None else autocovariance) * float(noise_scale)
    c0 = float(c[1, 1, 1])
    face = [c[1 + k[0], 1 + k[1], 1 + k[2]] for k in OFFSETS if sum(map(abs, k)) == 1]
    rho = float(sum(face) / len(face) / c0) if c0 > 0 else 0.0
    noise_std = math.sqrt(max(c0, 0.0))
    scores = {_label("none"): region * c0}
    best, best_volume = Denoising("none"), volume
    for s in sigmas:
        smoothed = gaussian_blur(volume, float(s))
        candidate = Denoising("gaussian", float(s))
        scores[candidate.label] = sure(volume, smoothed, float(s), region, c)
        if scores[candidate.label] < scores[best.label]:
            best, best_volume = candidate, smoothed
    if bilaterals and noise_std > 0:
        generator = torch.Generator().manual_seed(seed)
        probe = correlated_noise(c, volume.shape, generator).to(volume.device) * mask  # drawn on the CPU: the same on any device
        for s, k in bilaterals:
            def smoother(v, s=float(s), k=float(k)):
                return bilateral(v, s, k * noise_std)
            smoothed = smoother(volume)
            candidate = Denoising("bilateral", float(s), float(k))
            scores[candidate.label] = monte_carlo_sure(volume, smoother, smoothed, probe, region, c0)
            if scores[candidate.label] < scores[best.label]:
                best, best_volume = candidate, smoothed
    best.sure, best.noise_std, best.neighbour_correlation, best.region = scores, noise_std, rho, region
    best.noise_scale = float(noise_scale)
    best.seconds = time.perf_counter() - t0
    return best_volume, best


@torch.no_grad()
def discrepancy_smoothing(volume: torch.Tensor, misfit: Callable[[torch.Tensor], float], data_noise: float,
                          mask: Optional[torch.Tensor] = None, scales: Sequence[float] = NOISE_SCALES,
                          sigmas: Sequence[float] = SIGMAS, bilaterals: Sequence[tuple[float, float]] = BILATERALS,
                          seed: int = 0, give_up: float = GIVE_UP, band_fit: Optional[Callable[[torch.Tensor], float]] = None,
                          band_floor: float = BAND_FLOOR) -> tuple[torch.Tensor, Denoising]:
    """:func:`sure_smoothing` of ``volume`` [nx, ny, nz] with its noise estimate raised, by the
    factors ``scales`` in turn, while the choice still fits the data closer than their noise
    (module docstring): ``misfit(smoothed)`` is the mean square of the data minus the projections
    of a volume, ``data_noise`` the data's noise variance per value (``correction.noise_variance``).
    The first choice that reaches ``data_noise``, or the last one, is returned with every choice
    tried in ``Denoising.misfit``; a choice of none ends it at once (nothing to raise: the volume
    shows no noise). A choice whose misfit exceeds the unsmoothed volume's own by more than
    ``give_up`` x ``data_noise`` is refused and ends it: the last choice accepted before it is
    returned, or the volume as it is (``filter`` none, ``refused`` naming the choice). ``data_noise``
    <= 0 (nothing known) returns the first choice.

    ``band_fit`` (None: not asked) gives the smallest of a volume's residual's band power ratios
    (:func:`band_power_ratios`): a choice reaches the noise only where that is ``band_floor`` or more
    too. A model that misses the data's smoothest part (its bias) fits their noise at finer detector
    frequencies all the same, and the whole misfit, dominated by the bias, hides it; each choice's value
    is kept in ``Denoising.band_fit``."""
    import time

    t0 = time.perf_counter()
    volume = volume.float()
    mask = (volume != 0) if mask is None else mask.bool()
    c = noise_autocovariance(volume, mask)  # estimated once, raised for each scale
    tried, bands, own, refused = [], [], None, ""
    accepted = None  # (smoothed, choice) of the last choice within the noise
    for scale in scales:
        smoothed, choice = sure_smoothing(volume, mask, sigmas, bilaterals, seed, noise_scale=scale, autocovariance=c)
        if choice.filter == "none" or data_noise <= 0:
            accepted = (smoothed, choice)
            break
        if own is None:
            own = float(misfit(volume))
        smoothed_misfit = float(misfit(smoothed))
        ratio = smoothed_misfit / float(data_noise)
        tried.append((float(scale), choice.label, ratio))
        if smoothed_misfit - own > give_up * float(data_noise):
            refused = choice.label
            break
        accepted = (smoothed, choice)
        band = None if band_fit is None else float(band_fit(smoothed))
        bands.append(band)
        if ratio >= 1.0 and (band is None or band >= band_floor):
            break
    if accepted is None:  # the first choice gave up more than the noise: the volume stays as it is
        none = Denoising("none", sure=choice.sure, noise_std=choice.noise_std, neighbour_correlation=choice.neighbour_correlation,
                         region=choice.region, noise_scale=choice.noise_scale)
        accepted = (volume, none)
    smoothed, choice = accepted
    choice.misfit, choice.band_fit, choice.refused = tried, bands, refused
    choice.own_misfit = None if own is None else own / float(data_noise)
    choice.seconds = time.perf_counter() - t0
    return smoothed, choice
