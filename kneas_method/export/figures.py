"""Figures of a trained run (``kneas-export figures``, also drawn by ``kneas-eval``).

PNG files, matplotlib Agg, reusing :mod:`kneas_method.engine.figures`:

* ``projection-<i>.png``: held-out view ``i``: prediction, ground truth, error,
  as intensity ``exp(-p)`` (``views`` of them, spread over the held-out set);
* ``slices.png``: three orthogonal middle slices of the attenuation (data
  units) with the ground truth and the error when the scene has one;
* ``weights.png``: per-material selector weights ``w_k`` on the same three
  slices (SDF methods), and ``labels.png``: predicted material labels beside
  the ground-truth labels (built-in scenes).
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

from ..engine.figures import _plt, middle_slices, plot_projection_comparison, plot_slice_comparison, save_figure


def plot_weight_maps(weights: np.ndarray, path, title: str = "") -> Path:
    """Per-material weights ``[nx, ny, nz, K]`` on three orthogonal middle slices (rows = materials)."""
    plt = _plt()
    K = weights.shape[-1]
    fig, axes = plt.subplots(K, 3, figsize=(10, 3.2 * K), squeeze=False)
    for k in range(K):
        slices, names = middle_slices(weights[..., k])
        for col, (sl, axis) in enumerate(zip(slices, names)):
            ax = axes[k, col]
            im = ax.imshow(sl.T, cmap="magma", vmin=0.0, vmax=1.0, origin="lower")
            ax.set_title(f"w_{k + 1}, {axis} = middle")
            ax.axis("off")
        fig.colorbar(im, ax=axes[k].tolist(), fraction=0.02)
    fig.suptitle(title)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return Path(path)


def plot_label_maps(pred: np.ndarray, gt: Optional[np.ndarray], path, title: str = "") -> Path:
    """Predicted (and ground-truth) label volumes on three orthogonal middle slices."""
    plt = _plt()
    rows = [("predicted labels", pred)] + ([("ground-truth labels", gt)] if gt is not None else [])
    top = max(int(np.max(v)) for _, v in rows) if rows else 1
    fig, axes = plt.subplots(len(rows), 3, figsize=(10, 3.3 * len(rows)), squeeze=False)
    for r, (name, vol) in enumerate(rows):
        slices, names = middle_slices(vol)
        for col, (sl, axis) in enumerate(zip(slices, names)):
            ax = axes[r, col]
            ax.imshow(sl.T, cmap="tab10", vmin=0, vmax=max(9, top), origin="lower", interpolation="nearest")
            ax.set_title(f"{name}, {axis} = middle")
            ax.axis("off")
    fig.suptitle(title)
    return save_figure(fig, path)


def pick_views(n_total: int, n: Optional[int]) -> np.ndarray:
    """``n`` held-out view indices spread over ``0..n_total-1`` (all when ``n`` is None, none when 0)."""
    if n is not None and n <= 0:
        return np.arange(0)
    if n is None or n >= n_total:
        return np.arange(n_total)
    return np.unique(np.round(np.linspace(0, n_total - 1, max(1, n))).astype(int))


def export_figures(
    run,
    out_dir,
    *,
    views: Optional[int] = 3,
    projections: Optional[np.ndarray] = None,
    volume: Optional[np.ndarray] = None,
    chunk: int = 65536,
) -> list[Path]:
    """Draw the figures of the module docs into ``out_dir``; returns the paths.

    ``projections`` (rendered held-out views [N, nV, nU], all of them) and
    ``volume`` ([nx, ny, nz] data units) are reused when given (``kneas-eval``
    has them already); otherwise they are computed.
    """
    from ..engine.evaluate import render_views
    from ..evaluation.surfaces import query_grid, voxel_labels

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    scene, title = run.scene, f"{run.config.method} on {run.scene.name}"
    written: list[Path] = []
    idx = pick_views(len(scene.val), views)
    if len(idx) == 0:
        projections_sel = None
    elif projections is None:
        if run.model is not None:
            dev = next(run.model.parameters()).device
            eval_chunk = getattr(run.config.trainer, "eval_chunk", None) or 4096
            projections_sel = render_views(run.model, scene, np.asarray(scene.val.angles)[idx], device=dev, chunk=eval_chunk,
                                           n_samples=run.config.model.num_eval_samples)
        else:
            from ..classical.projector import forward

            projections_sel = forward(np.asarray(run.volume, dtype=np.float32), scene.geometry, np.asarray(scene.val.angles)[idx])
    else:
        projections_sel = np.asarray(projections)[idx]
    for j, i in enumerate(idx):
        written.append(plot_projection_comparison(projections_sel[j], scene.val.projections[i], out / f"projection-{int(i):03d}.png",
                                                  title=f"{title}, held-out view {int(i)}"))
    weights = None
    if run.model is not None:
        q = query_grid(run.model, scene.geometry, keys=("mu", "weights", "mu_materials"), chunk=chunk)
        if volume is None:
            volume = q["mu"]
        weights = q.get("weights")
    elif volume is None:
        volume = np.asarray(run.volume, dtype=np.float32)
    written.append(plot_slice_comparison(volume, scene.image, out / "slices.png", title=f"{title}: attenuation (data units)"))
    if weights is not None:
        written.append(plot_weight_maps(weights, out / "weights.png", title=f"{title}: selector weights per material"))
        written.append(plot_label_maps(voxel_labels(q)[0], scene.labels, out / "labels.png",
                                       title=f"{title}: material labels (0 = air; partial-volume shells relabelled)"))
    return written
