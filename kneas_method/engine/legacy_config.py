"""``config.json`` files written by older kneas, upgraded to today's settings on load, so that their runs
still evaluate, export and resume as they were trained.

Until 2026-12-02 (f57f826) a neural run's stages outside the training loop were flat ``trainer``
settings (``warm_start``, ``warm_start_anchor``, ``correction_passes``, ``denoise``, ``time_budget``,
...) with ``bounds_volume`` at the top; :func:`upgrade` maps them onto ``procedure`` and ``stages``.
Until 2026-12-07 the anchor had one weight on every scan: an older ``stages.anchor`` gets
``weight_at_noise`` None (that weight where the start fits the views to their noise too).
"""

from __future__ import annotations

from typing import Any, Callable

# keys of older config.json files, dropped on load
DROPPED = ("reconstructor",)
# the flat trainer settings of the stages, before they had configs of their own
STAGE_KEYS = ("warm_start", "warm_start_steps", "warm_start_points", "warm_start_occupancy", "warm_start_anchor", "anchor_points",
              "anchor_region", "anchor_outside", "fit_outside", "anchor_occupancy", "anchor_edge_contrast", "correction_passes",
              "correction_iterations", "correction_weights", "correction_ring", "correction_refresh", "correction_noise_factor",
              "correction_steps", "correction_lr", "correction_points", "correction_curvature", "correction_solve", "denoise",
              "denoise_steps", "denoise_lr", "materials_refit_steps", "time_budget")


def upgrade(data: dict, attenuation_has_width: Callable[[str, dict], bool]) -> dict:
    """``data`` (a config.json's dict, with a ``method``) in today's settings. ``attenuation_has_width``
    tells whether the method's attenuation network has a ``hidden_dim`` (older surface runs were 64 wide)."""
    data = dict(data)
    for key in DROPPED:
        data.pop(key, None)
    if "fdk_filter" in data:  # older neural configs kept the FDK window at the top
        data.setdefault("reconstruction", {})["filter"] = data.pop("fdk_filter")
    model = data.get("model")
    if isinstance(model, dict) and model.get("reference") is False:
        data["model"] = model = {k: v for k, v in model.items() if k != "reference"}
    stages = data.get("stages")
    if isinstance(stages, dict) and isinstance(stages.get("anchor"), dict) and "weight_at_noise" not in stages["anchor"]:
        data["stages"] = dict(stages, anchor=dict(stages["anchor"], weight_at_noise=None))
    trainer = data.get("trainer")
    if not isinstance(trainer, dict) or not any(k in trainer for k in STAGE_KEYS) and "bounds_volume" not in data:
        return data
    t = dict(trainer)
    if "warm_start_steps" in t and isinstance(model, dict) and isinstance(model.get("attenuation_options"), dict) \
            and "hidden_dim" not in model["attenuation_options"] and attenuation_has_width(data["method"], model):
        # written before 2026-11-27 (d39c0ca), whose presets left the attenuation networks at their 64-wide default
        data["model"] = dict(model, attenuation_options=dict(model["attenuation_options"], hidden_dim=64))
    if "correction_solve" in t:  # the band ("band") or its steep voxels only ("edges"): a ring weight of 1 or 0
        t.setdefault("correction_ring", 0.0 if t.pop("correction_solve") == "edges" else 1.0)
    if "correction_passes" in t and "denoise" not in t:
        t["denoise"] = "none"  # the correction stage ended with the passes
    if "denoise" in t and "denoise_steps" not in t:  # Gaussians alone, fitted as a pass fits
        t.update(denoise="sure-gaussian" if t["denoise"] == "sure" else t["denoise"],
                 denoise_steps=t.get("correction_steps", 75), denoise_lr=t.get("correction_lr", 1e-4))
    if "denoise_steps" in t and "materials_refit_steps" not in t:
        t["materials_refit_steps"] = 0  # the start's materials were kept
    old = {k: t.pop(k) for k in STAGE_KEYS if k in t}
    bounds_volume = data.pop("bounds_volume", None)
    warm = old.get("warm_start")
    start = warm if warm not in (None, "none") else bounds_volume if bounds_volume not in (None, "prior") else None
    if all(v is None for v in old.values()) and bounds_volume is None:  # left to the preset: today's preset decides
        data["trainer"] = t
        return data
    stages: dict[str, Any] = dict(data.get("stages") or {})
    stages["classical_start"] = {"algorithm": start} if start else None
    stages["warm_start"] = ({"steps": int(old.get("warm_start_steps") or 0), "points": old.get("warm_start_points", 16384),
                             "occupancy": old.get("warm_start_occupancy", 0.01)}
                            if start and warm not in (None, "none") and old.get("warm_start_steps") else None)
    anchor = float(old.get("warm_start_anchor") or 0.0)
    stages["anchor"] = ({"weight": anchor, "weight_at_noise": None, "points": old.get("anchor_points", 4096), "occupancy": old.get("anchor_occupancy") or 0.0,
                         "edge_contrast": old.get("anchor_edge_contrast") or 0.0, "region": old.get("anchor_region", "box")}
                        if start and anchor > 0 else None)
    passes = int(old.get("correction_passes") or 0)
    stages["correction"] = ({"passes": passes, "iterations": old.get("correction_iterations", 4),
                             "weights": old.get("correction_weights", "ring"),
                             "ring": 0.5 if old.get("correction_ring") is None else old["correction_ring"],
                             "refresh": old.get("correction_refresh", 3), "noise_factor": old.get("correction_noise_factor", 1.5),
                             "steps": old.get("correction_steps", 75), "lr": old.get("correction_lr", 1e-4),
                             "points": old.get("correction_points", 8192), "curvature": old.get("correction_curvature", 3e-3)}
                            if passes else None)
    denoise = old.get("denoise")
    stages["smoothing"] = ({"rule": denoise, "steps": old.get("denoise_steps", 300), "lr": old.get("denoise_lr", 1e-3),
                            "points": old.get("correction_points", 8192), "curvature": old.get("correction_curvature", 3e-3)}
                           if passes and denoise in ("sure", "sure-gaussian") else None)
    refit = int(old.get("materials_refit_steps") or 0)
    stages["materials_refit"] = ({"steps": refit, "points": old.get("warm_start_points", 16384),
                                  "occupancy": old.get("warm_start_occupancy", 0.01)} if passes and refit else None)
    budget = float(old.get("time_budget") or 0.0)
    stages["time_budget"] = {"seconds": budget} if budget else None
    data["stages"] = stages
    data["trainer"] = t
    data.setdefault("procedure", "refine-classical" if any(v is not None for v in stages.values()) else "paper")
    return data
