"""The representation ceiling of a trained run's model: the same model, fitted to the exact volume.

    python benchmarks/ceiling.py RUN_DIR [RUN_DIR ...] [--steps 1500] [--out benchmarks/results/ceiling_cpu.json]
    python benchmarks/ceiling.py RUN_DIR --set model.encoding_options.log2_hashmap_size=19 --bounds truth

``--set`` and ``--bounds`` measure another representation's ceiling on the same scene without
training it: a dotted key of the run's ``config.json`` with a JSON value (the grid, the width, K), and
bounds fitted to the true volume itself (``truth``: the mixture's valleys as the paper places them,
the top bound at the truth's maximum, K by BIC or ``model.num_materials`` when set).

For each k-neas (or any neural) run folder on a built-in scene: a fresh model of the run's own
config (same encoding, K, bounds from its ``bounds.json``, same empty-space grid) is fitted to the
scene's **ground-truth** volume at the voxel centres with the warm start's loss
(``stages.warm_start.warm_start``: MSE of mu + occupancy term + eikonal, ``--steps`` Adam steps of
the warm-start stage's voxel centres per step). Its psnr3d / ssim3d is how far this representation
can go; the run's own psnr3d is how far training from the projections got. Not part of the test
suite.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np
from run_rows import run_rows


def changed_config(run_dir: Path, settings: list[str]):
    """The run's config with ``KEY=VALUE`` settings (dotted config.json keys, JSON values) applied."""
    from kneas_method.engine.loading import config_from_dict

    data = json.loads((run_dir / "config.json").read_text(encoding="utf-8"))
    for setting in settings:
        key, sep, text = setting.partition("=")
        if not sep or not key:
            raise SystemExit(f"error: --set takes KEY=VALUE (a dotted config.json key), got {setting!r}")
        try:
            value = json.loads(text)
        except ValueError:
            value = text
        *sections, leaf = key.split(".")
        parent = data
        for name in sections:
            if not isinstance(parent.get(name), dict):
                raise SystemExit(f"error: --set {key}: {name!r} is not a section of the run's config.json")
            parent = parent[name]
        parent[leaf] = value
    return config_from_dict(data, f"{run_dir / 'config.json'} with --set")


def truth_bounds(gt: np.ndarray, K) -> tuple[list, list]:
    """Bounds fitted to the true volume: the paper's mixture valleys, the top at the truth's maximum."""
    from kneas_method.bounds import GMMBounds

    fit = GMMBounds(n_components=K, upper_percentile=100.0, upper_factor=1.02).fit(gt.reshape(-1))
    return [float(v) for v in fit.alphas_], [float(v) for v in fit.betas_]


def ceiling(run_dir: Path, steps: int, settings: list[str] = (), bounds_from: str = "run") -> dict:
    from kneas_method.engine.evaluate import sample_volume
    from kneas_method.engine.loading import load_scene
    from kneas_method.engine.loss_scale import loss_scale
    from kneas_method.engine.trainer import Trainer
    from kneas_method.engine.visual_hull import set_visual_hull
    from kneas_method.stages.warm_start import WarmStartConfig, warm_start
    from kneas_method.evaluation.metrics import volume_metrics

    config = changed_config(run_dir, list(settings))
    scene = load_scene(config)
    if scene.image is None:
        raise SystemExit(f"{run_dir}: the scene has no ground-truth volume; the ceiling needs a built-in scene")
    bounds = None
    if (run_dir / "bounds.json").is_file():
        b = json.loads((run_dir / "bounds.json").read_text(encoding="utf-8"))
        bounds = (b["alphas"], b["betas"])
    gt = np.asarray(scene.image, dtype=np.float32)
    if bounds_from == "truth":
        asked = next((v for v in settings if v.startswith("model.num_materials=")), None)
        bounds = truth_bounds(gt, int(config.model.num_materials) if asked else None)
        config.model.num_materials = len(bounds[0])
    elif bounds is not None and len(bounds[0]) != config.model.num_materials:
        raise SystemExit(f"error: the run's bounds have K = {len(bounds[0])}, --set asks {config.model.num_materials}; add --bounds truth")
    with tempfile.TemporaryDirectory() as tmp:
        trainer = Trainer(config, scene, Path(tmp), epochs=1, device="cpu", bounds=bounds, label="ceiling", loss_scale=loss_scale(scene))
        if trainer.model.occupancy is not None:
            set_visual_hull(trainer.model, scene, "ceiling")
        fit = config.stages.warm_start or WarmStartConfig()
        seconds = warm_start(trainer, gt, steps, int(fit.points), what="ground-truth", occupancy_weight=float(fit.occupancy))
        volume = sample_volume(trainer.model, scene.geometry)
    m = volume_metrics(volume, gt)
    run_metrics = json.loads((run_dir / "metrics.json").read_text(encoding="utf-8")) if (run_dir / "metrics.json").is_file() else {}
    return {"run": str(run_dir), "scene": scene.name, "method": config.method, "steps": steps, "fit_seconds": round(seconds, 1),
            "settings": list(settings), "bounds": bounds_from, "K": len(bounds[0]) if bounds else None,
            "top_bound": round(float(np.sum(np.array(bounds)[:, -1])), 4) if bounds else None,
            "ceiling_psnr3d": round(float(m["psnr3d"]), 2), "ceiling_ssim3d": round(float(m["ssim3d"]), 4),
            "run_psnr3d": run_metrics.get("psnr3d"), "run_ssim3d": run_metrics.get("ssim3d")}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+", type=Path, help="run folders written by kneas-train on built-in scenes")
    p.add_argument("--steps", type=int, default=1500, help="Adam steps of the fit to the exact volume (default 1500)")
    p.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                   help="change the run's config first: a dotted config.json key and a JSON value (model.attenuation_options.hidden_dim=64)")
    p.add_argument("--bounds", choices=("run", "truth"), default="run",
                   help="the run's bounds.json (default) or bounds fitted to the true volume, its whole range covered")
    p.add_argument("--out", type=Path, default=None, help="write the rows as JSON here")
    args = p.parse_args(argv)
    run_rows(args.runs, lambda run: ceiling(run, args.steps, args.set, args.bounds), args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
