"""The end of a run: one metrics dict per kind of run, ``metrics.json``, and the summary block.

:func:`neural_metrics` and :func:`classical_metrics` build ``metrics.json`` (the SPEC §5
metrics, the run's facts, the time of every stage); :func:`finish` writes it and prints
the summary: the headline metrics, the time per stage, the run folder and the next
commands to run on it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import torch

from ..console import console, say
from .code_version import code_version
from .machine import machine_record
from .progress import _duration, summary_table
from .run_dir import write_json

# (metrics key, label) of the core's times and the classical runs', in the order they run; the stages'
# times are their records' ``seconds`` (``stages`` in metrics.json)
CORE_TIMES = (("prior_time_s", "prior"), ("bounds_time_s", "bounds"), ("reconstruct_time_s", "reconstruction"),
              ("train_time_s", "training"))


def split_per_view(metrics: dict) -> tuple[dict, dict]:
    """``(headline, per_view)``: the ``*_per_view`` lists apart from the rest."""
    per_view = {k: v for k, v in metrics.items() if k.endswith("_per_view")}
    return {k: v for k, v in metrics.items() if k not in per_view}, per_view


def scene_notes(scene) -> list[str]:
    """What the metrics of a scene cannot say (no ground truth, held-out training views)."""
    notes = []
    if scene.image is None:
        notes.append("the scene has no ground-truth volume: no 3D metrics (psnr3d, ssim3d)")
    if "holdout" in scene.meta:
        h = scene.meta["holdout"]
        notes.append(f"the scene has no held-out views: training views {h['held_out_training_views']} (of {h['of']}) "
                     "were held out of training for the 2D metrics")
    return notes


def _common(config, scene, evaluation, device) -> tuple[dict, dict]:
    headline, per_view = split_per_view(evaluation.metrics)
    out = {**headline, "method": config.method, "scene": scene.name, "views": len(scene.train)}
    # the thread count changes the order of floating-point sums, so a neural run's figures follow it as they follow the seed
    facts = {"preset": config.preset, "scene_source": scene.source, "device": str(device), "threads": torch.get_num_threads(),
             "code": code_version(), "machine": machine_record(device)}
    notes = scene_notes(scene)
    if notes:
        facts["notes"] = notes
    return out, {**facts, "_per_view": per_view}


def classical_metrics(config, scene, reconstruction, evaluation, device) -> dict:
    """``metrics.json`` of a classical run."""
    out, facts = _common(config, scene, evaluation, device)
    per_view = facts.pop("_per_view")
    out.update(parameters=0, steps=0, algorithm=config.algorithm, settings=reconstruction.settings,
               wall_time_s=reconstruction.seconds + evaluation.seconds,
               reconstruct_time_s=reconstruction.seconds, eval_time_s=evaluation.seconds, **facts)
    out.update(per_view)
    return out


def neural_metrics(config, scene, trainer, bounds, evaluation, device, *, stages: list[str], records: dict,
                   session_wall_time_s: float) -> dict:
    """``metrics.json`` of a neural run (``bounds``: a BoundsResult, or None without surfaces;
    ``stages``: the names of the stages it ran, in order; ``records``: what each did)."""
    out, facts = _common(config, scene, evaluation, device)
    per_view = facts.pop("_per_view")
    prior_time = bounds.prior_wall_time_s if bounds is not None else 0.0
    bounds_time = float(bounds.details.get("fit_time_s", 0.0)) if bounds is not None else 0.0  # the GMM fit
    ran = {name: records.get(name) for name in stages}
    stage_time = sum(float((r or {}).get("seconds", 0.0)) for r in ran.values())
    out.update(parameters=trainer.model.num_parameters(), steps=trainer.step, epochs=trainer.epochs, procedure=config.procedure,
               wall_time_s=trainer.wall_time_s + prior_time + bounds_time + stage_time + evaluation.seconds,
               train_time_s=trainer.wall_time_s, prior_time_s=prior_time, bounds_time_s=bounds_time,
               stages=ran, stage_scores=list(records.get("scores", [])), loss_scale=float(trainer.model.loss_scale),
               eval_time_s=evaluation.seconds, **facts, bad_steps=len(trainer.bad_steps))
    if trainer.model.has_surfaces:
        out["num_materials"] = int(trainer.model.num_materials)
        out["alphas"], out["betas"] = trainer.model.bounds
        out["bounds_source"] = bounds.source if bounds is not None else None
        if bounds is not None and "prior_reused" in bounds.details:
            out["prior_reused"] = bounds.details["prior_reused"]
            out["prior_run"] = bounds.details.get("prior_run")
    out["session_wall_time_s"] = session_wall_time_s
    out.update(per_view)
    return out


def stage_times(metrics: dict) -> str:
    """``prior 0 s, classical-start 28 s, ..., total 8 min 10 s`` (what took time, in the order it ran)."""
    records = metrics.get("stages") if isinstance(metrics.get("stages"), dict) else {}
    seconds = {name: (r or {}).get("seconds") if isinstance(r, dict) else None for name, r in records.items()}
    core = {label: metrics.get(key) for key, label in CORE_TIMES}
    times = ([("classical-start", seconds.get("classical-start"))] + [(label, core[label]) for label in ("prior", "bounds", "reconstruction")]
             + [("warm-start", seconds.get("warm-start")), ("training", core["training"])]
             + [(name, v) for name, v in seconds.items() if name not in ("classical-start", "warm-start")]
             + [("evaluation", metrics.get("eval_time_s"))])
    parts = [f"{label} {_duration(v)}" for label, v in times if isinstance(v, (int, float)) and v > 0]
    total = metrics.get("wall_time_s")
    if isinstance(total, (int, float)):
        parts.append(f"total {_duration(total)}")
    return ", ".join(parts)


def next_commands(run_dir: Path, surfaces: bool) -> list[str]:
    mesh = "one surface mesh per material" if surfaces else "iso-surfaces of the attenuation (Otsu threshold)"
    return [f"kneas-export mesh {run_dir}      # {mesh}",
            f"kneas-export volume {run_dir}    # .npy attenuation and label volumes (+ NIfTI with [nifti])",
            f"kneas-export figures {run_dir}   # projections, slices, weight maps",
            f"kneas-eval {run_dir}             # re-evaluate (surface metrics on built-in scenes)"]


def print_summary(run_dir: Path, metrics: dict) -> None:
    """The summary block: headline metrics, time per stage, notes, run folder, next commands."""
    console.print(summary_table(metrics, title=f"{metrics.get('method')} on {metrics.get('scene')}"))
    times = stage_times(metrics)
    if times:
        say(f"time per stage: {times}", markup=False)
    for note in metrics.get("notes", []) or []:
        say(f"note: {note}", markup=False)
    say(f"run folder: {run_dir}", markup=False)
    say("next:", markup=False)
    for line in next_commands(run_dir, "num_materials" in metrics):
        say(f"  {line}", markup=False)


def with_fitting_box(metrics: dict, fitting) -> dict:
    """``metrics`` with the slices the fitted box has beyond the scene's at each end
    (``fitting_box_extra_slices``, ``data.truncation.FittingBox``) and a note, where it has any, and
    ``wider_than_view`` with a note where the object is wider than the field of view."""
    if fitting is not None and fitting.wider_than_view:
        metrics["wider_than_view"] = True
        metrics["notes"] = list(metrics.get("notes") or []) + [
            "the object is wider than the detector's field of view: the volume outside it is not measured by every view"]
    if fitting is not None and fitting.slices:
        metrics["fitting_box_extra_slices"] = int(fitting.slices)
        metrics["notes"] = list(metrics.get("notes") or []) + [
            f"the object goes on beyond the box along the axis: the views were fitted on a box {fitting.slices} slices longer at "
            "each end and the volume kept on the scene's box"]
    return metrics


def finish(run_dir: Path, metrics: dict) -> int:
    """Write ``metrics.json`` and print the summary block; returns 0."""
    write_json(Path(run_dir) / "metrics.json", metrics)
    print_summary(Path(run_dir), metrics)
    return 0
