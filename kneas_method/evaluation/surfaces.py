"""Material labels and surface metrics of a trained model against a built-in scene's
exact ground truth (SPEC §5, last item).

Definitions
-----------
**Grids.** A model is queried on a rectilinear grid of cell centres covering the
scene's volume box: ``factor = 1`` is the scene's voxel grid
(:meth:`Geometry.voxel_centres`), ``factor = f`` splits every voxel into
``f^3`` cells (``Geometry.refined``). Queries run in chunks of ``chunk`` points,
under ``torch.no_grad``; results are float32 numpy arrays.

**Predicted material labels.** At each point the label is ``1 + argmax_k w_k``
(the selector's largest weight, materials ``k = 0..K-1`` in ascending attenuation),
or 0 (air) where the total weight ``Σ_k w_k`` is below ``air_threshold`` (0.5).

**Matching predicted materials to ground-truth labels.** K (model) and M
(ground truth) may differ, so each predicted material ``k`` is assigned to the
ground-truth label ``m in 0..M`` whose attenuation level (data units; air, label
0, at 0; the phantom's levels, or the mean ground-truth image over each label)
is nearest to the material's *mean predicted attenuation*: the mean of the model's ``mu`` over
the voxels labelled ``k`` (what it reconstructs where material ``k`` wins; for
the hard selector ``mu_1 Omega(d_1)`` this differs from the raw head value), or,
when no voxel is, the mean of the raw head ``mu_materials[:, k]`` over the
voxels where ``w_k`` is largest among materials, or else over all voxels. Several predicted
materials may map to one ground-truth label (their regions are merged); a
ground-truth label no material maps to gets Dice 0 and no predicted surface. A
material whose mean attenuation is nearest air's is air: its voxels count as
air and it has no surface (a model may hold the partial-volume voxels just
outside the object, a tenth of the lowest tissue's level, in a material of its
own; scoring them as that tissue would call air tissue).
The report also holds the overlap (Dice) matrix of every predicted material
with every ground-truth label, so other matchings can be read off it.

**Dice** per ground-truth label, on the scene's voxel grid: mapped predicted
labels against ``scene.labels`` (the exact membership at voxel centres).

**Surfaces**, points in mm in the scene's frame:

* ground truth: marching cubes (level 0.5) on the exact membership mask
  ``scene.membership(points) == m`` sampled on the fine grid (``factor``, default
  2 = twice the voxel resolution), via :func:`metrics.surface_points_from_labels`;
* prediction: marching cubes (level 0) on a signed field built from the SDFs
  ``d_k`` sampled on the same fine grid. The region the model shows as material
  ``k`` (sequential selector, hard limit: ``d_k < 0`` and not covered by a
  higher material) is exactly ``e_k < 0`` with
  ``e_k = max(d_k, max_{j > k} -d_j)`` (CSG intersection); for a ground-truth
  label ``m`` the field is ``min`` of ``e_k`` over the materials matched to
  ``m`` (union). Its zero level set is made of pieces of the zero sets of the
  ``d_k``: the part of ``d_k``'s surface that is visible, plus the surfaces of
  higher materials where they cut into ``k``. Using ``d_k``'s whole zero set
  instead would score surfaces hidden inside higher materials, where the
  projections do not constrain ``d_k`` at all.

**Partial-volume shells** (``shells=True``, the default for models): before scoring, the
pieces of a material that are nowhere thicker than about 1.5 voxels and lie between a lower
and a higher label (an edge's intermediate attenuation, not a layer of that material) take,
cell by cell, the neighbouring label whose level is nearest the attenuation there, on the
voxel grid (Dice) and on the surface grid (the fields are moved to agree); see
:mod:`kneas_method.evaluation.partial_volume`. The counts moved are in ``shell_cells_moved``.

Both point sets are padded by an outside layer so surfaces touching the volume
border close. Per label: Chamfer distance (symmetric and both directions, mm,
:func:`metrics.chamfer_distance`) and F-score with precision/recall at one
voxel (the smallest voxel side, mm; :func:`metrics.fscore`).
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from typing import Any, Callable, Optional, Sequence

import numpy as np
import torch

from ..errors import KneasError
from .metrics import chamfer_distance, dice_per_label, fscore, surface_points_from_labels
from .partial_volume import relabel_fields, relabel_shells, shell_counts

DEFAULT_AIR_THRESHOLD = 0.5
DEFAULT_CHUNK = 65536


# --------------------------------------------------------------------- grids
def grid_points(geometry, factor: int = 1, resolution: Optional[int] = None):
    """``(geometry', axes)``: the grid geometry and its per-axis cell centres (model units).

    ``resolution`` (if given) makes the longest axis that many cells, the others
    in proportion (same box), instead of ``factor``.
    """
    if resolution is not None:
        resolution = int(resolution)
        if resolution < 2:
            raise KneasError(f"--resolution must be at least 2, got {resolution}")
        size = [n * d for n, d in zip(geometry.n_voxel, geometry.d_voxel)]
        cell = max(size) / resolution
        n = tuple(max(2, int(round(s / cell))) for s in size)
        geo = dataclasses.replace(geometry, n_voxel=n, d_voxel=tuple(s / k for s, k in zip(size, n)))
    else:
        geo = geometry.refined(factor)
    return geo, geo.voxel_axes(dtype=torch.float32)


@torch.no_grad()
def query_grid(model, geometry, *, keys: Sequence[str] = ("mu", "weights", "distances", "mu_materials"),
               chunk: int = DEFAULT_CHUNK, device=None, dtype=np.float32) -> dict[str, np.ndarray]:
    """Query ``model.query`` at every cell centre of ``geometry``'s voxel grid.

    Args:
        model: a CTModel (or anything with ``query(points [P, 3]) -> dict``).
        geometry: grid geometry (e.g. from ``Geometry.refined``).
        keys: outputs to keep (missing ones, e.g. ``weights`` of a NAF model, are skipped).
        chunk: points per query; memory is ``chunk`` x the model's activations plus
            the outputs, ``nx·ny·nz·4`` bytes per scalar channel.

    Returns:
        ``{key: [nx, ny, nz] or [nx, ny, nz, K]}`` float32 (data units for ``mu``,
        model units for ``distances``).
    """
    if device is None:
        try:
            device = next(model.parameters()).device
        except (AttributeError, StopIteration):
            device = torch.device("cpu")
    xs, ys, zs = geometry.voxel_axes(dtype=torch.float32)
    nx, ny, nz = len(xs), len(ys), len(zs)
    out: dict[str, np.ndarray] = {}
    plane = ny * nz
    yz = torch.stack(torch.meshgrid(ys, zs, indexing="ij"), -1).reshape(-1, 2)  # [ny*nz, 2]
    total = nx * plane
    flat: dict[str, np.ndarray] = {}
    start = 0
    step = max(1, int(chunk))
    while start < total:
        stop = min(total, start + step)
        idx = torch.arange(start, stop)
        ix, r = idx // plane, idx % plane
        pts = torch.cat([xs[ix, None], yz[r]], -1).to(device)
        q = model.query(pts)
        for k in keys:
            v = q.get(k)
            if v is None:
                continue
            v = v.detach().float().cpu().numpy()
            if k not in flat:
                flat[k] = np.empty((total,) + v.shape[1:], dtype=dtype)
            flat[k][start:stop] = v
        start = stop
    for k, v in flat.items():
        out[k] = v.reshape((nx, ny, nz) + v.shape[1:])
    return out


# ------------------------------------------------------------------- labels
def labels_from_weights(weights, air_threshold: float = DEFAULT_AIR_THRESHOLD) -> np.ndarray:
    """Material labels ``[...]`` uint8 from selector weights ``[..., K]``:
    ``1 + argmax_k w_k``, or 0 (air) where ``Σ_k w_k < air_threshold``."""
    w = np.asarray(weights)
    lab = (np.argmax(w, axis=-1) + 1).astype(np.uint8)
    lab[w.sum(-1) < air_threshold] = 0
    return lab


def gt_levels(scene) -> np.ndarray:
    """Ground-truth attenuation per label 1..M (data units): the phantom's levels
    for built-in scenes, else the mean of ``scene.image`` over each label."""
    name = scene.meta.get("phantom") if isinstance(scene.meta, dict) else None
    if isinstance(name, str):
        try:
            from ..data.phantoms import PHANTOM_NAMES, get_phantom

            if name in PHANTOM_NAMES:
                return np.asarray(get_phantom(name).levels, dtype=np.float64)
        except ImportError:
            pass
    if scene.labels is None or scene.image is None:
        raise KneasError(f"scene {scene.name!r} has no ground-truth labels; material metrics need a built-in scene")
    M = int(scene.labels.max())
    return np.array([float(scene.image[scene.labels == m].mean()) if (scene.labels == m).any() else np.nan for m in range(1, M + 1)])


def material_mean_attenuation(mu_materials: np.ndarray, weights: np.ndarray, labels: np.ndarray,
                              mu: Optional[np.ndarray] = None) -> np.ndarray:
    """Mean predicted attenuation per material [K] (data units); see the module docs.

    With ``mu`` (the model's attenuation, the selector's output): the mean of ``mu``
    over the points labelled k, i.e. what the model reconstructs where material k
    wins. This matters for the hard selector, whose ``mu = mu_1 Omega(d_1)`` can
    reach a level with a partly occupied material (raw head value x occupancy).
    Materials labelled nowhere fall back to the raw head ``mu_materials[..., k]``
    where k has the largest weight, then everywhere."""
    K = mu_materials.shape[-1]
    mm = mu_materials.reshape(-1, K)
    lab = labels.reshape(-1)
    top = np.argmax(weights.reshape(-1, K), -1)
    flat_mu = None if mu is None else np.asarray(mu).reshape(-1)
    out = np.empty(K)
    for k in range(K):
        if flat_mu is not None and (lab == k + 1).any():
            out[k] = float(flat_mu[lab == k + 1].mean())
            continue
        for sel in (lab == k + 1, top == k, slice(None)):
            vals = mm[sel, k]
            if vals.size:
                out[k] = float(vals.mean())
                break
    return out


def voxel_labels(q: dict, air_threshold: float = DEFAULT_AIR_THRESHOLD, *, shells: bool = True) -> tuple[np.ndarray, np.ndarray, dict]:
    """A model's material labels on a grid, from its query there (``mu``, ``weights``,
    ``mu_materials``; :func:`query_grid`): ``(labels [...] uint8, mean attenuation [K], moved)``.
    Labels are :func:`labels_from_weights`, with partial-volume shells relabelled when ``shells``
    (:mod:`kneas_method.evaluation.partial_volume`; the grid is taken as the voxel grid); ``moved``
    counts the cells moved out of each material (``{"k": n}``)."""
    labels = labels_from_weights(q["weights"], air_threshold)
    mean_mu = material_mean_attenuation(q["mu_materials"], q["weights"], labels, mu=q.get("mu"))
    if not shells:
        return labels, mean_mu, {}
    cleaned = relabel_shells(labels, q["mu"], mean_mu, 1)
    return cleaned, mean_mu, {str(k): n for k, n in shell_counts(labels, cleaned).items()}


AIR_LEVEL = 0.0  # the attenuation of air (label 0), data units


def match_materials(mean_mu: Sequence[float], levels: Sequence[float]) -> list[int]:
    """Ground-truth label for each predicted material ``[K]``: the one (0 = air at
    ``AIR_LEVEL``, 1..M at ``levels [M]``) whose level is nearest its mean attenuation."""
    lv = np.concatenate([[AIR_LEVEL], np.asarray(levels, dtype=np.float64)])
    lv = np.where(np.isfinite(lv), lv, np.inf)
    return [int(np.argmin(np.abs(lv - float(m)))) for m in mean_mu]


def map_labels(pred_labels: np.ndarray, matching: Sequence[int]) -> np.ndarray:
    """Predicted labels 0..K -> ground-truth labels 0..M through ``matching`` (0 = air)."""
    lut = np.concatenate([[0], np.asarray(matching, dtype=np.int64)]).astype(np.uint8)
    return lut[pred_labels]


def visible_fields(distances: np.ndarray) -> np.ndarray:
    """``e_k = max(d_k, max_{j>k} -d_j)`` ``[..., K]``: negative exactly where material ``k``
    is the visible one (hard limit of the sequential selector)."""
    d = np.asarray(distances, dtype=np.float32)
    e = d.copy()
    cover = None  # max_{j>k} -d_j, built from the top
    for k in range(d.shape[-1] - 1, -1, -1):
        if cover is not None:
            np.maximum(e[..., k], cover, out=e[..., k])
            cover = np.maximum(cover, -d[..., k])
        else:
            cover = -d[..., k]
    return e


def visible_labels(fields: np.ndarray) -> np.ndarray:
    """Labels ``[...]`` uint8 of visible-region fields ``[..., K]`` (:func:`visible_fields`): ``1 + k``
    where ``e_k < 0``, 0 (air) where none is."""
    neg = np.asarray(fields) < 0
    return np.where(neg.any(-1), np.argmax(neg, -1) + 1, 0).astype(np.uint8)


def shell_free_fields(model, geometry, levels: Sequence[float], voxel_geometry, *, chunk: int = DEFAULT_CHUNK,
                      moved: Optional[dict] = None) -> np.ndarray:
    """Visible-region fields ``[nx, ny, nz, K]`` of ``model`` on ``geometry``'s grid with its
    partial-volume shells relabelled (:mod:`kneas_method.evaluation.partial_volume`).

    Args:
        levels: ``[K]`` the materials' attenuations (data units; :func:`material_mean_attenuation`).
        voxel_geometry: the scene's grid, whose voxel sets the shells' scale on this grid.
        moved: if given, ``moved["cells"]`` is set to the cells moved out of each material.
    """
    f = query_grid(model, geometry, keys=("distances", "mu"), chunk=chunk)
    e = visible_fields(f["distances"])
    labels = visible_labels(e)
    cells_per_voxel = max(1, int(round(min(voxel_geometry.d_voxel) / min(geometry.d_voxel))))
    cleaned = relabel_shells(labels, f["mu"], levels, cells_per_voxel)
    if moved is not None:
        moved["cells"] = {str(k): n for k, n in shell_counts(labels, cleaned).items()}
    return relabel_fields(e, labels, cleaned, margin=0.5 * float(min(geometry.d_voxel)))  # signed distances: half a cell


def _sdf_surface_points(field: np.ndarray, geometry) -> np.ndarray:
    """Zero level set (marching cubes) of ``field`` [nx, ny, nz] on ``geometry``'s
    grid, in mm; padded with an outside layer. ``[0, 3]`` when there is none."""
    from skimage.measure import marching_cubes

    f = np.asarray(field, dtype=np.float32)
    if f.size == 0 or not float(f.min()) < 0.0:
        return np.zeros((0, 3))
    padded = np.pad(f, 1, constant_values=max(float(np.abs(f).max()), 1e-3))
    spacing = tuple(float(d) * geometry.mm_per_unit for d in geometry.d_voxel)
    verts, _f, _n, _v = marching_cubes(padded, level=0.0, spacing=spacing)
    first = np.array([float(ax[0]) for ax in geometry.voxel_axes(dtype=torch.float64)]) * geometry.mm_per_unit
    return verts.astype(np.float64) + (first - np.asarray(spacing))[None]


def membership_grid(scene, geometry, chunk: int = 1_000_000) -> np.ndarray:
    """Exact ground-truth labels [nx, ny, nz] uint8 at ``geometry``'s cell centres (model
    units) from ``scene.membership``, in chunks."""
    if scene.membership is None:
        raise KneasError(f"scene {scene.name!r} has no exact membership function; surface metrics need a built-in scene")
    name = scene.meta.get("phantom") if isinstance(scene.meta, dict) else None
    if isinstance(name, str):  # built-in phantom: the same exact labels, on its fast rectilinear-grid path
        from ..data.phantoms import PHANTOM_NAMES, get_phantom

        if name in PHANTOM_NAMES:
            return np.asarray(get_phantom(name).labels(geometry), dtype=np.uint8)
    xs, ys, zs = (a.numpy() for a in geometry.voxel_axes(dtype=torch.float64))
    out = np.empty((len(xs), len(ys), len(zs)), dtype=np.uint8)
    yy, zz = np.meshgrid(ys, zs, indexing="ij")
    yz = np.stack([yy.reshape(-1), zz.reshape(-1)], -1)
    rows = max(1, chunk // max(1, len(yz)))
    for i0 in range(0, len(xs), rows):
        xi = xs[i0 : i0 + rows]
        pts = np.concatenate([np.repeat(xi, len(yz))[:, None], np.tile(yz, (len(xi), 1))], -1)
        out[i0 : i0 + len(xi)] = np.asarray(scene.membership(pts)).reshape(len(xi), len(ys), len(zs))
    return out


def _dice_matrix(pred_labels: np.ndarray, gt_labels: np.ndarray, K: int, M: int) -> list[list[float]]:
    rows = []
    for k in range(1, K + 1):
        a = pred_labels == k
        row = []
        for m in range(1, M + 1):
            b = gt_labels == m
            den = int(a.sum()) + int(b.sum())
            row.append(1.0 if den == 0 else 2.0 * int(np.logical_and(a, b).sum()) / den)
        rows.append(row)
    return rows


# ------------------------------------------------------------------ metrics
def material_metrics(
    model,
    scene,
    *,
    factor: int = 2,
    air_threshold: float = DEFAULT_AIR_THRESHOLD,
    chunk: int = DEFAULT_CHUNK,
    surfaces: bool = True,
    shells: bool = True,
    progress: Optional[Callable[[str], None]] = None,
) -> dict[str, Any]:
    """Per-material label Dice and surface errors of an SDF model (module docs).

    Args:
        model: CTModel with an SDF (``has_surfaces``), or an object with ``query`` giving
            ``weights``, ``distances``, ``mu_materials`` and ``num_materials``.
        scene: built-in scene (``labels`` and ``membership`` present).
        factor: fine-grid factor for the surfaces (2 = twice the voxel resolution).
        air_threshold: total weight below which a point is air.
        surfaces: also compute Chamfer/F-score (needs ``scene.membership``).
        shells: relabel partial-volume shells, on the voxel grid and on the surface grid
            (:mod:`kneas_method.evaluation.partial_volume`); False scores the fields as they are.
        progress: called with one line as each phase starts (None: silent).

    Returns:
        JSON-able dict: ``matching`` (per predicted material: GT label, name, mean
        predicted attenuation), ``gt_levels``, ``dice_matrix``, ``materials`` (per
        GT material: ``dice``, ``chamfer_mm``, ``chamfer_pred_to_gt_mm``,
        ``chamfer_gt_to_pred_mm``, ``fscore``, ``precision``, ``recall``), the
        means ``dice_mean``, ``chamfer_mm_mean``, ``fscore_mean`` and the settings.
    """
    if not getattr(model, "has_surfaces", True):
        raise KneasError("material metrics need a model with signed distance fields; NAF/FDK volumes have no materials")
    _check_labels(scene)
    geo = scene.geometry
    say = progress or (lambda line: None)
    say(f"materials: the model's labels at the {math.prod(geo.n_voxel):,} voxel centres")
    q = query_grid(model, geo, keys=("mu", "weights", "mu_materials"), chunk=chunk)
    if "weights" not in q:
        raise KneasError("the model's query gives no material weights; it has no materials")
    pred, mean_mu, moved_voxels = voxel_labels(q, air_threshold, shells=shells)
    moved: dict[str, dict] = {"voxels": moved_voxels} if shells else {}
    del q

    def visible(fgeo):  # [..., K] fields negative where each material is the visible one
        if not shells:
            return visible_fields(query_grid(model, fgeo, keys=("distances",), chunk=chunk)["distances"])
        fine_moved: dict = {}
        e = shell_free_fields(model, fgeo, mean_mu, geo, chunk=chunk, moved=fine_moved)
        moved["surface_grid_cells"] = fine_moved["cells"]
        return e

    definition = ("labels: 1+argmax weight, air where total weight < air_threshold; predicted material k -> GT label with the "
                  "nearest attenuation level (air at 0 included) to the mean predicted attenuation mu where it is the label; surfaces: visible-region SDF "
                  "e_k = max(d_k, max_{j>k} -d_j) vs exact membership, marching cubes on a grid refined by grid_factor, mm")
    if shells:
        definition += ("; partial-volume shells (the thin cells of a material's pieces nowhere thicker than 1.5 voxels, with a "
                       "lower and a higher label within one voxel) relabelled to the neighbouring label of the nearest level, on both grids")
    settings = {"air_threshold": float(air_threshold), "grid_factor": int(factor), "shells_relabelled": bool(shells),
                "shell_cells_moved": moved}
    return _score_materials(scene, pred, mean_mu, visible if surfaces else None, fine=factor, definition=definition,
                            settings=settings, progress=say)


def threshold_labels(volume, boundaries: Sequence[float], air_cut: float) -> np.ndarray:
    """Material labels of a volume [nx, ny, nz] by thresholds: 0 (air) where ``mu < air_cut``,
    else ``1 + k`` for ``boundaries[k] <= mu < boundaries[k+1]`` (the last class open above)."""
    v = np.asarray(volume, dtype=np.float32)
    inner = np.asarray(boundaries, dtype=np.float64)[1:-1]
    lab = (np.searchsorted(inner, v, side="right") + 1).astype(np.uint8)
    lab[v < air_cut] = 0
    return lab


def threshold_fields(volume, boundaries: Sequence[float], air_cut: float) -> np.ndarray:
    """Signed fields [nx, ny, nz, K] (data units), negative exactly where :func:`threshold_labels`
    gives class k: ``max(lo_k - mu, mu - hi_k)`` with ``lo_0 = air_cut`` and ``hi_{K-1} = inf``."""
    v = np.asarray(volume, dtype=np.float32)
    b = [float(x) for x in boundaries]
    K = len(b) - 1
    lo = [max(air_cut, b[0])] + b[1:K]
    out = np.empty(v.shape + (K,), dtype=np.float32)
    for k in range(K):
        out[..., k] = lo[k] - v if k == K - 1 else np.maximum(lo[k] - v, v - b[k + 1])
    return out


def volume_material_metrics(volume, scene, *, seed: int = 0, max_components: int = 4, k_rule: str = "bic", min_std: float = 0.0,
                            restarts: int = 1, surfaces: bool = True, shells: bool = False, fit_values=None,
                            fit_values_are: str = "", boundaries: Optional[Sequence[float]] = None,
                            boundaries_are: str = "") -> dict[str, Any]:
    """Per-material Dice and surface errors of a voxel volume [nx, ny, nz] (data units; a
    classical reconstruction or a NAF field sampled at the voxel centres), segmented the way a
    user would: thresholds at the automatic GMM bounds fitted on the volume itself
    (:class:`~kneas_method.bounds.GMMBounds`, K up to ``max_components`` by ``k_rule``, components
    at least ``min_std`` wide, the best of ``restarts`` starts; the defaults are the paper's rule), air below half
    the lowest class mean. Classes are matched to ground-truth labels like a model's materials;
    surfaces are the iso-surfaces of the thresholds (marching cubes of :func:`threshold_fields`
    on the voxel grid). ``shells`` relabels the thresholded volume's partial-volume shells as
    :func:`material_metrics` does a model's (off by default: thresholding is what a user of a
    classical volume does; ``benchmarks/classical.py --shells`` scores both ways). ``fit_values``: the
    values the bounds are fitted on instead of the volume's (the refine-classical procedure's at-noise
    rule fits a noisy start after a filter; ``fit_values_are`` says what they are); the volume itself is
    thresholded. ``boundaries`` [K + 1]: thresholds given instead of the GMM's (a K-material model's own
    bounds, ``kneas-eval --materials values``; ``boundaries_are`` says whose), air then below half the mean of
    the volume's values in the first class. Same keys as :func:`material_metrics`, plus ``boundaries`` and
    ``air_cut``."""
    from ..bounds import GMMBounds

    _check_labels(scene)
    vol = np.asarray(volume, dtype=np.float32)
    boundaries_given = boundaries is not None
    if not boundaries_given:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the GMM's remarks are kept in the result's notes
            gmm = GMMBounds(random_state=int(seed), max_components=max_components, k_rule=k_rule, min_std=min_std,
                            n_init=int(restarts)).fit(vol if fit_values is None else np.asarray(fit_values, dtype=np.float32))
        boundaries = [float(x) for x in gmm.boundaries_]
        centres = [float(m) for m in gmm.means_]
    else:
        boundaries = [float(x) for x in boundaries]
        centres = [0.5 * (lo + hi) for lo, hi in zip(boundaries[:-1], boundaries[1:])]
        first = vol[(vol >= boundaries[0]) & (vol < boundaries[1])]
        if first.size:
            centres[0] = float(first.mean())
    air_cut = 0.5 * centres[0]
    pred = threshold_labels(vol, boundaries, air_cut)
    K = len(boundaries) - 1
    mean_mu = np.array([float(vol[pred == k + 1].mean()) if (pred == k + 1).any() else centres[k] for k in range(K)])
    fields = threshold_fields(vol, boundaries, air_cut)
    moved: dict[str, dict] = {}
    if shells:
        cleaned = relabel_shells(pred, vol, mean_mu, 1)
        moved["voxels"] = {str(k): n for k, n in shell_counts(pred, cleaned).items()}
        fields = relabel_fields(fields, pred, cleaned)
        pred = cleaned
    fitted_on = "the volume" if fit_values is None else (fit_values_are or "values given beside the volume")
    thresholds = (f"thresholds at the GMM bounds fitted on {fitted_on} (K = 1..{max_components} by {k_rule}, min_std {min_std:g}, "
                  f"{restarts} start(s))" if not boundaries_given else f"thresholds at {boundaries_are or 'given bounds'}")
    definition = (f"labels: {thresholds}, air below half the lowest class mean; "
                  + ("partial-volume shells relabelled as for a model's; " if shells else "") +
                  "class k -> GT label with the nearest attenuation level (air at 0 included) to the class's mean mu; surfaces: iso-surfaces of the "
                  "thresholds (marching cubes on the voxel grid) vs exact membership on a grid refined by 2, mm")
    settings = {"boundaries": boundaries, "air_cut": air_cut, "K": K, "shells_relabelled": bool(shells), "shell_cells_moved": moved}
    if boundaries_given:
        settings["boundaries_are"] = boundaries_are or "given"
    else:
        settings.update(notes=list(gmm.warnings_), gmm={"max_components": max_components, "k_rule": k_rule, "k_rule_used": gmm.k_rule_used_,
                                                        "min_std": min_std, "restarts": int(restarts), "fitted_on": fitted_on})
    return _score_materials(scene, pred, mean_mu, (lambda fgeo: fields) if surfaces else None, fine=2,
                            definition=definition, settings=settings, field_geometry=scene.geometry)


def _check_labels(scene) -> None:
    if scene.labels is None:
        raise KneasError(f"scene {scene.name!r} has no ground-truth labels; material metrics need a built-in scene")


def _score_materials(scene, pred: np.ndarray, mean_mu: np.ndarray, fields, *, fine: int, definition: str, settings: dict,
                     field_geometry=None, progress: Optional[Callable[[str], None]] = None) -> dict[str, Any]:
    """Dice (and, with ``fields(geometry) -> [..., K]`` signed fields, Chamfer / F-score) of
    predicted labels ``pred`` (0 air, 1..K) whose classes have mean attenuation ``mean_mu [K]``.
    The fields are sampled on ``field_geometry`` (default: the scene's grid refined by ``fine``)."""
    geo = scene.geometry
    K = len(mean_mu)
    levels = gt_levels(scene)
    M = len(levels)
    names = list(scene.materials) if len(scene.materials) == M else [f"label {m}" for m in range(1, M + 1)]
    matching = match_materials(mean_mu, levels)
    mapped = map_labels(pred, matching)
    gt = np.asarray(scene.labels)
    dices = dice_per_label(mapped, gt, labels=list(range(1, M + 1)))
    voxel_mm = float(min(geo.d_voxel)) * geo.mm_per_unit
    per: dict[str, dict] = {}
    for m in range(1, M + 1):
        per[names[m - 1]] = {"label": m, "level": float(levels[m - 1]), "dice": float(dices[m]),
                             "predicted_materials": [k + 1 for k in range(K) if matching[k] == m]}
    result: dict[str, Any] = {
        "definition": definition,
        **settings,
        "fscore_threshold_mm": voxel_mm,
        "gt_levels": [float(v) for v in levels],
        "matching": [{"material": k + 1, "mean_mu": float(mean_mu[k]), "gt_label": int(matching[k]),
                      "gt_name": names[matching[k] - 1] if matching[k] else "air"} for k in range(K)],
        "dice_matrix": _dice_matrix(pred, gt, K, M),
        "materials": per,
    }
    if fields is not None:
        say = progress or (lambda line: None)
        fgeo = geo.refined(fine)
        pgeo = field_geometry or fgeo
        say(f"surfaces: the signed distances on the {fine}x grid ({math.prod(pgeo.n_voxel):,} points) and the exact membership")
        e = fields(pgeo)
        gt_fine = membership_grid(scene, fgeo)
        for m in range(1, M + 1):
            entry = per[names[m - 1]]
            say(f"surfaces: {names[m - 1]} ({m}/{M}), marching cubes and distances")
            ks = [k for k in range(K) if matching[k] == m]
            gt_pts = surface_points_from_labels(gt_fine == m, fgeo)
            pred_pts = _sdf_surface_points(np.min(e[..., ks], axis=-1), pgeo) if ks else np.zeros((0, 3))
            entry["gt_surface_points"] = int(len(gt_pts))
            entry["pred_surface_points"] = int(len(pred_pts))
            if len(gt_pts) == 0 or len(pred_pts) == 0:
                entry.update(chamfer_mm=None, chamfer_pred_to_gt_mm=None, chamfer_gt_to_pred_mm=None,
                             fscore=0.0 if len(gt_pts) else None, precision=None, recall=None,
                             note="no predicted surface" if len(gt_pts) else "material absent from the ground truth")
                continue
            c, ab, ba = chamfer_distance(pred_pts, gt_pts)
            f, p, r = fscore(pred_pts, gt_pts, voxel_mm, return_pr=True)
            entry.update(chamfer_mm=c, chamfer_pred_to_gt_mm=ab, chamfer_gt_to_pred_mm=ba, fscore=f, precision=p, recall=r)
    vals = list(per.values())
    result["dice_mean"] = float(np.mean([v["dice"] for v in vals]))
    ch = [v["chamfer_mm"] for v in vals if v.get("chamfer_mm") is not None]
    fs = [v["fscore"] for v in vals if v.get("fscore") is not None]
    if fields is not None:
        result["chamfer_mm_mean"] = float(np.mean(ch)) if ch else None
        result["fscore_mean"] = float(np.mean(fs)) if fs else None
    return result
