"""The figures a researcher looks at after a run (matplotlib, Agg, PNG)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: str | Path, dpi: int = 100) -> Path:
    """Lay out, write (PNG) and close a matplotlib figure; returns the path."""
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    _plt().close(fig)
    return Path(path)


def _np(x) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float32)


def plot_loss_curves(history: dict[str, list[tuple[int, float]]], path: str | Path, title: str = "") -> Path:
    """Loss terms against step (log scale). ``history[name] = [(step, value), ...]``."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 4))
    for name, points in history.items():
        points = [(s, v) for s, v in points if np.isfinite(v) and v > 0]
        if points:
            steps, values = zip(*points)
            ax.plot(steps, values, label=name, lw=1)
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("loss")
    ax.set_title(title)
    if ax.lines:
        ax.legend()
    return save_figure(fig, path, dpi=110)


def plot_projection_comparison(pred, gt, path: str | Path, title: str = "") -> Path:
    """One view: prediction, ground truth and error, as intensity ``exp(-p)``.

    Args:
        pred, gt: projections [nV, nU] (line integrals).
    """
    plt = _plt()
    pred_i, gt_i = np.exp(-_np(pred)), np.exp(-_np(gt))
    err = pred_i - gt_i
    fig, axes = plt.subplots(1, 3, figsize=(11, 3.8))
    lo, hi = float(min(pred_i.min(), gt_i.min())), float(max(pred_i.max(), gt_i.max()))
    for ax, img, name in ((axes[0], pred_i, "prediction"), (axes[1], gt_i, "ground truth")):
        im = ax.imshow(img, cmap="gray", vmin=lo, vmax=hi)
        ax.set_title(name)
        fig.colorbar(im, ax=ax, fraction=0.046)
    m = float(np.abs(err).max()) or 1.0
    im = axes[2].imshow(err, cmap="coolwarm", vmin=-m, vmax=m)
    axes[2].set_title("error")
    fig.colorbar(im, ax=axes[2], fraction=0.046)
    for ax in axes:
        ax.axis("off")
    fig.suptitle(title)
    return save_figure(fig, path, dpi=110)


def middle_slices(vol: np.ndarray):
    """The three orthogonal middle slices of ``vol [nx, ny, nz, ...]`` and their axis names."""
    cx, cy, cz = (s // 2 for s in vol.shape[:3])
    return (vol[cx, :, :], vol[:, cy, :], vol[:, :, cz]), ("x", "y", "z")


def plot_slice_comparison(pred, gt, path: str | Path, title: str = "") -> Path:
    """Three orthogonal middle slices: prediction, ground truth (if any), error.

    Args:
        pred, gt: volumes [nx, ny, nz] in data units; ``gt`` may be None.
    """
    plt = _plt()
    pred = _np(pred)
    vols = [("prediction", pred)]
    if gt is not None:
        gt = _np(gt)
        vols += [("ground truth", gt), ("error", pred - gt)]
    fig, axes = plt.subplots(len(vols), 3, figsize=(10, 3.3 * len(vols)), squeeze=False)
    hi = float(max(v.max() for n, v in vols if n != "error")) or 1.0
    for row, (name, vol) in enumerate(vols):
        slices, names = middle_slices(vol)
        for col, (sl, axis) in enumerate(zip(slices, names)):
            ax = axes[row, col]
            if name == "error":
                m = float(np.abs(vol).max()) or 1.0
                ax.imshow(sl.T, cmap="coolwarm", vmin=-m, vmax=m, origin="lower")
            else:
                ax.imshow(sl.T, cmap="gray", vmin=0, vmax=hi, origin="lower")
            ax.set_title(f"{name}, {axis} = middle")
            ax.axis("off")
    fig.suptitle(title)
    return save_figure(fig, path, dpi=100)


def plot_validation(points, path: str | Path, title: str = "") -> Path:
    """Validation 2D PSNR against step; ``points = [(step, psnr), ...]``."""
    plt = _plt()
    steps, values = zip(*points)
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.plot(steps, values, "o-")
    ax.set_xlabel("step")
    ax.set_ylabel("validation PSNR2D [dB]")
    ax.set_title(title)
    return save_figure(fig, path, dpi=100)


def run_figures(run_dir: str | Path, scene, projections, volume, title: str, trainer=None) -> None:
    """The figures of a finished run in ``run_dir/figures``: loss curves and validation PSNR
    (``trainer``, neural runs), held-out view 0 against its measurement, the volume's slices
    against the ground truth (when known)."""
    fig = Path(run_dir) / "figures"
    fig.mkdir(parents=True, exist_ok=True)
    if trainer is not None and trainer.history:
        plot_loss_curves(trainer.loss_history(), fig / "loss_curves.png", title=title)
        if trainer.history.get("val_psnr2d"):
            plot_validation(trainer.history["val_psnr2d"], fig / "validation_psnr2d.png", title)
    plot_projection_comparison(projections[0], np.asarray(scene.val.projections[0]), fig / "projection_val0.png",
                               title=f"{title}: held-out view 0")
    if volume is not None:
        plot_slice_comparison(volume, None if scene.image is None else np.asarray(scene.image), fig / "slices.png",
                              title=f"{title}: volume (data units)")
