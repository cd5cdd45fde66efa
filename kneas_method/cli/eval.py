"""`kneas-eval RUN_DIR`: re-evaluate a trained run on all held-out views (SPEC §5).

    kneas-eval outputs/foot/k-neas/20250101-120000
    kneas-eval --checkpoint outputs/foot/k-neas/20250101-120000/checkpoints/step-00000800.ckpt
    kneas-eval outputs/foot/k-neas/20250101-120000 --scene foot_noisy_50.pickle -o eval-noisy/

Writes ``metrics.json`` and figures to ``-o DIR`` (default ``RUN_DIR/eval-<timestamp>/``):

* 2D: PSNR/SSIM per held-out view and their means (intensity domain);
* 3D: PSNR/SSIM at the voxel centres with the exact unit conversion
  (``psnr3d``, ``ssim3d``) and the least-squares-rescaled variant
  (``psnr3d_ls``, ``ssim3d_ls``, ``ls_scale``); where the truth reaches above 1 (a scanner's
  units), also against the truth's maximum and range (``psnr3d_truth_peak``, ``ssim3d_truth_range``);
* built-in scenes: per ground-truth material Dice, Chamfer distance (mm) and F-score at
  one voxel, with the material matching. SDF methods: labels and surfaces from the
  fields, partial-volume shells relabelled (``--keep-shells``: as they are), or with
  ``--materials values`` the model's volume thresholded at its own bounds; methods without
  (classical, NAF): the volume thresholded at the automatic GMM bounds fitted on it, the way
  a user would segment it
  (:mod:`kneas_method.evaluation.surfaces` documents the definitions).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Literal, get_args

from ..errors import KneasError
from .common import ArgumentParser, run_cli
from .export import _say, output_folder


def _parser() -> argparse.ArgumentParser:
    p = ArgumentParser(prog="kneas-eval", description="Re-evaluate a trained kneas run on its held-out views (SPEC §5 metrics).")
    p.add_argument("run", metavar="RUN_DIR", nargs="?", default=None, help="run folder (or a checkpoint file of it)")
    p.add_argument("--checkpoint", metavar="FILE", default=None, help="evaluate this checkpoint (its run's config.json is next to it or one folder up)")
    p.add_argument("--scene", default=None, help="evaluate on this scene instead (built-in name or NAF pickle with the same volume box)")
    p.add_argument("-o", "--output", metavar="DIR", default=None, help="output folder (default RUN_DIR/eval-<timestamp>/)")
    p.add_argument("--device", default="cpu", help="torch device: cpu (default), cuda, or auto")
    p.add_argument("--no-surfaces", action="store_true", help="skip the surface metrics (Chamfer, F-score); Dice is still computed")
    p.add_argument("--grid-factor", type=int, default=2, help="surface grids at this multiple of the voxel resolution (default 2)")
    p.add_argument("--keep-shells", action="store_true",
                   help="score the model's labels and surfaces as they are, without relabelling partial-volume shells "
                        "(thin layers of a material between a lower and a higher one; see kneas_method.evaluation.partial_volume)")
    p.add_argument("--air-threshold", type=float, default=0.5, help="total selector weight below which a point is air (default 0.5)")
    p.add_argument("--materials", choices=MATERIAL_READOUTS, default="surfaces",
                   help="how an SDF model's materials are read: surfaces (default, the paper's): each point belongs to the material "
                        "its signed distance fields show there; values: its volume thresholded at the model's own attenuation bounds, "
                        "and scored as a classical volume is (no shells relabelled; real anatomy's texture is held by mixing "
                        "materials, so the fields' labels can disagree with the values)")
    p.add_argument("--figure-views", type=int, default=3, help="held-out views drawn as figures (default 3; 0 = none)")
    p.add_argument("--no-figures", action="store_true", help="write metrics.json only")
    return p


MaterialReadout = Literal["surfaces", "values"]
MATERIAL_READOUTS = get_args(MaterialReadout)


def evaluate_run(run, *, device, surfaces: bool = True, grid_factor: int = 2, air_threshold: float = 0.5, shells: bool = True,
                 materials: MaterialReadout = "surfaces"):
    """``(metrics dict, projections [N, nV, nU], volume [nx, ny, nz] or None)`` of a loaded run; ``materials``: how an
    SDF model's materials are read (:data:`MATERIAL_READOUTS`, the ``--materials`` help)."""
    from ..engine.evaluate import evaluate_model, evaluate_volume

    if materials not in MATERIAL_READOUTS:
        raise KneasError(f"no material reading {materials!r}: choose one of {', '.join(MATERIAL_READOUTS)}")
    _say(f"held-out views and volume: {len(run.scene.val)} views, {run.scene.geometry.n_voxel} voxels")
    if run.model is None:
        metrics, (proj, vol) = evaluate_volume(run.volume, run.scene, return_arrays=True, fitted=run.fitted)
    else:
        metrics, (proj, vol) = evaluate_model(run.model, run.scene, run.config, device, return_arrays=True)
    if run.has_surfaces and run.scene.labels is not None and materials == "values" and vol is not None:
        from ..bounds import Bounds
        from ..evaluation.surfaces import volume_material_metrics

        alphas, betas = run.model.bounds
        metrics["materials"] = volume_material_metrics(vol, run.scene, boundaries=list(Bounds(tuple(alphas), tuple(betas)).boundaries),
                                                       boundaries_are="the model's own attenuation bounds",
                                                       surfaces=surfaces and run.scene.membership is not None)
        metrics["materials"]["readout"] = "values"
    elif run.has_surfaces and run.scene.labels is not None:
        from ..evaluation.surfaces import material_metrics

        metrics["materials"] = material_metrics(run.model, run.scene, factor=grid_factor, air_threshold=air_threshold,
                                                surfaces=surfaces and run.scene.membership is not None, shells=shells,
                                                progress=_say)
    elif run.scene.labels is not None and vol is not None:
        from ..evaluation.surfaces import volume_material_metrics

        metrics["materials"] = volume_material_metrics(vol, run.scene, seed=int(run.config.seed),
                                                       surfaces=surfaces and run.scene.membership is not None)
    return metrics, proj, vol


def _print(metrics: dict) -> None:
    keys = [("psnr2d", "2D PSNR (dB, mean over held-out views)"), ("ssim2d", "2D SSIM"),
            ("psnr3d", "3D PSNR (dB, exact units)"), ("ssim3d", "3D SSIM (exact units)"),
            ("psnr3d_ls", "3D PSNR, least-squares scaled"), ("ssim3d_ls", "3D SSIM, least-squares scaled"),
            ("psnr3d_truth_peak", "3D PSNR, peak: the truth's maximum"), ("ssim3d_truth_range", "3D SSIM, the truth's range")]
    for key, label in keys:
        if key in metrics:
            _say(f"  {label:42s} {metrics[key]:.4f}")
    mat = metrics.get("materials")
    if mat:
        match = ", ".join(f"{m['material']}->{m['gt_name']}" for m in mat["matching"])
        _say(f"  material matching (predicted -> ground truth): {match}")
        for name, m in mat["materials"].items():
            ch = "-" if m.get("chamfer_mm") is None else f"{m['chamfer_mm']:.3f} mm"
            fs = "-" if m.get("fscore") is None else f"{m['fscore']:.3f}"
            _say(f"  {name:20s} Dice {m['dice']:.3f}   Chamfer {ch}   F@1voxel {fs}")


def main(argv=None) -> None:
    argv = sys.argv[1:] if argv is None else list(argv)

    def body() -> int:
        from ..device import resolve_device
        from ..engine.loading import load_run
        from ..engine.run_dir import timestamp, write_json

        args = _parser().parse_args(argv)
        target = args.checkpoint or args.run
        if target is None:
            raise KneasError("give a run folder (kneas-eval RUN_DIR) or a checkpoint (--checkpoint FILE)")
        if args.figure_views < 0:
            raise KneasError(f"--figure-views must be 0 (none) or more, got {args.figure_views}")
        if args.checkpoint and not Path(args.checkpoint).exists():
            raise KneasError(f"--checkpoint {args.checkpoint} does not exist; give a .ckpt file of the run (RUN_DIR/checkpoints/)")
        if args.checkpoint and args.run and Path(args.run).resolve() != Path(args.checkpoint).resolve().parent.parent \
                and Path(args.run).resolve() != Path(args.checkpoint).resolve().parent:
            raise KneasError(f"--checkpoint {args.checkpoint} is not inside run {args.run}; give only one of them")
        if args.grid_factor < 1:
            raise KneasError(f"--grid-factor must be a positive integer, got {args.grid_factor}")
        device = resolve_device(args.device)
        run = load_run(target, scene=args.scene, device=device)
        what = f"checkpoint {run.checkpoint_path} (step {run.step})" if run.checkpoint_path else "volume.npy"
        _say(f"evaluating {run.config.method} run {run.run_dir}: {what} on scene {run.scene.name} ({len(run.scene.val)} held-out views)")
        for note in run.notes:
            _say(f"note: {note}")
        out = output_folder(run.run_dir, args.output, f"eval-{timestamp()}")
        t0 = time.perf_counter()
        metrics, proj, vol = evaluate_run(run, device=device, surfaces=not args.no_surfaces, grid_factor=args.grid_factor,
                                          air_threshold=args.air_threshold, shells=not args.keep_shells, materials=args.materials)
        report = {
            "method": run.config.method,
            "run_dir": str(run.run_dir),
            "checkpoint": str(run.checkpoint_path) if run.checkpoint_path else None,
            "step": run.step,
            "scene": run.scene.name,
            "scene_source": run.scene.source,
            "training_scene": run.config.scene,
            "device": str(device),
            **metrics,
            "seconds": round(time.perf_counter() - t0, 2),
        }
        write_json(out / "metrics.json", report)
        if not args.no_figures:
            from ..export.figures import export_figures

            export_figures(run, out / "figures", views=args.figure_views if args.figure_views > 0 else 0,
                           projections=proj, volume=vol)
        _print(metrics)
        _say(f"wrote {out / 'metrics.json'}" + ("" if args.no_figures else f" and figures in {out / 'figures'}"))
        return 0

    run_cli(body)


if __name__ == "__main__":  # pragma: no cover
    main()
