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
- ``band``: the voxels within one voxel of a place where ``v``'s gradient exceeds 0.02 per voxel (from
  the run's own volume, no ground truth), and the share of the squared error inside it;
- ``corrections``: ``v + M x`` with ``M`` the band and ``x`` from CGLS on ``(A M) x = r`` started at
  0, psnr3d per iteration (best and where), for four residuals ``r``:
  ``oracle`` ``A gt - A v`` (a projector without discretisation error: what the views determine
  once the error is confined to the band); ``data`` ``b - A v``; ``data_exact_discretisation``
  ``b - d - A v`` with ``d = A_f g_f - A box(g_f)`` from the phantom on the fine grid (the best a
  discretisation estimate can do at that resolution); ``data_field_discretisation`` the same ``d``
  computed from the run's own field (queried on the fine grid inside the band, 2x sharper, the
  trilinear upsampling of ``v`` elsewhere) - what a method could do without the ground truth.
  ``fine_floor`` and the exact row need an analytic phantom: built-in scenes only.

Minutes per run, no training. Not part of the test suite.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from run_rows import run_rows

BAND_GRADIENT = 0.02  # per voxel, data units
QUERY_CHUNK = 262144


def edge_band(volume: torch.Tensor, dilate: int) -> torch.Tensor:
    """[nx, ny, nz] -> bool: within ``dilate`` voxels of a central-difference gradient above BAND_GRADIENT."""
    gx, gy, gz = torch.gradient(volume)
    hot = ((gx * gx + gy * gy + gz * gz).sqrt() > BAND_GRADIENT).float()[None, None]
    return F.max_pool3d(hot, 2 * dilate + 1, 1, dilate)[0, 0] > 0


def fine_geometry(geometry, f: int):
    return dataclasses.replace(geometry, n_voxel=tuple(n * f for n in geometry.n_voxel),
                               d_voxel=tuple(d / f for d in geometry.d_voxel))


def box(volume: torch.Tensor, f: int) -> torch.Tensor:
    """Mean over f^3 blocks: [f nx, f ny, f nz] -> [nx, ny, nz]."""
    nx, ny, nz = (n // f for n in volume.shape)
    return volume.reshape(nx, f, ny, f, nz, f).mean((1, 3, 5))


def band_cgls(A, v: torch.Tensor, gt: np.ndarray, band: torch.Tensor, r: torch.Tensor, iterations: int) -> list[float]:
    """psnr3d of ``v + M x_i`` for the CGLS iterates x_i of ``(A M) x = r`` from 0."""
    from kneas_method.evaluation.metrics import psnr3d

    m = band.to(v.dtype)
    r = r.clone()
    x = torch.zeros_like(v)
    s = A.back(r) * m
    p, g = s.clone(), (s * s).sum()
    out = []
    for _ in range(iterations):
        q = A.forward(p * m)
        a = g / (q * q).sum()
        x += a * p
        r -= a * q
        s = A.back(r) * m
        gn = (s * s).sum()
        p, g = s + gn / g * p, gn
        out.append(round(float(psnr3d((v + m * x).clamp_min(0).numpy(), gt)), 3))
    return out


def field_discretisation(model, geometry, v: torch.Tensor, band: torch.Tensor, f: int, A, A_fine) -> torch.Tensor:
    """``A_f w - A box(w)`` for ``w`` the model's field on the fine grid inside the band (sharpness x2)
    and the trilinear upsampling of ``v`` elsewhere."""
    w = F.interpolate(v[None, None], scale_factor=f, mode="trilinear", align_corners=False)[0, 0]
    fine_band = band.repeat_interleave(f, 0).repeat_interleave(f, 1).repeat_interleave(f, 2)
    idx = fine_band.nonzero()
    axes = fine_geometry(geometry, f).voxel_axes()
    boundary = model.boundary
    saved = boundary.log_s.data.clone()
    boundary.log_s.data += math.log(2.0) / boundary.LOG_SCALE
    try:
        vals = []
        for i in range(0, len(idx), QUERY_CHUNK):
            j = idx[i:i + QUERY_CHUNK]
            pts = torch.stack([axes[0][j[:, 0]], axes[1][j[:, 1]], axes[2][j[:, 2]]], -1)
            vals.append(model.query(pts)["mu"])
    finally:
        boundary.log_s.data = saved
    w[fine_band] = torch.cat(vals)
    return A_fine.forward(w) - A.forward(box(w, f))


def summary(curve: list[float]) -> dict:
    best = int(np.argmax(curve))
    return {"best_psnr3d": curve[best], "at_iteration": best + 1, "psnr3d_per_iteration": curve}


def visible_error(run_dir: Path, fine: int, iterations: int) -> dict:
    from kneas_method.classical.projector import Projector
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
    A_fine = Projector(fine_geometry(geometry, fine), scene.train.angles)
    e = v - gt_t
    band = edge_band(v, 1)
    A_gt = A.forward(gt_t)
    d_field = field_discretisation(loaded.model, geometry, v, band, fine, A, A_fine)
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
        gt_fine = torch.as_tensor(phantom.volume(fine_geometry(geometry, fine), supersample=2))
        A_fine_gt = A_fine.forward(gt_fine)
        d_exact = A_fine_gt - A.forward(box(gt_fine, fine))
        residuals["data_exact_discretisation"] = b - d_exact - A_v
        row["fine_floor"] = float(((A_fine_gt - b) ** 2).mean())
        row["discretisation_estimate_error"]["exact"] = float(((d_true - d_exact) ** 2).mean())
    row["corrections"] = {name: summary(band_cgls(A, v, gt, band, r, iterations)) for name, r in residuals.items()}
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
