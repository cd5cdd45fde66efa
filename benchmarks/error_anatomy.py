"""Where a reconstruction's squared error lies: at material edges, and how much of it is blur.

    python benchmarks/error_anatomy.py RUN_DIR [RUN_DIR ...] [--out benchmarks/results/error_anatomy_cpu.json]

For each run folder on a built-in scene (ground-truth volume and labels), the run's volume (a neural
run's model at the voxel centres, a classical run's ``volume.npy``) and, when the folder has one, the
classical start it was given (``<method>_volume.npy``, e.g. ASD-POCS) are compared with the exact
volume:

- ``edge_voxels`` / ``edge_error_share``: the voxels whose 3x3x3 neighbourhood holds more than one
  ground-truth label, and the share of the squared error that lies in them;
- ``blur_share`` / ``blur_sigma_voxels``: the error ``e = v - gt`` regressed on the blur of the exact
  volume, ``a * (G_sigma * gt - gt)`` (Gaussian, sigma in voxels, the best of a few): the share of
  the squared error that a blur of the exact volume explains, and the width of that blur,
  ``sigma * sqrt(a)`` (for a small blur ``G_sigma * gt - gt ~ sigma^2 / 2 * laplacian(gt)``);
- ``start_error_share`` / ``start_error_coefficient``: the run's error regressed the same way on
  its classical start's error ``v_start - gt``: how much of what the run gets wrong is what its start
  got wrong (a share near 1 with a coefficient below 1: the run shrinks its start's error but keeps
  its pattern);
- ``edge_pairs``: the edge voxels split by the two labels their 3x3x3 neighbourhood spans (lowest
  and highest, material names), each pair's share of the squared error, its rms and its mean error
  (bias), the largest first: which interfaces hold the error (abdomen: the one-voxel cortical
  shell's);
- for an SDF run, ``edge_sigma_voxels``: the standard deviation of the run's learned occupancy
  profile ``sigmoid(-s d)`` across a surface, ``pi / (sqrt(3) s)`` in voxels (the exact volume's
  edges, voxel means of a sharp surface, have about 0.29).

Seconds per run, no training. Not part of the test suite.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np
from run_rows import run_rows

SIGMAS = (0.35, 0.5, 0.75, 1.0)


def neighbourhood_range(labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``labels [nx, ny, nz]`` -> (lowest, highest) label in each voxel's 3x3x3 neighbourhood."""
    from scipy import ndimage

    return ndimage.minimum_filter(labels, size=3), ndimage.maximum_filter(labels, size=3)


def edge_mask(labels: np.ndarray) -> np.ndarray:
    """``labels [nx, ny, nz]`` -> bool mask of the voxels with another label within their 3x3x3 neighbourhood."""
    low, high = neighbourhood_range(labels)
    return low != high


def edge_pairs(error: np.ndarray, labels: np.ndarray, names: tuple[str, ...] = (), top: int = 6) -> list[dict]:
    """The edge voxels of ``labels [nx, ny, nz]`` (0 = air, ``k`` = ``names[k - 1]``) grouped by the
    lowest and highest label of their 3x3x3 neighbourhood: ``[{"pair", "voxels", "error_share",
    "rms", "bias"}]`` for the ``top`` pairs by squared ``error [nx, ny, nz]`` (``volume - gt``),
    largest first; ``error_share`` is of the whole volume's squared error."""
    labels = np.asarray(labels)
    low, high = neighbourhood_range(labels)
    edges = low != high
    e = np.asarray(error, dtype=np.float64)
    total = max(float(np.sum(e * e)), 1e-30)
    key = low[edges].astype(np.int64) * (int(labels.max()) + 1) + high[edges]
    err = e[edges]
    name = lambda k: "air" if k == 0 else (names[k - 1] if k - 1 < len(names) else f"label {k}")
    rows = []
    for k in np.unique(key):
        m = key == k
        a, b = divmod(int(k), int(labels.max()) + 1)
        sq = float(np.sum(err[m] ** 2))
        rows.append({"pair": f"{name(a)} | {name(b)}", "voxels": int(m.sum()), "error_share": round(sq / total, 3),
                     "rms": round(math.sqrt(sq / int(m.sum())), 4), "bias": round(float(err[m].mean()), 4)})
    return sorted(rows, key=lambda r: -r["error_share"])[:top]


def blur_directions(gt: np.ndarray) -> dict[float, np.ndarray]:
    """``{sigma: G_sigma * gt - gt}`` for each sigma of :data:`SIGMAS` (float64, voxels): what a
    Gaussian blur of the exact volume changes. Computed once per scene."""
    from scipy import ndimage

    g = np.asarray(gt, dtype=np.float64)
    return {s: ndimage.gaussian_filter(g, s) - g for s in SIGMAS}


def fit_along(error: np.ndarray, direction: np.ndarray) -> tuple[float, float]:
    """Least-squares ``a`` in ``error ~ a * direction`` and the share of ``sum(error^2)`` it explains."""
    a = float(np.sum(error * direction) / max(float(np.sum(direction * direction)), 1e-30))
    rest = error - a * direction
    return a, 1.0 - float(np.sum(rest * rest)) / max(float(np.sum(error * error)), 1e-30)


def anatomy(volume: np.ndarray, gt: np.ndarray, edges: np.ndarray, blurs: dict[float, np.ndarray],
            start: np.ndarray | None = None, labels: np.ndarray | None = None, names: tuple[str, ...] = ()) -> dict:
    from kneas_method.evaluation.metrics import psnr3d

    e = np.asarray(volume, dtype=np.float64) - np.asarray(gt, dtype=np.float64)
    sq = e * e
    fits = {s: fit_along(e, b) for s, b in blurs.items()}
    best = max(fits, key=lambda s: fits[s][1])
    row = {"psnr3d": round(float(psnr3d(volume, gt)), 2), "mse": float(sq.mean()),
           "edge_voxels": round(float(edges.mean()), 4), "edge_error_share": round(float(sq[edges].sum() / sq.sum()), 3),
           "blur_share": round(fits[best][1], 3), "blur_sigma_voxels": round(best * math.sqrt(max(fits[best][0], 0.0)), 2)}
    if start is not None:
        a, share = fit_along(e, np.asarray(start, dtype=np.float64) - np.asarray(gt, dtype=np.float64))
        row["start_error_share"], row["start_error_coefficient"] = round(share, 3), round(a, 3)
    if labels is not None:
        row["edge_pairs"] = edge_pairs(e, labels, names)
    return row


def run_anatomy(run_dir: Path) -> dict:
    from kneas_method.engine.evaluate import sample_volume
    from kneas_method.engine.loading import load_run

    loaded = load_run(run_dir)
    scene = loaded.scene
    if scene.image is None or scene.labels is None:
        raise SystemExit(f"{run_dir}: the scene has no ground-truth volume and labels; use a run on a built-in scene")
    gt = np.asarray(scene.image, dtype=np.float32)
    edges = edge_mask(np.asarray(scene.labels))
    blurs = blur_directions(gt)
    volume = loaded.volume if loaded.model is None else sample_volume(loaded.model, scene.geometry)
    starts = {path.name[: -len("_volume.npy")]: np.load(path) for path in sorted(run_dir.glob("*_volume.npy"))}
    start = next(iter(starts.values())) if len(starts) == 1 else None
    row = {"run": str(run_dir), "scene": scene.name, "method": loaded.config.method,
           "model": anatomy(volume, gt, edges, blurs, start, scene.labels, tuple(scene.materials))}
    boundary = getattr(loaded.model, "boundary", None)
    if boundary is not None:
        s = float(boundary.s.detach())
        voxel = float(min(scene.geometry.d_voxel))  # model units per voxel
        row["model"]["sharpness_s"] = round(s, 1)
        row["model"]["edge_sigma_voxels"] = round(math.pi / (math.sqrt(3.0) * s * voxel), 2)
    for name, other in starts.items():
        row[name] = anatomy(other, gt, edges, blurs, labels=scene.labels, names=tuple(scene.materials))
    return row


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+", type=Path, help="run folders written by kneas-train on built-in scenes")
    p.add_argument("--out", type=Path, default=None, help="write the rows as JSON here")
    args = p.parse_args(argv)
    run_rows(args.runs, run_anatomy, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
