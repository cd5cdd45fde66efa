"""How much of a run's 3D error do the training views see, and what would it take to use it?

    python benchmarks/visible_error.py RUN_DIR [RUN_DIR ...] [--fine 4] [--iterations 12]
        [--out benchmarks/results/visible_error_cpu.json]

For each run folder of a surface method on a scene with a ground-truth volume, the
run's volume ``v`` (its model at the voxel centres) and error ``e = v - gt`` are put against the
training projections ``b`` with this project's Joseph projector ``A`` (``kneas_method.classical``):

- ``visible_mse``: ``mean((A e)^2)``, what the views see of the error, next to ``joseph_floor``,
  ``mean((b - A gt)^2)``: the projector's own discretisation error on the exact volume, and
  ``fine_floor``: the same on a grid ``--fine`` times finer (the phantom's voxel means there,
  projected at that resolution);
- ``band``: the voxels within one voxel of a place where ``v``'s gradient exceeds 2 % of its 99.5th
  percentile per voxel (``kneas_method.stages.band_correction.edge_band``, the run's own volume, no ground truth;
  the figures of 2026-11-25 used 0.02 data units per voxel), and the share
  of the squared error inside it;
- ``corrections``: ``v + M x`` with ``M`` the band and ``x`` from CGLS on ``(A M) x = r`` started at
  0, psnr3d per iteration (best and where), for four residuals ``r``:
  ``oracle`` ``A gt - A v`` (a projector without discretisation error: what the views determine
  once the error is confined to the band); ``data`` ``b - A v``; ``data_exact_discretisation``
  ``b - d - A v`` with ``d = A_f g_f - A box(g_f)`` from the phantom on the fine grid (the best a
  discretisation estimate can do at that resolution); ``data_field_discretisation`` the same ``d``
  computed from the run's own field (on the fine grid inside the band, 2x sharper, from its fields
  queried on a 2x grid and interpolated; the trilinear upsampling of ``v`` elsewhere;
  ``kneas_method.stages.band_correction.discretisation_error``) - what
  the cpu preset's band correction does after training, here without its noise stop.
  ``fine_floor`` and the exact row need an analytic phantom: built-in scenes only.

Minutes per run, no training. Not part of the test suite.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
from run_rows import run_rows


def band_curve(A, v: torch.Tensor, gt: np.ndarray, band: torch.Tensor, r: torch.Tensor, iterations: int) -> list[float]:
    """psnr3d of ``v + x_i`` for the CGLS iterates x_i of ``(A M) x = r`` from 0 (``band_correction.band_cgls``)."""
    from kneas_method.stages.band_correction import band_cgls
    from kneas_method.evaluation.metrics import psnr3d

    out: list[float] = []
    band_cgls(A, r, band, iterations, iterates=lambda i, x: out.append(round(float(psnr3d((v + x).clamp_min(0).numpy(), gt)), 3)))
    return out


def summary(curve: list[float]) -> dict:
    best = int(np.argmax(curve))
    return {"best_psnr3d": curve[best], "at_iteration": best + 1, "psnr3d_per_iteration": curve}


def visible_error(run_dir: Path, fine: int, iterations: int) -> dict:
    from kneas_method.classical.projector import Projector
    from kneas_method.stages.band_correction import box_mean, discretisation_error, edge_band
    from kneas_method.data.phantoms import PHANTOM_NAMES, get_phantom
    from kneas_method.engine.evaluate import sample_volume
    from kneas_method.engine.loading import load_run
    from kneas_method.evaluation.metrics import psnr3d

    torch.set_grad_enabled(False)
    loaded = load_run(run_dir)
    scene = loaded.scene
    if scene.image is None:
        raise SystemExit(f"{run_dir}: the scene has no ground-truth volume; use a built-in scene or a written held-out one")
    if loaded.model is None or not loaded.has_surfaces:
        raise SystemExit(f"{run_dir}: needs a run of a surface method (k-neas, neas-2m): the field discretisation estimate queries its SDF")
    geometry = scene.geometry
    phantom = get_phantom(scene.name) if scene.name in PHANTOM_NAMES else None  # exact rows need the analytic phantom
    gt = np.asarray(scene.image, dtype=np.float32)
    gt_t = torch.as_tensor(gt)
    v = torch.as_tensor(np.asarray(sample_volume(loaded.model, geometry), dtype=np.float32))
    b = torch.as_tensor(np.asarray(scene.train.projections, dtype=np.float32))
    A = Projector(geometry, scene.train.angles)
    A_fine = Projector(geometry.refined(fine), scene.train.angles)
    e = v - gt_t
    band = edge_band(v)
    A_gt = A.forward(gt_t)
    d_field = discretisation_error(loaded.model, geometry, v, band, A, A_fine, fine=fine, sharpen=2.0)
    d_true = b - A_gt
    A_v = A.forward(v)
    residuals = {"oracle": A_gt - A_v, "data": b - A_v, "data_field_discretisation": b - d_field - A_v}
    row = {"run": str(run_dir), "scene": scene.name, "method": loaded.config.method,
           "psnr3d": round(float(psnr3d(v.numpy(), gt)), 3),
           "visible_mse": float((A.forward(e) ** 2).mean()),
           "joseph_floor": float((d_true ** 2).mean()), "fine": fine,
           "discretisation_estimate_error": {"field": float(((d_true - d_field) ** 2).mean())},
           "band_voxels": round(float(band.float().mean()), 4),
           "band_error_share": round(float((e * e)[band].sum() / (e * e).sum()), 4)}
    if phantom is not None:
        gt_fine = torch.as_tensor(phantom.volume(geometry.refined(fine), supersample=2))
        A_fine_gt = A_fine.forward(gt_fine)
        d_exact = A_fine_gt - A.forward(box_mean(gt_fine, fine))
        residuals["data_exact_discretisation"] = b - d_exact - A_v
        row["fine_floor"] = float(((A_fine_gt - b) ** 2).mean())
        row["discretisation_estimate_error"]["exact"] = float(((d_true - d_exact) ** 2).mean())
    row["corrections"] = {name: summary(band_curve(A, v, gt, band, r, iterations)) for name, r in residuals.items()}
    return row


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+", type=Path, help="run folders of a surface method on scenes with a ground-truth volume")
    p.add_argument("--fine", type=int, default=4, help="the finer grid's factor for the discretisation terms (default 4)")
    p.add_argument("--iterations", type=int, default=12, help="CGLS iterations per correction (default 12)")
    p.add_argument("--out", type=Path, default=None, help="write the rows as JSON here")
    args = p.parse_args(argv)
    if args.fine < 2 or args.iterations < 1:
        raise SystemExit("--fine must be at least 2 and --iterations at least 1")
    run_rows(args.runs, lambda run: visible_error(run, args.fine, args.iterations), args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
