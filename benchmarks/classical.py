"""Classical reconstructions on the built-in scenes: 3D PSNR / SSIM and wall time (not part of the test suite).

    python benchmarks/classical.py                                   # foot, all algorithms, default settings
    python benchmarks/classical.py --scenes foot,jaw,chest,abdomen --algorithms sart,asd-pocs
    python benchmarks/classical.py --scenes heldout:head-256,heldout:jaw-noisy --dice   # benchmarks/heldout.py
    python benchmarks/classical.py --runs "sart:iterations=5" "sart:iterations=10" "cgls:iterations=30" \\
        --threads 2 --out benchmarks/results/classical_cpu.json
    python benchmarks/classical.py --scenes foot,jaw --runs "asd-pocs:iterations=40" --trace   # every count 1..40
    python benchmarks/classical.py --scenes abdomen --runs "cgls:iterations=30" --dice --shells   # also with shells relabelled
    python benchmarks/classical.py --scenes data/real/ts-chest-noisy.pickle --runs "sart:iterations=40" --trace --smooth
    python benchmarks/classical.py --scenes data/real/ts-chest.pickle --runs "sart:iterations=40" --trace --init truth-classes

A run is ``algorithm[:key=value,...]`` (``fdk``, ``sart``, ``os-sart``, ``cgls``,
``asd-pocs`` with fields of ``ReconstructionOptions``: ``iterations``, ``relaxation``,
``subsets``, ``positivity``, ``backprojector``, ``tv_steps``, ``tv_alpha``, ``filter``;
values are parsed as Python literals): the same call ``kneas-train ALGORITHM`` makes
(``kneas_method.classical.reconstruct``). ``--trace`` also scores the volume after every
iteration of each run (psnr3d / ssim3d against the truth; ASD-POCS's iterate clamped at 0 as
its result is), so one 40-iteration run gives the best count from 1 to 40 (``trace`` and
``best`` in the JSON). ``--dice`` adds the per-material Dice and
Chamfer of ``kneas-eval`` (the volume thresholded at the GMM bounds fitted on it). ``--algorithms`` with ``--iterations`` is a shorthand for runs
with default settings. Every run reconstructs from the scene's training views
on the box ``kneas-train`` fits them on (``data.truncation.fitting_scene``: the scene's own,
or longer along the axis where the object goes on beyond it) and is scored on the scene's grid; PSNR/SSIM are SPEC §5's primary 3D figures
(``volume_metrics``: data units, peak 1, no fitting). The wall time covers the
whole call (weights included) at ``--threads`` torch threads. The machine
(CPU count, threads, load average before and after each run) is recorded,
since other work on a shared machine slows every run.

Built-in scenes are simulated once and cached (``$KNEAS_CACHE``, see
``kneas_method.data.scenes``). The JSON (``--out``) holds one row per
scene x run and the command lines that produced them (``--append`` adds to an
existing file); a table is printed.
"""

from __future__ import annotations

import argparse
import ast
import json
import os
import platform
import sys
import time
from pathlib import Path

import torch

HERE = Path(__file__).resolve().parent


def parse_run(text: str) -> tuple[str, dict]:
    """``"sart:iterations=5,relaxation=0.5"`` -> ``("sart", {"iterations": 5, "relaxation": 0.5})``."""
    name, _, rest = text.partition(":")
    kwargs = {}
    for item in filter(None, rest.split(",")):
        key, sep, value = item.partition("=")
        if not sep:
            raise SystemExit(f"error: run option {item!r} in {text!r} must be key=value")
        try:
            kwargs[key.strip()] = ast.literal_eval(value.strip())
        except (ValueError, SyntaxError):
            kwargs[key.strip()] = value.strip()
    return name.strip(), kwargs


def machine(threads: int) -> dict:
    return {
        "platform": platform.platform(),
        "cpu_count": os.cpu_count(),
        "torch_threads": threads,
        "torch": torch.__version__,
        "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
    }


def per_material_chamfer(metrics: dict) -> dict:
    """``{material name: symmetric Chamfer distance in mm}`` from a ``volume_material_metrics``
    result; a material that no class was matched to has no surface and is left out."""
    return {name: round(m["chamfer_mm"], 3) for name, m in metrics["materials"].items() if m.get("chamfer_mm") is not None}


def start_volume(spec, scene, box):
    """``--init``: None, a .npy volume on the grid the views are fitted on (``box``: the scene's, or
    longer along the axis where the object goes on beyond it; a run's ``asd-pocs_volume.npy`` is on
    it), or ``truth-classes`` (the true volume, each labelled class at its mean value); a mistake is one line."""
    import numpy as np

    if spec is None:
        return None
    grid = tuple(box.scene.geometry.n_voxel)
    if spec == "truth-classes":
        if scene.image is None or scene.labels is None:
            raise SystemExit(f"error: --init truth-classes needs the scene's true volume and labels, and {scene.name!r} has none; "
                             "give a .npy volume instead")
        if grid != tuple(scene.geometry.n_voxel):
            raise SystemExit(f"error: --init truth-classes is on the scene's grid, and {scene.name!r} is fitted on a longer box "
                             f"{grid}; give a .npy volume of that grid instead")
        volume = np.zeros_like(scene.image, dtype=np.float32)
        for k in np.unique(scene.labels):
            inside = scene.labels == k
            volume[inside] = scene.image[inside].mean()
        return volume
    try:
        volume = np.load(spec, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise SystemExit(f"error: --init {spec!r} could not be read as a .npy volume ({exc}); give a .npy file or truth-classes")
    if not isinstance(volume, np.ndarray) or volume.shape != grid:
        what = f"shape {volume.shape}" if isinstance(volume, np.ndarray) else "several arrays (an .npz)"
        raise SystemExit(f"error: --init {spec!r} has {what}, and {scene.name!r} is fitted on a grid of {grid}; "
                         "give a .npy volume of that shape, or truth-classes")
    return volume.astype(np.float32)


def smoothed_rows(box, scene, views: tuple, volume, best: dict, device) -> tuple[dict, dict]:
    """``smoothed`` (and, where ``best`` holds the best count's volume, ``smoothed_best``): psnr3d /
    ssim3d of the run's volume [nx, ny, nz] (on the fitting ``box``; numpy or a tensor) after k-neas's
    smoothing, with the filter it chose. ``views``: ``(projections tensor, Projector)`` of the box's
    training views. The noise is estimated over the whole grid (a classical volume has no empty space
    set to 0), and the smoothed volume is clamped at 0 as the stage's fit target is. Returns those rows
    and the smoothed volumes by the same keys (the box's grid, tensors)."""
    from kneas_method.evaluation.metrics import psnr3d, ssim3d
    from kneas_method.stages.smoothing import smooth_against_views

    projections, projector = views
    out, volumes = {}, {}
    for key, v, extra in (("smoothed", volume, {}), ("smoothed_best", best.get("volume"), {"iteration": best.get("iteration")})):
        if v is None:
            continue
        v = torch.as_tensor(v, dtype=torch.float32, device=device)
        smoothed, choice = smooth_against_views(v, projections, projector, mask=torch.ones(v.shape, dtype=torch.bool, device=device))
        volumes[key] = smoothed.clamp_min(0)
        s = box.crop(volumes[key].cpu().numpy())
        out[key] = {**extra, "filter": choice.label, "psnr3d": round(psnr3d(s, scene.image), 4),
                    "ssim3d": round(ssim3d(s, scene.image), 4)}
    return out, volumes


def tissue_rows(volume, box, scene, views: tuple, shells: bool, suffix: str = "") -> dict:
    """Dice and Chamfer per material of a classical ``volume`` [nx, ny, nz] (the fitting ``box``'s grid,
    numpy or a tensor) thresholded at GMM bounds fitted on itself, against ``scene``'s labels: under the
    paper's K rule (``dice``, ``chamfer_mm``) and under the K rule the cpu preset's procedure gives
    k-neas's start (``*_cpu_rule``; ``cpu_rule`` says which); with ``shells``, the same again with the
    partial-volume shells relabelled (keys ending in ``_shells``). Every key ends in ``suffix``. Whether the
    volume fits the views to their noise, and the filtered values the at-noise rule fits, are computed once."""
    import dataclasses

    import numpy as np
    from kneas_method import presets, registry
    from kneas_method.engine.bounds_stage import at_noise_k_rule, histogram_smoothing
    from kneas_method.evaluation.surfaces import volume_material_metrics
    from kneas_method.stages.band_correction import volume_at_noise

    # the bounds settings of the default k-neas run on the cpu preset, resolved as kneas-train resolves them
    cpu = presets.resolve(dataclasses.replace(registry.load("methods", "k-neas").config, preset="cpu"))
    vol = np.ascontiguousarray(box.crop(torch.as_tensor(volume).cpu().numpy()))
    surfaces = scene.membership is not None
    at_noise = volume_at_noise(volume, *views)[0]
    # the rule estimate_bounds picks for a start at the views' noise (K not given), and the filtered values it fits then
    noisy_rule = at_noise_k_rule(cpu) if at_noise else None
    rule = noisy_rule or cpu.bounds_k_rule
    fit_values = histogram_smoothing(vol) if noisy_rule else None
    row = {}
    for tail, relabel in [("", False)] + ([("_shells", True)] if shells else []):
        tail += suffix
        mm = volume_material_metrics(vol, scene, surfaces=surfaces, shells=relabel)
        row["dice" + tail] = {k: round(v["dice"], 3) for k, v in mm["materials"].items()}
        row["dice_mean" + tail] = mm["dice_mean"]
        row["chamfer_mm_mean" + tail] = mm.get("chamfer_mm_mean")
        row["chamfer_mm" + tail] = per_material_chamfer(mm)
        mv = volume_material_metrics(vol, scene, max_components=cpu.bounds_max_materials, k_rule=rule,
                                     min_std=cpu.bounds_min_std, restarts=cpu.bounds_gmm_restarts, surfaces=surfaces,
                                     shells=relabel, fit_values=fit_values,
                                     fit_values_are="the volume after the bounds' edge-preserving filter" if noisy_rule else "")
        row["cpu_rule" + tail] = {"k_rule": rule, "k_rule_used": mv["gmm"]["k_rule_used"], "K": mv["K"], "at_noise": at_noise}
        row["dice_cpu_rule" + tail] = {k: round(v["dice"], 3) for k, v in mv["materials"].items()}
        row["dice_mean_cpu_rule" + tail] = mv["dice_mean"]
        row["chamfer_mm_mean_cpu_rule" + tail] = mv.get("chamfer_mm_mean")
        row["chamfer_mm_cpu_rule" + tail] = per_material_chamfer(mv)
    return row


def training_views(box, device) -> tuple:
    """``(projections [N, nV, nU] tensor, Projector)`` of the fitting box's training views."""
    import numpy as np
    from kneas_method.classical.projector import Projector

    fit = box.scene
    return (torch.as_tensor(np.asarray(fit.train.projections, dtype=np.float32), device=device),
            Projector(fit.geometry, fit.train.angles, device=device))


def main(argv=None) -> int:
    sys.path.insert(0, str(HERE))
    import numpy as np
    from heldout import scene_from_spec
    from kneas_method.classical.options import ALGORITHMS, ReconstructionOptions
    from kneas_method.classical.reconstruct import reconstruct
    from kneas_method.console import say
    from kneas_method.data.truncation import fitting_scene
    from kneas_method.evaluation.metrics import psnr3d, ssim3d, volume_metrics

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default="foot",
                    help="comma-separated built-in names, NAF pickle paths or heldout:NAME (benchmarks/heldout.py)")
    ap.add_argument("--algorithms", default=",".join(ALGORITHMS), help="comma-separated, used when --runs is not given")
    ap.add_argument("--iterations", type=int, default=None, help="iterations for every --algorithms run (default: each one's own)")
    ap.add_argument("--runs", nargs="*", default=None, help="explicit runs 'algorithm[:key=value,...]'")
    ap.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--dice", action="store_true", help="also per-material Dice / Chamfer (GMM thresholds, as kneas-eval: K = 1..4 "
                    "by BIC), and under dice_cpu_rule the same with the cpu preset's K rule (the refine-classical procedure: the histogram's "
                    "peaks, bic-valleys with its GMM starts where there are fewer than two; where the volume fits the training views "
                    "to their noise, its at-noise rule: BIC on the volume after the bounds' edge-preserving filter)")
    ap.add_argument("--shells", action="store_true", help="with --dice: also score the thresholded volume with its partial-volume "
                    "shells relabelled first, as kneas-eval does a k-neas model's (kneas_method.evaluation.partial_volume): "
                    "the same keys ending in _shells")
    ap.add_argument("--trace", action="store_true", help="score the volume after every iteration (psnr3d / ssim3d) and "
                    "report the best iteration count of each run; needs ground truth")
    ap.add_argument("--smooth", action="store_true", help="also score the volume after the smoothing k-neas's smoothing stage "
                    "applies (SURE's filter, checked against the views: stages.smoothing.smooth_against_views), and with --trace "
                    "the best count's volume smoothed the same way: smoothed and smoothed_best in the JSON; with --dice their tissues "
                    "too (the --dice keys ending in _smoothed and _smoothed_best); needs ground truth")
    ap.add_argument("--init", default=None, help="start every iterative run from this volume instead of zeros: a .npy on the "
                    "scene's grid (a run's asd-pocs_volume.npy, kneas-export volume's attenuation.npy), or 'truth-classes', "
                    "the true volume with each of its labelled classes at its mean value (a perfect K-material prior)")
    ap.add_argument("--out", default=None, help="JSON file to write (default: none)")
    ap.add_argument("--append", action="store_true", help="add the rows (and the command) to an existing --out file")
    args = ap.parse_args(argv)

    torch.set_num_threads(args.threads)
    if args.runs:
        runs = [parse_run(r) for r in args.runs]
    else:
        extra = {} if args.iterations is None else {"iterations": args.iterations}
        runs = [(a.strip(), dict(extra)) for a in args.algorithms.split(",") if a.strip()]
    for name, _ in runs:
        if name not in ALGORITHMS:
            raise SystemExit(f"error: unknown algorithm {name!r}; choose from {', '.join(ALGORITHMS)}")
    if args.init is not None and all(name == "fdk" for name, _ in runs):
        raise SystemExit("error: --init starts the iterative methods from a volume, and FDK is not iterative; "
                         "add an iterative run or leave --init out")

    rows = []
    header = f"{'scene':9s} {'algorithm':9s} {'settings':44s} {'psnr3d':>7s} {'ssim3d':>7s} {'seconds':>8s} {'residual':>8s} {'load':>9s}"
    print(header)
    print("-" * len(header))
    for spec in [s.strip() for s in args.scenes.split(",") if s.strip()]:
        scene = scene_from_spec(spec)
        box = fitting_scene(scene, say=say)
        scoring = [flag for flag, given in (("--trace", args.trace), ("--smooth", args.smooth)) if given]
        if scoring and scene.image is None:
            raise SystemExit(f"error: {' and '.join(scoring)} score volumes against the ground truth, and scene {scene.name!r} has "
                             f"none; leave {' and '.join(scoring)} out for it")
        init = start_volume(args.init, scene, box)
        views = training_views(box, args.device) if (args.smooth or args.dice) else None
        for name, kwargs in runs:
            residuals = []
            load0 = os.getloadavg()[0]
            try:
                options = ReconstructionOptions(**kwargs)
            except TypeError as exc:
                raise SystemExit(f"error: run {name}:{kwargs}: {exc}; use fields of ReconstructionOptions") from None
            trace = []
            best = {}  # with --smooth: the best count's volume on the fitting box

            def score(i, x, name=name):
                x = x.clamp(min=0.0) if name == "asd-pocs" else x
                v = box.crop(x.detach().cpu().numpy())
                trace.append({"iteration": i, "psnr3d": round(psnr3d(v, scene.image), 4),
                              "ssim3d": round(ssim3d(v, scene.image), 4)})
                if args.smooth and (not best or trace[-1]["psnr3d"] > best["psnr3d"]):
                    best.update(psnr3d=trace[-1]["psnr3d"], iteration=i, volume=x.detach().cpu().clone())

            rec = reconstruct(name, box.scene, options, device=args.device, init=None if name == "fdk" else init,
                              progress=lambda i, n, r: residuals.append(r), iterates=score if args.trace else None)
            vol, seconds = np.ascontiguousarray(box.crop(np.asarray(rec.volume))), rec.seconds
            load1 = os.getloadavg()[0]
            m = volume_metrics(vol, scene.image) if scene.image is not None else {}
            row = {
                "scene": scene.name, "algorithm": name, "settings": rec.settings, "iterations": len(residuals),
                "psnr3d": m.get("psnr3d"), "ssim3d": m.get("ssim3d"), "seconds": round(seconds, 2),
                "residual": residuals[-1] if residuals else None, "residuals": residuals,
                "load_avg_1m": [round(load0, 2), round(load1, 2)],
            }
            if init is not None and name != "fdk":
                row["init"] = {"volume": args.init,
                               "psnr3d": round(psnr3d(box.crop(init), scene.image), 4) if scene.image is not None else None}
            if trace:
                row["trace"] = trace
                row["best"] = max(trace, key=lambda t: t["psnr3d"])
            smoothed = {}
            if args.smooth:
                smoothed_scores, smoothed = smoothed_rows(box, scene, views, rec.volume, best, args.device)
                row.update(smoothed_scores)
            if args.dice and scene.labels is not None:
                row.update(tissue_rows(rec.volume, box, scene, views, args.shells))
                for key, volume in smoothed.items():
                    row.update(tissue_rows(volume, box, scene, views, args.shells, "_" + key))
            rows.append(row)
            settings = ",".join(f"{k}={v}" for k, v in kwargs.items()) or "(defaults)"
            if "init" in row:
                settings += f" from {Path(args.init).name}"
            print(f"{scene.name:9s} {name:9s} {settings:44s} {row['psnr3d'] or float('nan'):7.2f} "
                  f"{row['ssim3d'] or float('nan'):7.3f} {seconds:8.1f} {row['residual'] or float('nan'):8.4f} {load0:4.1f}/{load1:4.1f}"
                  + (f"  dice {row['dice']}" if "dice" in row else "")
                  + (f"  best psnr3d {row['best']['psnr3d']:.2f} at {row['best']['iteration']} iterations" if "best" in row else "")
                  + "".join(f"  {k} ({row[k]['filter']}) {row[k]['psnr3d']:.2f} / {row[k]['ssim3d']:.3f}"
                            for k in ("smoothed", "smoothed_best") if k in row),
                  flush=True)
    if args.out:
        path = Path(args.out)
        command = "python benchmarks/classical.py " + " ".join(argv if argv is not None else sys.argv[1:])
        out = {
            "benchmark": "classical",
            "commands": [],
            "machine": machine(args.threads),
            "note": "psnr3d/ssim3d: SPEC §5 primary 3D figures (data units, peak 1, no fitting); seconds: wall time of the "
                    "whole call; residual: the algorithm's last reported ||Ax-b||/||b|| (SART family: sweep residual); "
                    "load_avg_1m: machine load before/after the run (shared machine)"
                    + ("; dice / chamfer_mm (per material, mm) / *_mean: the volume thresholded at GMM bounds fitted on "
                       "itself with the paper's K rule (K = 1..4 by BIC), air at 0 a matching candidate; *_cpu_rule: the "
                       "same with the cpu preset's K rule (cpu_rule: the rule, the rule that decided K, K, and at_noise: the volume "
                       "fits the views to their noise, so the procedure's at-noise rule on the volume after the bounds' filter); a material no "
                       "class was matched to has Dice 0 and no Chamfer; keys ending in _shells: the same with the partial-volume shells "
                       "relabelled first (--shells); with --smooth, keys ending in _smoothed / _smoothed_best: the same for the "
                       "smoothed volumes" if args.dice else "")
                    + ("; trace: psnr3d / ssim3d after every iteration (the seconds include scoring them); best: its "
                       "highest psnr3d" if args.trace else "")
                    + ("; smoothed / smoothed_best: the run's volume / the best count's volume after k-neas's smoothing "
                       "stage's filter (SURE, checked against the views), its label and psnr3d / ssim3d" if args.smooth else ""),
            "rows": [],
        }
        if args.append and path.is_file():
            out = json.loads(path.read_text(encoding="utf-8"))
        out["commands"].append(command)
        out["rows"].extend(rows)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(out, indent=2) + "\n", encoding="utf-8")
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
