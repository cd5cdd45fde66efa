"""Presets: fill the settings a run leaves at ``None`` (SPEC §3).

- ``paper``: the paper's schedule and architecture exactly (1000 epochs, 512 +
  128 rays, 320 / 128 samples, the full 14-level 2^19 hash grid, exact eikonal
  on every sample).
- ``cpu``: a much smaller schedule for 2 CPU cores, meant to finish a k-neas
  foot run, prior model included, in under 15 minutes (see the comment on
  ``TABLE["cpu"]`` for what was measured and what is still missing).
- ``tiny``: seconds; for tests and smoke runs.
- ``auto``: ``paper`` when CUDA is available, else ``cpu``; :func:`choose`
  says which and why, and the run prints it.

Anything the user set (not ``None``) wins over the preset; ``encoding_options``
are merged key by key (user keys win).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import torch

from .config import to_dict, update_from_dict
from .errors import ConfigError
from .methods import PRESETS, RunConfig, TrainConfig
from .model import build_component, field_has_surfaces

PAPER_HASHGRID = {"num_levels": 14, "features_per_level": 2, "log2_hashmap_size": 19, "base_resolution": 16, "per_level_scale": 2.0}

TABLE: dict[str, dict[str, dict[str, Any]]] = {
    "paper": {
        "hashgrid": PAPER_HASHGRID,
        "attenuation": {"hidden_dim": 64},
        "model": {"num_samples": 320, "num_eval_samples": 128, "eikonal_fraction": 1.0, "s_init": 20.0, "lambda_eikonal": 0.01,
                  "occupancy_grid": False, "quadrature": "bins"},
        "datamanager": {"num_object_rays": 512, "num_air_rays": 128},
        "trainer": {"epochs": 1000, "prior_epochs": 1000, "lr": 1e-3, "lr_decay_at": 0.5, "eval_every": 100, "checkpoint_every": 100, "eval_chunk": 8192, "eval_views": None, "eval_projections": "rendered",
                    "warm_start": "none", "warm_start_steps": 0, "warm_start_anchor": 0.0, "anchor_occupancy": 0.0, "anchor_edge_contrast": 0.0, "correction_passes": 0, "denoise": "none", "time_budget": 0.0},
        "run": {"bounds_volume": "prior", "bounds_max_materials": 4, "bounds_k_rule": "bic", "bounds_min_std": 0.0, "bounds_gmm_restarts": 1},
    },
    # CPU preset (2 cores, torch hash grid): 6 levels, 2^16 entries, scale 1.75
    # (finest resolution 263 across the volume box: a cell of about half a voxel on the built-in
    # 128^3 volumes; scale 1.6, finest 168, until the 72nd stop: abdomen 42.24 -> 43.56 dB, jaw
    # 41.55 -> 41.91; 1.9 and 2.0 were worse, docs/experiments.md), 128 + 32 rays x 64
    # samples, the exact eikonal on every sample with lambda 1e-5 (the paper's 0.01
    # dominates the ~1e-5 intensity loss of NAF-convention data in a short run), s
    # starting at 100, 64 evenly spaced evaluation samples in 256-ray chunks, a
    # 80-epoch model (4000 steps on 50 views; 2000 steps of 256 + 64 rays until the 52nd
    # stop: the same rays in twice the steps gave abdomen +0.61 dB, the other six scenes +0.00 to
    # +0.06, training 1.26x as long; the prior, an option here, keeps its rays: 40 epochs;
    # docs/experiments.md). Bounds from the ASD-POCS reconstruction,
    # and a 300-step warm start fitting the model to it (options beside the paper's
    # procedure; see docs/experiments.md for what each lever measured on foot:
    # 22.0 dB with the paper's procedure -> 33.9 dB from FDK, 34.2 from SART, 34.7 from ASD-POCS),
    # and the visual-hull occupancy grid, which puts the 64 samples on the stretch of each ray that
    # can hold material (~0.8 voxel spacing instead of 2-3 voxels): 34.7 -> 38.5 dB on foot;
    # the ASD-POCS volume kept as a prior during projection training (anchor 0.01): foot 38.8,
    # chest 35.9 -> 37.4 dB; and the final 2D metrics on the held-out views projected from the
    # model's volume (Joseph), 7 s instead of 1 min 21 s on foot. Materials: K = 1..6 (first), the lowest
    # BIC among K whose boundaries are all density valleys (the paper: 1..4 by BIC, which chose
    # K = 3 on abdomen and left bone without a material): abdomen 37.16 -> 39.17 dB, chest
    # 37.43 -> 37.62, foot 38.79 -> 38.56, jaw 40.66 -> 40.13 (docs/experiments.md). The voxel-planes
    # quadrature (--model.quadrature voxel-planes) stays an option: +0.0-0.2 dB on the built-in scenes,
    # but twice the samples and -0.25 dB on a head that fills the box (docs/experiments.md).
    # The anchor keeps the ASD-POCS volume's labels too, where they are trusted (>= 2 voxels from
    # any other label; anchor occupancy 0.03): a material whose level sits near a boundary
    # (head-256's ventricles) keeps its label, ventricle Dice 0.00 -> 0.93; 0.01 did not keep it,
    # 0.1 cost chest's blood (docs/experiments.md). Then K = 1..8, each mixture the best of 3 k-means
    # starts: one start misjudged K on abdomen and merged kidney with liver (kidney Dice 0 -> 0.89,
    # abdomen 39.28 -> 39.58 dB, foot 38.65 -> 38.87, the other five scenes within 0.01 dB).
    # Now K and the bounds come from the histogram's peaks (--bounds-k-rule peaks: one material per
    # peak, boundaries at its valleys, no mixture, the same at every seed; the mixtures' K moved with
    # the seed and lost abdomen's kidney at seed 1), falling back to the rule above where the histogram
    # has fewer than two peaks (noisy scans): over seeds 0 and 1 the four built-in scenes +0.06 dB on
    # average, the kidney kept at both, held-out head-256 +1.0 dB, every run faster (docs/experiments.md).
    # The attenuation networks (shared body and K heads) 32 wide instead of the paper's 64 (61st stop):
    # a step at K = 7 is 22 % cheaper; abdomen +0.16 dB, head-256 +0.18, chest 11:41 -> 9:54;
    # 16 wide cost head-256 1.96 dB (docs/experiments.md).
    "cpu": {
        "hashgrid": {"num_levels": 6, "features_per_level": 2, "log2_hashmap_size": 16, "base_resolution": 16, "per_level_scale": 1.75},
        "attenuation": {"hidden_dim": 32},
        "model": {"num_samples": 64, "num_eval_samples": 64, "eikonal_fraction": 1.0, "s_init": 100.0, "lambda_eikonal": 1e-5,
                  "occupancy_grid": True, "quadrature": "bins"},
        "datamanager": {"num_object_rays": 128, "num_air_rays": 32},
        "trainer": {"epochs": 80, "prior_epochs": 40, "lr": 1e-3, "lr_decay_at": 0.85, "eval_every": 16, "checkpoint_every": 4, "eval_chunk": 256, "eval_views": 3, "eval_projections": "volume",
                    "warm_start": "asd-pocs", "warm_start_steps": 300, "warm_start_anchor": 0.01, "anchor_occupancy": 0.03, "anchor_edge_contrast": 0.0, "correction_passes": 12, "denoise": "sure", "time_budget": 600.0},
        "run": {"bounds_volume": "asd-pocs", "bounds_max_materials": 8, "bounds_k_rule": "peaks", "bounds_min_std": 0.0, "bounds_gmm_restarts": 3},
    },
    "tiny": {
        "hashgrid": {"num_levels": 3, "features_per_level": 2, "log2_hashmap_size": 10, "base_resolution": 4, "per_level_scale": 2.0},
        "attenuation": {"hidden_dim": 64},
        "model": {"num_samples": 16, "num_eval_samples": 16, "eikonal_fraction": 1.0, "s_init": 20.0, "lambda_eikonal": 0.01,
                  "occupancy_grid": False, "quadrature": "bins"},
        "datamanager": {"num_object_rays": 32, "num_air_rays": 8},
        "trainer": {"epochs": 2, "prior_epochs": 1, "lr": 1e-3, "lr_decay_at": 0.5, "eval_every": 1, "checkpoint_every": 1, "eval_chunk": 1024, "eval_views": 2, "eval_projections": "rendered",
                    "warm_start": "none", "warm_start_steps": 5, "warm_start_anchor": 0.0, "anchor_occupancy": 0.0, "anchor_edge_contrast": 0.0, "correction_passes": 0, "denoise": "none", "time_budget": 0.0},
        "run": {"bounds_volume": "prior", "bounds_max_materials": 4, "bounds_k_rule": "bic", "bounds_min_std": 0.0, "bounds_gmm_restarts": 1},
    },
}


def choose(preset: str) -> tuple[str, str]:
    """``(concrete preset, reason)`` for a requested preset name."""
    if preset not in PRESETS:
        raise ConfigError(f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
    if preset != "auto":
        return preset, f"preset '{preset}' as requested"
    if torch.cuda.is_available():
        return "paper", f"preset 'paper' chosen automatically: CUDA GPU found ({torch.cuda.get_device_name(0)})"
    return "cpu", "preset 'cpu' chosen automatically: no CUDA GPU, and the paper schedule would take days on CPU (use --preset paper to force it)"


def k_from_data(config: TrainConfig) -> bool:
    """True when K is left for the data to decide: a soft-selector, multi-head surface
    method with ``num_materials`` unset and no explicit ``model.alphas``; K then comes from
    BIC on the bounds volume (automatic bounds) or from the ``--bounds`` file."""
    m = config.model
    return (config.num_materials is None and field_has_surfaces(m)
            and m.attenuation != "single" and m.selector != "hard" and m.alphas is None
            and (config.bounds is not None or config.bounds_source == "auto"))


def automatic_bounds(config: TrainConfig) -> bool:
    """True when the run estimates its bounds (SPEC §4) rather than being given them."""
    return (field_has_surfaces(config.model) and config.bounds_source == "auto" and config.bounds is None
            and config.model.alphas is None)


def attenuation_options(model, preset_options: dict[str, Any]) -> dict[str, Any]:
    """The attenuation network's options: the preset's (those its config has, e.g. ``hidden_dim``)
    with the user's ``model.attenuation_options`` on top, key by key."""
    own = {f.name for f in dataclasses.fields(build_component("attenuations", model.attenuation))}
    merged = {k: v for k, v in preset_options.items() if k in own}
    merged.update(model.attenuation_options or {})
    return merged


def _fill(obj, values: dict[str, Any]):
    changes = {k: v for k, v in values.items() if getattr(obj, k) is None}
    return dataclasses.replace(obj, **changes) if changes else obj


# Numeric settings checked before any work starts: (section, setting, whole number?, lowest, lowest allowed?).
# A setting the run leaves at None is the preset's or unused, and is not checked.
NUMBER_RULES = (
    ("model", "num_samples", True, 1, True), ("model", "num_eval_samples", True, 1, True),
    ("model", "s_init", False, 0, False), ("model", "lambda_eikonal", False, 0, True),
    ("model", "eikonal_fraction", False, 0, False), ("model", "eikonal_fd_step", False, 0, False),
    ("model", "floater_fraction", False, 0, True), ("model", "lambda_floater", False, 0, True),
    ("model", "occupancy_resolution", True, 1, True),
    ("trainer", "lr", False, 0, False), ("trainer", "lr_decay_factor", False, 0, False),
    ("trainer", "eval_every", True, 0, True), ("trainer", "checkpoint_every", True, 0, True),
    ("trainer", "eval_chunk", True, 1, True), ("trainer", "eval_views", True, 1, True),
    ("trainer", "log_every", True, 1, True), ("trainer", "max_bad_steps", True, 0, True),
    ("trainer", "anchor_points", True, 1, True), ("trainer", "correction_passes", True, 0, True),
    ("trainer", "correction_iterations", True, 0, True), ("trainer", "correction_steps", True, 0, True),
    ("trainer", "correction_points", True, 0, True), ("trainer", "correction_refresh", True, 1, True),
    ("trainer", "denoise_steps", True, 0, True), ("trainer", "materials_refit_steps", True, 0, True),
    ("trainer", "correction_noise_factor", False, 0, True), ("trainer", "correction_lr", False, 0, True),
    ("trainer", "correction_curvature", False, 0, True), ("trainer", "denoise_lr", False, 0, True),
    ("trainer", "time_budget", False, 0, True),
    ("datamanager", "num_object_rays", True, 0, True), ("datamanager", "num_air_rays", True, 0, True),
    ("reconstruction", "iterations", True, 1, True), ("reconstruction", "subsets", True, 1, True),
    ("reconstruction", "relaxation", False, 0, False), ("reconstruction", "tv_steps", True, 0, True),
    ("reconstruction", "tv_alpha", False, 0, True),
)


def check_numbers(config) -> None:
    """One-line ConfigError for the first setting of :data:`NUMBER_RULES` out of its range (a
    count below 1, a learning rate of 0, ...), named as its command-line flag."""
    for section, name, whole, lowest, inclusive in NUMBER_RULES:
        value = getattr(getattr(config, section, None), name, None)
        if value is None:
            continue
        number = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
        if whole:
            number = number and float(value).is_integer()
        if not (number and (value >= lowest if inclusive else value > lowest)):
            what = ("a whole number >= " if whole else "a number >= " if inclusive else "a number > ") + f"{lowest:g}"
            raise ConfigError(f"--{section}.{name.replace('_', '-')} must be {what}, got {value!r}")
    rays = getattr(config, "datamanager", None)
    if rays is not None and rays.num_object_rays is not None and rays.num_air_rays is not None and rays.num_object_rays + rays.num_air_rays < 1:
        raise ConfigError("--datamanager.num-object-rays and --datamanager.num-air-rays are both 0; give at least one ray per step")


def validate_choices(config: RunConfig) -> RunConfig:
    """Every setting checked against its type (``Literal`` choices included); a one-line
    ConfigError names the first that does not fit."""
    return update_from_dict(config, to_dict(config), where="config")


def resolve(config: RunConfig) -> RunConfig:
    """Return a copy of ``config`` with the preset applied and ``config.preset`` made concrete.

    Neural runs (:class:`TrainConfig`) also get ``num_materials`` applied to the model,
    checked against the method. The reason for the preset choice is
    :func:`choose` ``(config.preset)[1]``, computed before resolving.
    """
    name, _ = choose(config.preset)
    config = validate_choices(config)
    if not isinstance(config, TrainConfig):
        check_numbers(config)  # its reconstruction's settings, before any scene is loaded or run folder made
        return dataclasses.replace(config, preset=name)
    table = TABLE[name]
    model = _fill(config.model, table["model"])
    if model.encoding == "hashgrid":
        merged = dict(table["hashgrid"])
        merged.update(model.encoding_options or {})
        model = dataclasses.replace(model, encoding_options=merged)
    elif model.encoding_options is None:
        model = dataclasses.replace(model, encoding_options={})
    surfaces = field_has_surfaces(model)
    if surfaces:
        model = dataclasses.replace(model, attenuation_options=attenuation_options(model, table["attenuation"]))
    K = config.num_materials
    if K is not None:
        if not surfaces:
            raise ConfigError(f"method {config.method!r} has no materials; drop --num-materials")
        if K < 1:
            raise ConfigError(f"--num-materials must be >= 1, got {K}")
        if model.attenuation == "single" and K != 1:
            raise ConfigError(f"method {config.method!r} is single-material; drop --num-materials or use a K-material method such as k-neas")
        if model.selector == "hard" and K != 2:
            raise ConfigError(f"method {config.method!r} uses the hard selector, which works only with 2 materials; use --num-materials 2 or a soft-selector method such as k-neas")
        model = dataclasses.replace(model, num_materials=K)
    elif surfaces and not k_from_data(dataclasses.replace(config, model=model)):
        K = model.num_materials
        if model.selector == "hard" and K != 2:  # refused here, before a prior is trained or bounds are fitted
            raise ConfigError(f"the hard selector works only with 2 materials, and {config.method} has K = {K}; "
                              "add --num-materials 2 (with --bounds, a 2-material file)")
    trainer = _fill(config.trainer, table["trainer"])
    if not (isinstance(trainer.warm_start_steps, int) and trainer.warm_start_steps >= 0):
        raise ConfigError(f"trainer.warm_start_steps must be a whole number >= 0, got {trainer.warm_start_steps!r}")
    if not (isinstance(trainer.warm_start_points, int) and trainer.warm_start_points >= 1):
        raise ConfigError(f"trainer.warm_start_points must be a whole number >= 1, got {trainer.warm_start_points!r}")
    for weight in ("warm_start_occupancy", "anchor_occupancy", "anchor_edge_contrast"):
        value = getattr(trainer, weight)
        if not (isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value >= 0):
            raise ConfigError(f"trainer.{weight} must be a number >= 0, got {value!r}")
    anchor = trainer.warm_start_anchor
    if not (isinstance(anchor, (int, float)) and not isinstance(anchor, bool) and math.isfinite(anchor) and anchor >= 0):
        raise ConfigError(f"trainer.warm_start_anchor must be a number >= 0, got {anchor!r}")
    if trainer.warm_start == "none" and config.trainer.warm_start_anchor is None:
        trainer = dataclasses.replace(trainer, warm_start_anchor=0.0)  # no warm-start volume, no prior from it
    elif anchor > 0 and trainer.warm_start == "none":
        raise ConfigError("trainer.warm_start_anchor keeps the warm-start volume as a prior, but warm_start is none; "
                          "give --trainer.warm-start asd-pocs (or another method) or --trainer.warm-start-anchor 0")
    if not trainer.warm_start_anchor and config.trainer.anchor_occupancy is None:
        trainer = dataclasses.replace(trainer, anchor_occupancy=0.0)  # no anchor, no labels in it
    elif trainer.anchor_occupancy and not trainer.warm_start_anchor:
        raise ConfigError("trainer.anchor_occupancy weighs the warm-start volume's labels inside the anchor, but there is no anchor "
                          "(warm_start_anchor 0); give --trainer.warm-start-anchor 0.01 or leave --trainer.anchor-occupancy out")
    if not trainer.warm_start_anchor and config.trainer.anchor_edge_contrast is None:
        trainer = dataclasses.replace(trainer, anchor_edge_contrast=0.0)  # no anchor, no weights in it
    elif trainer.anchor_edge_contrast and not trainer.warm_start_anchor:
        raise ConfigError("trainer.anchor_edge_contrast weighs the warm-start volume's voxels inside the anchor, but there is no anchor "
                          "(warm_start_anchor 0); give --trainer.warm-start-anchor 0.01 or leave --trainer.anchor-edge-contrast out")
    decay = trainer.lr_decay_at
    if not (isinstance(decay, (int, float)) and not isinstance(decay, bool) and 0 <= decay <= 1):
        raise ConfigError(f"trainer.lr_decay_at must be the fraction of the steps after which the rate drops, got {decay!r}; "
                          "give --trainer.lr-decay-at a number from 0 to 1 (0.5: the paper's)")
    ring = trainer.correction_ring
    if ring is not None and trainer.correction_weights != "ring":
        raise ConfigError(f"trainer.correction_ring weights the band's outer ring in the ring rule, and the correction weights are "
                          f"{trainer.correction_weights!r}; add --trainer.correction-weights ring or drop --trainer.correction-ring")
    if ring is not None and not (isinstance(ring, (int, float)) and not isinstance(ring, bool) and 0 <= ring <= 1):
        raise ConfigError(f"trainer.correction_ring must be a number from 0 (the band's steep voxels only) to 1 (the whole band), "
                          f"got {ring!r}; give --trainer.correction-ring 0.5 (the ring rule's default) or leave it out")
    if trainer.correction_passes and not surfaces:
        if config.trainer.correction_passes is not None:
            raise ConfigError(f"method {config.method!r} has no surfaces, and the band correction sharpens them to model the "
                              "grid's discretisation; drop --trainer.correction-passes or use a surface method such as k-neas")
        trainer = dataclasses.replace(trainer, correction_passes=0)  # the preset's, where it cannot apply
    if trainer.denoise in ("sure", "sure-gaussian") and not (trainer.correction_passes and trainer.correction_iterations):
        if config.trainer.denoise is not None:
            raise ConfigError(f"--trainer.denoise {trainer.denoise} smooths the volume at the end of the band correction, and this run has no "
                              "correction passes; give --trainer.correction-passes 12 (a surface method such as k-neas) or drop "
                              "--trainer.denoise")
        trainer = dataclasses.replace(trainer, denoise="none")  # the preset's, where there is no correction stage
    datamanager = _fill(config.datamanager, table["datamanager"])
    check_numbers(dataclasses.replace(config, model=model, trainer=trainer, datamanager=datamanager))
    run = {k: getattr(config, k) if getattr(config, k) is not None else v for k, v in table["run"].items()}
    stages = [("--trainer.epochs", trainer.epochs)]
    if automatic_bounds(config) and run["bounds_volume"] == "prior":
        stages.append(("--trainer.prior-epochs", trainer.prior_epochs))
    for flag, epochs in stages:  # refused here, before any scene is loaded or run folder made
        if not (isinstance(epochs, int) and not isinstance(epochs, bool) and epochs >= 1):
            raise ConfigError(f"{flag} must be a whole number >= 1, got {epochs!r}")
    if not (isinstance(run["bounds_max_materials"], int) and not isinstance(run["bounds_max_materials"], bool)
            and run["bounds_max_materials"] >= 1):
        raise ConfigError(f"--bounds-max-materials must be a whole number >= 1, got {run['bounds_max_materials']!r}")
    min_std = run["bounds_min_std"]
    if not (isinstance(min_std, (int, float)) and not isinstance(min_std, bool) and math.isfinite(min_std) and 0 <= min_std < 1):
        raise ConfigError(f"--bounds-min-std must be a fraction in [0, 1) of the 99.5th-percentile attenuation, got {min_std!r}")
    restarts = run["bounds_gmm_restarts"]
    if not (isinstance(restarts, int) and not isinstance(restarts, bool) and restarts >= 1):
        raise ConfigError(f"--bounds-gmm-restarts must be a whole number >= 1, got {restarts!r}")
    if run["bounds_k_rule"] == "peaks" and config.bounds_method != "gmm" and config.bounds_k_rule is None:
        run["bounds_k_rule"] = "bic-valleys"  # a mixture boundary rule was asked for: the preset's rule that fits mixtures
    if run["bounds_k_rule"] == "peaks" and config.bounds_method != "gmm" and config.num_materials is None:
        raise ConfigError(f"--bounds-k-rule peaks places its own boundaries (the histogram's valleys), so --bounds-method "
                          f"{config.bounds_method} would not be used; drop --bounds-method or use another --bounds-k-rule")
    return dataclasses.replace(
        config,
        preset=name,
        **run,
        num_materials=K,
        model=model,
        datamanager=datamanager,
        trainer=trainer,
    )


def procedure_notes(config: TrainConfig) -> list[str]:
    """Lines saying where a resolved config leaves the paper's procedure (printed by ``kneas-train``)."""
    notes: list[str] = []
    if not isinstance(config, TrainConfig):
        return notes
    if automatic_bounds(config) and config.bounds_volume != "prior":
        how = ("from the peaks of the {v} reconstruction's histogram (where it has fewer than two, a GMM on it after an "
               "edge-preserving filter), not from"
               if config.bounds_k_rule == "peaks" and k_from_data(config) else "the GMM is fitted on the {v} reconstruction, not on")
        notes.append(f"bounds: {how.format(v=config.bounds_volume.upper())} a trained NeAS-1M prior "
                     "(an option beside the paper's procedure; --bounds-volume prior for the paper's)")
    if k_from_data(config) and automatic_bounds(config) and (
            config.bounds_max_materials != 4 or config.bounds_k_rule != "bic" or config.bounds_min_std
            or config.bounds_gmm_restarts != 1):
        peaks = config.bounds_k_rule == "peaks"
        notes.append(("materials: one per peak of the volume's histogram, boundaries at its valleys, material 1's labels from half "
                      "its peak; if the histogram has fewer than two peaks, fitted to the volume after a bilateral filter"
                      + (" (and after training to the trained volume after that filter, whose extra materials replace the model's: "
                         "--trainer.materials-refit-steps 0 keeps the start's)" if config.trainer.materials_refit_steps else "")
                      + ", " if peaks else "materials: ")
                     + f"K = 1..{config.bounds_max_materials} by "
                     + ("the lowest BIC whose boundaries are all density valleys" if config.bounds_k_rule != "bic" else "BIC")
                     + (f", components at least {config.bounds_min_std:g} x the 99.5th percentile wide" if config.bounds_min_std else "")
                     + (f", the best of {config.bounds_gmm_restarts} GMM starts" if config.bounds_gmm_restarts != 1 else "")
                     + " (the paper: K = 1..4 by BIC; " + " ".join(
                         flag for flag, differs in (("--bounds-max-materials 4", config.bounds_max_materials != 4),
                                                    ("--bounds-k-rule bic", config.bounds_k_rule != "bic"),
                                                    ("--bounds-min-std 0", bool(config.bounds_min_std)),
                                                    ("--bounds-gmm-restarts 1", config.bounds_gmm_restarts != 1)) if differs)
                     + " for the paper's)")
    if config.trainer.warm_start != "none" and config.trainer.warm_start_steps:
        notes.append(f"warm start: the model is first fitted to the {config.trainer.warm_start.upper()} reconstruction for "
                     f"{config.trainer.warm_start_steps} steps (not in the paper; --trainer.warm-start none trains from the initialisation)")
    if config.trainer.warm_start != "none" and config.trainer.warm_start_anchor:
        notes.append(f"anchor: during projection training the field is also pulled towards the {config.trainer.warm_start.upper()} "
                     f"volume (weight {config.trainer.warm_start_anchor:g}"
                     + (f", and to its labels away from its edges, weight {config.trainer.anchor_occupancy:g} inside it"
                        if config.trainer.anchor_occupancy and field_has_surfaces(config.model) else "")
                     + (f", each voxel's value held less where the volume is steep (--trainer.anchor-edge-contrast "
                        f"{config.trainer.anchor_edge_contrast:g}; 0 holds every voxel alike)" if config.trainer.anchor_edge_contrast else "")
                     + "; not in the paper; --trainer.warm-start-anchor 0 turns it off)")
    if config.trainer.lr_decay_at != 0.5:
        notes.append(f"learning rate: x{config.trainer.lr_decay_factor:g} after {config.trainer.lr_decay_at:.0%} of the steps, not after half "
                     "of them (--trainer.lr-decay-at 0.5 for the paper's)")
    if config.trainer.eval_projections == "volume":
        notes.append("evaluation: 2D metrics on the held-out views projected from the volume at the voxel centres (Joseph projector, "
                     "as for the classical methods; the validation during training too), not rendered through the field "
                     "(--trainer.eval-projections rendered for the paper's)")
    if config.model.quadrature == "voxel-planes":
        notes.append("quadrature: one sample where each ray crosses each voxel-centre plane of its dominant axis (Joseph's rule "
                     "on the scene's voxel grid), not the paper's jittered bins (--model.quadrature bins for the paper's)")
    if config.model.occupancy_grid:
        notes.append("empty space: samples only on the stretch of each ray inside the visual hull of the training views "
                     "(not in the paper; --model.occupancy-grid False samples the whole volume box)")
    return notes
