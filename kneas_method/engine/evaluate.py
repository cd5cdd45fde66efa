"""The shared evaluation of a trained model or a reconstructed volume (SPEC §5).

Used by ``kneas-train`` at the end of a run and by ``kneas-eval``:

* :func:`evaluate_model` ``(model, scene, config, device) -> dict``: 2D metrics on
  **all** held-out views and 3D metrics on the model's attenuation sampled at the
  voxel centres, data units. The held-out projections are rendered through the field
  (``config.model.num_eval_samples`` evenly spaced points per ray,
  ``config.trainer.eval_chunk`` rays at a time) or projected from that volume
  (``config.trainer.eval_projections``; :func:`model_arrays`).
* :func:`evaluate_volume` ``(volume, scene) -> dict``: the same metrics for a
  voxel volume (FDK): 2D metrics by forward-projecting the volume to the
  held-out views (``classical.projector.forward``, Joseph), 3D metrics directly.

Both return JSON-able dicts: ``psnr2d``, ``ssim2d`` (means over the held-out
views), ``psnr2d_per_view``, ``ssim2d_per_view``, ``n_views``, ``projections_2d``
(``rendered`` or ``volume``: how the held-out projections were made); with a ground
truth volume ``psnr3d``, ``ssim3d`` (exact unit conversion, peak 1, no fitting),
``psnr3d_ls``, ``ssim3d_ls``, ``ls_scale``, ``mse3d``. The helpers
:func:`render_views` and :func:`sample_volume` return the arrays behind them
(for figures and exports).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np
import torch

from ..data.truncation import fitting_scene
from ..evaluation.metrics import projection_metrics, volume_metrics

__all__ = ["evaluate_model", "evaluate_volume", "render_views", "sample_volume", "model_metrics_from_arrays",
           "model_arrays", "held_out_projections", "eval_projections", "Evaluation", "evaluate_model_stage"]

Progress = Optional[Callable[[int, int], None]]


def _chunk(config, default: int = 4096) -> int:
    try:
        return int(config.trainer.eval_chunk or default)
    except AttributeError:
        return default


def _eval_samples(config) -> Optional[int]:
    try:
        return config.model.num_eval_samples
    except AttributeError:
        return None


@torch.no_grad()
def render_views(model, scene, angles, *, device="cpu", chunk: int = 4096, n_samples: Optional[int] = None,
                 progress: Progress = None) -> np.ndarray:
    """Render the views at ``angles`` [N] (rad): line integrals [N, nV, nU] (float32).

    Evenly spaced samples (``n_samples``, default the model's ``num_eval_samples``). With an
    occupancy grid only the rays that cross it are rendered; the others are exactly 0
    (``CTModel.rays_through_occupied``). ``progress(done_rays, total_rays)`` is called after every chunk.
    """
    was_training = model.training
    model.eval()
    geometry = scene.geometry
    near, far = geometry.near_far
    nu, nv = geometry.n_detector
    angles = np.asarray(angles, dtype=np.float64).reshape(-1)
    out = np.zeros((len(angles), nv, nu), dtype=np.float32)
    per_view = nu * nv
    total = len(angles) * per_view
    try:
        for k, a in enumerate(angles):
            origins, directions = geometry.rays(angles[k : k + 1], device=device)
            origins, directions = origins.reshape(-1, 3), directions.reshape(-1, 3)
            line = torch.zeros(len(origins), dtype=torch.float32)
            hit = model.rays_through_occupied(origins, directions, near, far)
            rays = torch.arange(len(origins), device=origins.device) if hit is None else hit.nonzero().reshape(-1)
            for i in range(0, len(rays), chunk):
                j = rays[i : i + chunk]
                r = model.render(origins[j], directions[j], near, far, n_samples, stratified=False)
                line[j.cpu()] = r.line_integral.float().cpu()
                if progress is not None:  # in rays of the whole detector
                    progress(k * per_view + per_view * min(i + chunk, len(rays)) // len(rays), total)
            if progress is not None and len(rays) == 0:
                progress((k + 1) * per_view, total)
            out[k] = line.reshape(nv, nu).numpy()
    finally:
        model.train(was_training)
    return out


@torch.no_grad()
def sample_volume(model, geometry, *, device="cpu", chunk: int = 65536, progress: Progress = None) -> np.ndarray:
    """The model's attenuation ``mu`` (data units) at the voxel centres: [nx, ny, nz] float32.

    With an occupancy grid the field is queried only at the centres inside it; the others are
    exactly 0 (``CTModel.compose``)."""
    was_training = model.training
    model.eval()
    pts = geometry.voxel_centres(device=device).reshape(-1, 3)
    out = torch.zeros(len(pts), dtype=torch.float32)
    occupied = model.occupied(pts)
    cells = torch.arange(len(pts), device=pts.device) if occupied is None else (occupied > 0).nonzero().reshape(-1)
    try:
        for i in range(0, len(cells), chunk):
            j = cells[i : i + chunk]
            out[j.cpu()] = model.query(pts[j])["mu"].float().cpu()
            if progress is not None:  # in voxels of the whole grid
                progress(len(pts) * min(i + chunk, len(cells)) // max(1, len(cells)), len(pts))
    finally:
        model.train(was_training)
    return out.reshape(tuple(geometry.n_voxel)).numpy()


def model_metrics_from_arrays(pred_proj: np.ndarray, scene, volume: Optional[np.ndarray]) -> dict:
    """Metrics dict from rendered held-out projections [N, nV, nU] and a volume [nx, ny, nz] (data units)."""
    out = projection_metrics(pred_proj, np.asarray(scene.val.projections))
    if volume is not None and scene.image is not None:
        out.update(volume_metrics(volume, np.asarray(scene.image, dtype=np.float32)))
    return out


def eval_projections(config) -> str:
    """How a run's final evaluation makes its held-out projections: ``rendered`` or ``volume``
    (``trainer.eval_projections``; ``rendered`` for configs written before it existed)."""
    try:
        return config.trainer.eval_projections or "rendered"
    except AttributeError:
        return "rendered"


def model_arrays(model, scene, config, device, *, views: Progress = None, voxels: Progress = None,
                 fitting=None) -> tuple[np.ndarray, np.ndarray]:
    """The held-out projections ``[N, nV, nU]`` and the volume at the voxel centres ``[nx, ny, nz]``
    (data units) that score a model.

    Where the run fitted the views on a longer box (``fitting``, by default
    ``data.truncation.fitting_scene(scene)``), the held-out views see that box, what lies beyond
    the scene's included, and the volume is the scene's part of it.

    The projections are rendered through the field (:func:`render_views`) or, with
    ``trainer.eval_projections = volume``, the volume projected by the Joseph projector
    (``classical.projector.forward``, as :func:`evaluate_volume` scores a classical volume;
    the test suite checks that both agree on a smooth field). ``views(done, total)`` reports
    held-out views, ``voxels(done, total)`` voxels.
    """
    device = torch.device(device)
    box = fitting_scene(scene) if fitting is None else fitting
    fitted = sample_volume(model, box.scene.geometry, device=device, progress=voxels)
    proj = held_out_projections(model, box.scene, config, device, scene.val.angles, volume=fitted, progress=views)
    return proj, np.ascontiguousarray(box.crop(fitted))


def held_out_projections(model, scene, config, device, angles, *, volume: Optional[np.ndarray] = None,
                         progress: Progress = None) -> np.ndarray:
    """The model's projections [N, nV, nU] at ``angles`` [N] as the run's evaluation makes them
    (:func:`eval_projections`): rendered through the field, or its ``volume`` at the voxel centres
    (sampled here when not given) projected by the Joseph projector. ``progress(done, total)``
    reports views. The validation during training (``Trainer.validate``) makes them this way too."""
    from ..classical.projector import forward

    angles = np.asarray(angles, dtype=np.float64).reshape(-1)
    if eval_projections(config) == "volume":
        if volume is None:
            volume = sample_volume(model, scene.geometry, device=device)
        return forward(volume, scene.geometry, angles, progress=progress)
    nu, nv = scene.geometry.n_detector
    rays = None if progress is None else (lambda done, total: progress(done / (nu * nv), len(angles)))
    return render_views(model, scene, angles, device=device, chunk=_chunk(config), n_samples=_eval_samples(config), progress=rays)


def evaluate_model(model, scene, config, device, *, return_arrays: bool = False):
    """2D metrics on all held-out views and 3D metrics at the voxel centres (data units).

    Args:
        model: a :class:`~kneas_method.model.CTModel` (bounds set, weights loaded).
        scene: the scene (its ``val`` views are the held-out views; ``image`` the
            ground truth, if any).
        config: the resolved TrainConfig (``trainer.eval_projections``, and for rendered
            projections ``model.num_eval_samples`` and ``trainer.eval_chunk``).
        device: torch device the model lives on.
        return_arrays: also return ``(projections [N, nV, nU], volume [nx, ny, nz])``.

    Returns:
        The metrics dict (see the module docstring; ``projections_2d`` says how the
        projections were made), or ``(metrics, arrays)``.
    """
    proj, volume = model_arrays(model, scene, config, device)
    metrics = model_metrics_from_arrays(proj, scene, volume)
    metrics["projections_2d"] = eval_projections(config)
    return (metrics, (proj, volume)) if return_arrays else metrics


def evaluate_volume(volume, scene, *, return_arrays: bool = False, progress: Progress = None, fitted=None):
    """Metrics of a voxel volume [nx, ny, nz] (data units, the scene's grid).

    2D: the volume is forward-projected (Joseph projector, one sample per voxel slice) to every
    held-out view and scored like a model's rendering; 3D: compared with the
    ground truth, if any. ``progress(done_views, total_views)``. ``fitted``: ``(geometry,
    volume)``, the reconstruction on the longer box the views were fitted on, whose middle is
    ``volume`` (``data.truncation.FittingBox``); the held-out views are projected from it then.
    """
    from ..classical.projector import forward

    vol = np.asarray(volume.detach().cpu() if hasattr(volume, "detach") else volume, dtype=np.float32)
    geometry, projected = (scene.geometry, vol) if fitted is None else fitted
    proj = forward(projected, geometry, np.asarray(scene.val.angles), progress=progress)
    metrics = model_metrics_from_arrays(proj, scene, vol)
    metrics["projections_2d"] = "volume"
    return (metrics, (proj, vol)) if return_arrays else metrics


@dataclass
class Evaluation:
    """A run's evaluation: the metrics dict, the rendered held-out projections ``[N, nV, nU]``,
    the volume at the voxel centres ``[nx, ny, nz]`` (data units; None when not sampled) and seconds."""

    metrics: dict
    projections: np.ndarray
    volume: Optional[np.ndarray]
    seconds: float


def evaluate_model_stage(model, scene, config, device, console, fitting=None) -> Evaluation:
    """:func:`evaluate_model` with progress shown (voxels, then held-out views) on ``console``
    (``fitting``: as :func:`model_arrays`).

    The volume at the voxel centres is always sampled: 3D metrics where the scene has a
    ground truth, the slice figure in any case."""
    from .progress import stage_progress

    t0 = time.perf_counter()
    how = eval_projections(config)
    fitting = fitting_scene(scene) if fitting is None else fitting
    n_views, n_voxels = len(scene.val), int(np.prod(fitting.scene.geometry.n_voxel))
    info = (f"{n_views} held-out views projected from the volume (Joseph)" if how == "volume"
            else f"{n_views} held-out views x {_eval_samples(config)} samples")
    with stage_progress(console, unit="views") as progress:
        vtask = progress.add_task("volume", total=n_voxels, info="attenuation at the voxel centres", unit="voxels")
        task = progress.add_task("evaluation", total=n_views, info=info)
        proj, volume = model_arrays(model, scene, config, device, views=lambda d, t: progress.update(task, completed=d),
                                    voxels=lambda d, t: progress.update(vtask, completed=d), fitting=fitting)
    metrics = model_metrics_from_arrays(proj, scene, volume)
    metrics["projections_2d"] = how
    return Evaluation(metrics, proj, volume, time.perf_counter() - t0)


def evaluate_volume_stage(volume, scene, console, fitted=None) -> Evaluation:
    """:func:`evaluate_volume` with progress shown (held-out views projected) on ``console``."""
    from .progress import stage_progress

    t0 = time.perf_counter()
    with stage_progress(console, unit="views") as progress:
        task = progress.add_task("evaluation", total=len(scene.val), info="projecting the volume to the held-out views")
        metrics, (proj, vol) = evaluate_volume(volume, scene, return_arrays=True, fitted=fitted,
                                                 progress=lambda d, t: progress.update(task, completed=d))
    return Evaluation(metrics, proj, vol, time.perf_counter() - t0)
