"""Image, volume and surface metrics (SPEC §5).

Conventions
-----------
**2D (projections).** Inputs are line integrals ``p`` (the projection arrays,
``[N, nV, nU]``, unit-free). Every held-out view is converted to intensity
``I = exp(-p)`` and scored on its own:

* PSNR: each image of the pair is min–max normalised **by its own** minimum and
  maximum to [0, 1] (this is what the NAF/NeAS/K-NeAS reference code does), then
  ``PSNR = 10 log10(1 / MSE)``. A constant image normalises to all zeros.
* SSIM: on the un-normalised intensities with ``data_range = max(pair) - min(pair)``
  (Gaussian window σ = 1.5, population covariance: Wang et al. 2004).

The figures of a set of views are the mean over views; per-view arrays are kept.

**3D (volumes).** Volumes ``[nx, ny, nz]`` in data units (1/m; NAF images lie
in [0, 1]). ``psnr3d`` uses peak 1 and no fitting (the primary figure, SPEC §5);
``ssim3d`` is a true 3-D SSIM (Gaussian window σ = 1.5) with ``data_range = 1``.
The ``*_ls`` variants first rescale the prediction by the least-squares factor
``⟨p, g⟩ / ⟨p, p⟩`` as the reference code does; they are reported beside, never
instead of, the plain figures. Where the truth reaches above 1 (a scan in a scanner's
units), ``psnr3d_truth_peak`` and ``ssim3d_truth_range`` take the truth's maximum and range
instead, beside the primary figures.

**Identical inputs.** PSNR of an exact match is ``inf`` (``float('inf')``),
everywhere and consistently, never capped; a mean over views that contains an
``inf`` is ``inf``. ``json.dump`` writes it as ``Infinity``.

**Surfaces.** Point sets in mm in the scene's physical frame (the frame of
:class:`~kneas_method.geometry.Geometry`, converted with ``mm_per_unit``).
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import KneasError

__all__ = [
    "psnr",
    "psnr2d",
    "ssim2d",
    "psnr3d",
    "ssim3d",
    "psnr3d_ls",
    "ssim3d_ls",
    "ls_scale",
    "projection_metrics",
    "volume_metrics",
    "chamfer_distance",
    "fscore",
    "dice",
    "dice_per_label",
    "surface_points_from_labels",
]


# ----------------------------------------------------------------- helpers
def _np(x, name: str = "array") -> np.ndarray:
    """numpy float64 copy of a numpy array / torch tensor / sequence."""
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    arr = np.asarray(x, dtype=np.float64)
    if not np.all(np.isfinite(arr)):
        raise KneasError(f"{name} contains NaN or infinite values; check the reconstruction before scoring it")
    return arr


def _same_shape(a: np.ndarray, b: np.ndarray, what: str) -> None:
    if a.shape != b.shape:
        raise KneasError(f"{what}: prediction has shape {a.shape} but ground truth has {b.shape}; pass arrays of the same shape")


def psnr(pred, gt, data_range: float = 1.0) -> float:
    """Peak signal-to-noise ratio ``10 log10(data_range² / MSE)`` in dB (``inf`` if equal)."""
    p, g = _np(pred, "prediction"), _np(gt, "ground truth")
    _same_shape(p, g, "psnr")
    mse = float(np.mean((p - g) ** 2))
    if mse == 0.0:
        return math.inf
    return 10.0 * math.log10(data_range**2 / mse)


def _minmax(img: np.ndarray) -> np.ndarray:
    lo, hi = img.min(), img.max()
    if hi > lo:
        return (img - lo) / (hi - lo)
    return np.zeros_like(img)


def _ssim(a: np.ndarray, b: np.ndarray, data_range: float) -> float:
    """SSIM of two same-shape 2-D or 3-D arrays (Gaussian σ = 1.5 window; smaller
    uniform window when an axis is shorter than 11 samples)."""
    from skimage.metrics import structural_similarity

    if data_range <= 0:
        # both inputs constant and equal (range of the pair is zero)
        return 1.0 if np.array_equal(a, b) else 0.0
    smallest = min(a.shape)
    if smallest >= 11:
        return float(structural_similarity(a, b, data_range=data_range, gaussian_weights=True, sigma=1.5,
                                           use_sample_covariance=False))
    win = smallest if smallest % 2 == 1 else smallest - 1
    if win < 3:
        raise KneasError(f"SSIM needs every axis to have at least 3 samples, got shape {a.shape}; score larger images")
    return float(structural_similarity(a, b, data_range=data_range, win_size=win, use_sample_covariance=False))


def _views(x, name: str) -> np.ndarray:
    arr = _np(x, name)
    if arr.ndim == 2:
        arr = arr[None]
    if arr.ndim != 3:
        raise KneasError(f"{name} must be [N, nV, nU] projections (or one [nV, nU] view), got shape {arr.shape}")
    return arr


# ----------------------------------------------------------------------- 2D
def psnr2d(pred_proj, gt_proj, *, domain: str = "line_integral") -> np.ndarray:
    """Per-view PSNR [dB] in the intensity domain (SPEC §5).

    Args:
        pred_proj, gt_proj: ``[N, nV, nU]`` (or one ``[nV, nU]``) numpy or torch.
            Line integrals ``p`` by default; pass ``domain="intensity"`` if they
            already are intensities ``exp(-p)``.

    Returns:
        ``[N]`` float64 PSNR per view; each image is min–max normalised by its
        own range first; ``inf`` where a pair matches exactly.
    """
    p, g = _intensities(pred_proj, gt_proj, domain)
    return np.array([psnr(_minmax(a), _minmax(b), 1.0) for a, b in zip(p, g)])


def ssim2d(pred_proj, gt_proj, *, domain: str = "line_integral") -> np.ndarray:
    """Per-view SSIM in the intensity domain with the data range of each pair.

    Args / shapes as :func:`psnr2d`. Returns ``[N]`` float64.
    """
    p, g = _intensities(pred_proj, gt_proj, domain)
    out = []
    for a, b in zip(p, g):
        rng = float(max(a.max(), b.max()) - min(a.min(), b.min()))
        out.append(_ssim(a, b, rng))
    return np.array(out)


def _intensities(pred, gt, domain: str):
    if domain not in ("line_integral", "intensity"):
        raise KneasError(f"domain {domain!r} is not known; use 'line_integral' (projections p) or 'intensity' (exp(-p))")
    p, g = _views(pred, "predicted projections"), _views(gt, "ground-truth projections")
    _same_shape(p, g, "2D metrics")
    if domain == "line_integral":
        p, g = np.exp(-p), np.exp(-g)
    return p, g


def projection_metrics(pred_proj, gt_proj, *, domain: str = "line_integral") -> dict:
    """2D metrics of held-out views: ``psnr2d``, ``ssim2d`` (means over views) and
    ``psnr2d_per_view``, ``ssim2d_per_view`` (lists), ``n_views``. JSON-able."""
    ps = psnr2d(pred_proj, gt_proj, domain=domain)
    ss = ssim2d(pred_proj, gt_proj, domain=domain)
    return {
        "psnr2d": float(np.mean(ps)),
        "ssim2d": float(np.mean(ss)),
        "psnr2d_per_view": [float(v) for v in ps],
        "ssim2d_per_view": [float(v) for v in ss],
        "n_views": int(len(ps)),
    }


# ----------------------------------------------------------------------- 3D
def _vol_pair(pred, gt):
    p, g = _np(pred, "predicted volume"), _np(gt, "ground-truth volume")
    if g.ndim != 3:
        raise KneasError(f"volumes must be [nx, ny, nz], got shape {g.shape}")
    _same_shape(p, g, "3D metrics")
    return p, g


def psnr3d(pred_vol, gt_vol, data_range: float = 1.0) -> float:
    """3-D PSNR [dB] of volumes ``[nx, ny, nz]`` in data units, peak 1, no fitting."""
    p, g = _vol_pair(pred_vol, gt_vol)
    return psnr(p, g, data_range)


def ssim3d(pred_vol, gt_vol, data_range: float = 1.0) -> float:
    """3-D SSIM of volumes ``[nx, ny, nz]`` in data units, ``data_range`` 1 by default."""
    p, g = _vol_pair(pred_vol, gt_vol)
    return _ssim(p, g, data_range)


def ls_scale(pred_vol, gt_vol) -> float:
    """Least-squares factor ``⟨p, g⟩ / ⟨p, p⟩`` (1 for an all-zero prediction)."""
    p, g = _vol_pair(pred_vol, gt_vol)
    pp = float(np.sum(p * p))
    return float(np.sum(p * g)) / pp if pp > 0 else 1.0


def psnr3d_ls(pred_vol, gt_vol, data_range: float = 1.0) -> float:
    """:func:`psnr3d` after rescaling the prediction by :func:`ls_scale` (reference-code variant)."""
    p, g = _vol_pair(pred_vol, gt_vol)
    return psnr(p * ls_scale(p, g), g, data_range)


def ssim3d_ls(pred_vol, gt_vol, data_range: float = 1.0) -> float:
    """:func:`ssim3d` after rescaling the prediction by :func:`ls_scale`."""
    p, g = _vol_pair(pred_vol, gt_vol)
    return _ssim(p * ls_scale(p, g), g, data_range)


def volume_metrics(pred_vol, gt_vol, *, data_range: float = 1.0, ssim: bool = True) -> dict:
    """3D metrics: ``psnr3d``, ``ssim3d`` (primary, exact units) and ``psnr3d_ls``,
    ``ssim3d_ls``, ``ls_scale`` (least-squares-rescaled variant), ``mse3d``. Where the truth
    reaches above ``data_range`` (a scan in a scanner's units, not NAF's [0, 1]), also
    ``psnr3d_truth_peak`` and ``ssim3d_truth_range``: the same volumes with the truth's maximum as
    the peak and its range as SSIM's (the primary figures' peak 1 says little there).
    ``ssim=False`` skips the (slower) SSIMs. JSON-able floats."""
    p, g = _vol_pair(pred_vol, gt_vol)
    k = ls_scale(p, g)
    out = {
        "psnr3d": psnr(p, g, data_range),
        "psnr3d_ls": psnr(p * k, g, data_range),
        "ls_scale": k,
        "mse3d": float(np.mean((p - g) ** 2)),
    }
    peak = float(np.max(g)) if g.size else 0.0
    if peak > data_range:
        out["psnr3d_truth_peak"] = psnr(p, g, peak)
    if ssim:
        out["ssim3d"] = _ssim(p, g, data_range)
        out["ssim3d_ls"] = _ssim(p * k, g, data_range)
        if peak > data_range:
            out["ssim3d_truth_range"] = _ssim(p, g, peak - float(np.min(g)))
    return out


# ------------------------------------------------------------------ surfaces
def _points(x, name: str) -> np.ndarray:
    arr = _np(x, name)
    arr = arr.reshape(-1, 3) if arr.size else np.zeros((0, 3))
    if len(arr) == 0:
        raise KneasError(f"{name} is empty: the surface was not found (no voxels of that material); check the labels/threshold")
    return arr


def _nn_dist(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance from each point of ``a`` to its nearest neighbour in ``b``."""
    from scipy.spatial import cKDTree

    return cKDTree(b).query(a, k=1)[0]


def chamfer_distance(points_a_mm, points_b_mm) -> tuple[float, float, float]:
    """Chamfer distance between point sets ``[Pa, 3]`` and ``[Pb, 3]`` (mm).

    Returns:
        ``(symmetric, a_to_b, b_to_a)``: mean nearest-neighbour distances a→b and
        b→a, and their average ``(a_to_b + b_to_a) / 2``, all in mm (the input unit).
    """
    a, b = _points(points_a_mm, "first point set"), _points(points_b_mm, "second point set")
    ab, ba = float(np.mean(_nn_dist(a, b))), float(np.mean(_nn_dist(b, a)))
    return 0.5 * (ab + ba), ab, ba


def fscore(points_a, points_b, threshold_mm: float, *, return_pr: bool = False):
    """F-score at distance ``threshold_mm`` between predicted ``points_a`` and
    reference ``points_b`` ``[P, 3]`` (mm).

    precision = fraction of ``a`` within the threshold of ``b``; recall = fraction
    of ``b`` within it of ``a``; ``F = 2PR / (P + R)`` (0 when both are 0).
    Returns F, or ``(F, precision, recall)`` with ``return_pr=True``.
    """
    if not threshold_mm > 0:
        raise KneasError(f"F-score threshold must be a positive distance in mm, got {threshold_mm}")
    a, b = _points(points_a, "first point set"), _points(points_b, "second point set")
    precision = float(np.mean(_nn_dist(a, b) <= threshold_mm))
    recall = float(np.mean(_nn_dist(b, a) <= threshold_mm))
    f = 0.0 if precision + recall == 0 else 2 * precision * recall / (precision + recall)
    return (f, precision, recall) if return_pr else f


def dice(labels_pred, labels_gt, label: int) -> float:
    """Dice ``2|A∩B| / (|A| + |B|)`` of voxels equal to ``label`` in two label
    volumes of the same shape. 1.0 when the label is absent from both (agreement)."""
    p, g = np.asarray(_labels(labels_pred)), np.asarray(_labels(labels_gt))
    _same_shape(p, g, "dice")
    a, b = p == label, g == label
    denom = int(a.sum()) + int(b.sum())
    if denom == 0:
        return 1.0
    return 2.0 * int(np.logical_and(a, b).sum()) / denom


def dice_per_label(labels_pred, labels_gt, labels=None) -> dict[int, float]:
    """Dice per label: ``{label: dice}`` for ``labels`` (default: every non-zero
    label present in either volume; 0 = air is left out)."""
    p, g = _labels(labels_pred), _labels(labels_gt)
    if labels is None:
        labels = sorted(set(np.unique(p).tolist()) | set(np.unique(g).tolist()) - {0})
        labels = [int(v) for v in labels if v != 0]
    return {int(k): dice(p, g, int(k)) for k in labels}


def _labels(x) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x)


def surface_points_from_labels(mask, geometry, label: int | None = None, *, level: float = 0.5) -> np.ndarray:
    """Surface points (mm) of a binary material mask by marching cubes.

    Args:
        mask: ``[nx, ny, nz]`` boolean mask (e.g. ``labels == k``), or an integer
            label volume together with ``label``.
        geometry: the scene's :class:`~kneas_method.geometry.Geometry`; voxel
            ``[a, b, c]`` is centred at ``geometry.voxel_axes()`` (model units).
        label: if given, the mask is ``mask == label``.
        level: iso-level on the 0/1 mask.

    Returns:
        ``[P, 3]`` float64 vertices in mm in the scene's physical frame
        (``model units * geometry.mm_per_unit``); ``[0, 3]`` for an empty mask.
        The mask is padded by one empty voxel, so a material touching the
        volume's border still gives a closed surface.
    """
    import torch
    from skimage.measure import marching_cubes

    m = _labels(mask)
    if label is not None:
        m = m == label
    m = np.asarray(m, dtype=bool)
    if m.ndim != 3 or tuple(m.shape) != tuple(geometry.n_voxel):
        raise KneasError(f"mask shape {m.shape} does not match the geometry's volume {tuple(geometry.n_voxel)}; pass a mask on the scene's voxel grid")
    if not m.any():
        return np.zeros((0, 3))
    padded = np.pad(m.astype(np.float32), 1)
    spacing_mm = tuple(float(d) * geometry.mm_per_unit for d in geometry.d_voxel)
    verts, _faces, _n, _v = marching_cubes(padded, level=level, spacing=spacing_mm)
    first = np.array([float(ax[0]) for ax in geometry.voxel_axes(dtype=torch.float64)]) * geometry.mm_per_unit
    return verts.astype(np.float64) + (first - np.asarray(spacing_mm))[None]
