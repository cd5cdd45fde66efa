"""Presets (how much compute) and the resolution of a run's config: what a run leaves at ``None`` is
filled by its preset and its procedure, and the whole tree is checked, before any work starts.

- ``paper``: the paper's schedule and architecture exactly (1000 epochs, 512 + 128 rays, 320 / 128
  samples, the full 14-level 2^19 hash grid, exact eikonal on every sample); procedure ``paper``.
- ``cpu``: a short schedule and a small grid for 2 CPU cores (80 epochs of 128 + 32 rays x 64
  samples, a 6-level 2^16 grid, 32-wide attenuation networks); procedure ``refine-classical``.
- ``tiny``: seconds; for tests and smoke runs; procedure ``paper``.
- ``auto``: ``paper`` when CUDA is available, else ``cpu``; :func:`choose` says which and why.

A preset sets compute only (epochs, rays, samples, grid, width, evaluation chunks); the procedure
(``kneas_method.stages.procedures``) sets how the model is fitted. Anything the user set (not
``None``) wins; ``encoding_options`` and ``attenuation_options`` are merged key by key (user keys win).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import torch

from . import registry
from .cli.common import did_you_mean
from .config import check_tree, to_dict, update_from_dict
from .errors import ConfigError
from .methods import PRESETS, RunConfig, TrainConfig
from .model import build_component, field_has_surfaces
from .stages import BUILT_IN, SURFACES_ONLY, Procedure, StageConfig, field_name

PAPER_HASHGRID = {"num_levels": 14, "features_per_level": 2, "log2_hashmap_size": 19, "base_resolution": 16, "per_level_scale": 2.0}

TABLE: dict[str, dict[str, Any]] = {
    "paper": {
        "procedure": "paper",
        "hashgrid": PAPER_HASHGRID,
        "attenuation": {"hidden_dim": 64},
        "model": {"num_samples": 320, "num_eval_samples": 128, "eikonal_fraction": 1.0, "quadrature": "bins"},
        "datamanager": {"num_object_rays": 512, "num_air_rays": 128},
        "trainer": {"epochs": 1000, "prior_epochs": 1000, "lr": 1e-3, "eval_every": 100, "checkpoint_every": 100,
                    "eval_chunk": 8192, "eval_views": None, "eval_projections": "rendered"},
    },
    # 2 cores, the torch hash grid: the finest of the 6 levels (scale 1.75) is a cell of about half a
    # voxel of a 128^3 volume; the 2D metrics on the held-out views projected from the model's volume
    # (Joseph), as the classical volumes' are, in seconds instead of minutes.
    "cpu": {
        "procedure": "refine-classical",
        "hashgrid": {"num_levels": 6, "features_per_level": 2, "log2_hashmap_size": 16, "base_resolution": 16, "per_level_scale": 1.75},
        "attenuation": {"hidden_dim": 32},
        "model": {"num_samples": 64, "num_eval_samples": 64, "eikonal_fraction": 1.0, "quadrature": "bins"},
        "datamanager": {"num_object_rays": 128, "num_air_rays": 32},
        "trainer": {"epochs": 80, "prior_epochs": 40, "lr": 1e-3, "eval_every": 16, "checkpoint_every": 4, "eval_chunk": 256,
                    "eval_views": 3, "eval_projections": "volume"},
    },
    "tiny": {
        "procedure": "paper",
        "hashgrid": {"num_levels": 3, "features_per_level": 2, "log2_hashmap_size": 10, "base_resolution": 4, "per_level_scale": 2.0},
        "attenuation": {"hidden_dim": 64},
        "model": {"num_samples": 16, "num_eval_samples": 16, "eikonal_fraction": 1.0, "quadrature": "bins"},
        "datamanager": {"num_object_rays": 32, "num_air_rays": 8},
        "trainer": {"epochs": 2, "prior_epochs": 1, "lr": 1e-3, "eval_every": 1, "checkpoint_every": 1, "eval_chunk": 1024,
                    "eval_views": 2, "eval_projections": "rendered"},
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


def procedures() -> dict[str, Procedure]:
    """The registered procedures (``kneas.procedures``), by name."""
    out = {}
    for name in registry.names("procedures"):
        proc = registry.load("procedures", name)
        if not isinstance(proc, Procedure):
            raise ConfigError(f"entry point kneas.procedures:{name} is not a kneas_method.stages.Procedure")
        out[name] = proc
    return out


def procedure_of(name: str) -> Procedure:
    """The procedure registered as ``name`` (one-line ConfigError naming the closest when none is)."""
    known = procedures()
    if name not in known:
        raise ConfigError(f"--procedure {name!r} is not a procedure{did_you_mean(name, known)}; choose one of {', '.join(known)}")
    return known[name]


def stage_class(name: str) -> type:
    """The config class of the stage registered as ``name`` (``kneas.stages``)."""
    known = registry.names("stages")
    if name not in known:
        raise ConfigError(f"no stage named {name!r}{did_you_mean(name, known)}; stages: {', '.join(known)}")
    cls = registry.load("stages", name)
    if not (isinstance(cls, type) and issubclass(cls, StageConfig)):
        raise ConfigError(f"entry point kneas.stages:{name} is not a StageConfig subclass")
    return cls


def k_from_data(config: TrainConfig) -> bool:
    """True when K is left for the data to decide: a soft-selector, multi-head surface
    method with ``num_materials`` unset and no explicit ``model.alphas``; K then comes from
    the K rule on the bounds volume (automatic bounds) or from the ``--bounds`` file."""
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


def validate_choices(config: RunConfig) -> RunConfig:
    """Every setting checked against its type (``Literal`` choices included); a one-line
    ConfigError names the first that does not fit."""
    return update_from_dict(config, to_dict(config), where="config")


def stage_names(config: TrainConfig) -> list[str]:
    """The stages a resolved config runs, in their order: the procedure's and ``add_stages``, less the
    skipped and those whose settings are null."""
    proc = procedure_of(config.procedure)
    listed = list(dict.fromkeys(list(proc.stages) + list(config.add_stages)))
    out = []
    for name in listed:
        if name in config.skip_stages:
            continue
        if name in BUILT_IN and getattr(config.stages, BUILT_IN[name]) is None:
            continue
        out.append(name)
    return out


def stage_configs(config: TrainConfig) -> list[StageConfig]:
    """The configs of :func:`stage_names`: a built-in's from ``config.stages``, a plugin's from its
    registered class with ``config.stages.plugins[name]`` applied."""
    out = []
    for name in stage_names(config):
        if name in BUILT_IN:
            out.append(getattr(config.stages, BUILT_IN[name]))
        else:
            cls = stage_class(name)
            out.append(update_from_dict(cls(), dict(config.stages.plugins.get(name, {})), where=f"stages.plugins.{name}"))
    return out


def _select_stages(config: TrainConfig, proc: Procedure, surfaces: bool) -> TrainConfig:
    """``config`` with null settings for every built-in stage it does not run; refuses a skipped or
    added stage that is not one, and a stage without the stages it needs."""
    listed = list(dict.fromkeys(list(proc.stages) + list(config.add_stages)))
    for name in config.add_stages:
        stage_class(name)  # registered?
    for name in config.skip_stages:
        if name not in listed:
            raise ConfigError(f"--skip-stages {name}: procedure {proc.name!r} has no such stage{did_you_mean(name, listed)}; "
                              f"its stages: {', '.join(listed) or 'none'}")
    stages = config.stages
    for name, attr in BUILT_IN.items():
        off = name not in listed or name in config.skip_stages or (name in SURFACES_ONLY and not surfaces)
        if off and getattr(stages, attr) is not None:
            stages = dataclasses.replace(stages, **{attr: None})
    config = dataclasses.replace(config, stages=stages)
    running = stage_names(config)
    orphans = {type(cfg).name: [n for n in type(cfg).needs if n not in running] for cfg in stage_configs(config)}
    orphans = {name: missing for name, missing in orphans.items() if missing}
    if orphans:  # every stage left without what it works on, in one line
        missing = sorted({n for m in orphans.values() for n in m})
        names = list(orphans)
        which = f"stage {names[0]} works" if len(names) == 1 else f"stages {', '.join(names[:-1])} and {names[-1]} work"
        raise ConfigError(f"{which} on the {' and '.join(missing)} stage's result, which this run leaves out; "
                          f"add --skip-stages {' '.join(names)} too, or keep {' '.join(missing)}")
    return config


def resolve(config: RunConfig) -> RunConfig:
    """Return a copy of ``config`` with the preset and the procedure applied, ``config.preset`` and
    ``config.procedure`` made concrete, the stages the run does not run set to None, and every setting
    checked (one line naming the first that does not fit).

    Neural runs (:class:`TrainConfig`) also get ``num_materials`` applied to the model,
    checked against the method. The reason for the preset choice is
    :func:`choose` ``(config.preset)[1]``, computed before resolving.
    """
    name, _ = choose(config.preset)
    config = validate_choices(config)
    if not isinstance(config, TrainConfig):
        check_tree(config)  # its reconstruction's settings, before any scene is loaded or run folder made
        return dataclasses.replace(config, preset=name)
    table = TABLE[name]
    proc = procedure_of(config.procedure or table["procedure"])
    for section, values in proc.settings.items():
        if section not in ("model", "trainer", "run"):
            raise ConfigError(f"procedure {proc.name!r} gives settings of {section!r}; a procedure sets model, trainer and run settings only")
    model = _fill(_fill(config.model, proc.settings.get("model", {})), table["model"])
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
    trainer = _fill(_fill(config.trainer, proc.settings.get("trainer", {})), table["trainer"])
    datamanager = _fill(config.datamanager, table["datamanager"])
    run = {k: getattr(config, k) if getattr(config, k) is not None else v for k, v in proc.settings.get("run", {}).items()}
    if run.get("bounds_k_rule") == "peaks" and config.bounds_method != "gmm" and config.bounds_k_rule is None:
        run["bounds_k_rule"] = "bic-valleys"  # a mixture boundary rule was asked for: the procedure's rule that fits mixtures
    config = dataclasses.replace(config, preset=name, procedure=proc.name, **run, num_materials=K, model=model,
                                 datamanager=datamanager, trainer=trainer)
    if config.bounds_cover_percentile is None:  # a procedure that predates the setting keeps SPEC §4's top bound
        config = dataclasses.replace(config, bounds_cover_percentile=0.0)
    config = _select_stages(config, proc, surfaces)
    check_tree(config)
    for flag, value in (("--trainer.epochs", trainer.epochs), ("--bounds-max-materials", config.bounds_max_materials),
                        ("--bounds-gmm-restarts", config.bounds_gmm_restarts),
                        ("--bounds-upper-percentile", config.bounds_upper_percentile),
                        ("--bounds-upper-factor", config.bounds_upper_factor)):
        if value is None:
            raise ConfigError(f"{flag} is not set, and procedure {proc.name!r} and preset {name!r} leave it unset too; give {flag}")
    if automatic_bounds(config) and config.stages.classical_start is None and trainer.prior_epochs is None:
        raise ConfigError("--trainer.prior-epochs is not set, and the bounds need the NeAS-1M prior; give --trainer.prior-epochs")
    return config


RULE_WORDS = {"bic": "K by BIC", "bic-valleys": "K by the lowest BIC with every boundary a density valley",
              "peaks": "one material per histogram peak (a mixture where there are fewer than two)"}


def describe(config: TrainConfig) -> list[str]:
    """The lines a neural run prints and records about how it is fitted: the procedure, each stage it
    runs in order (the core included), and where its settings leave the paper's."""
    if not isinstance(config, TrainConfig):
        return []
    proc = procedure_of(config.procedure)
    lines = [f"procedure: {proc.name}: {proc.description}"]
    steps = []
    for cfg in stage_configs(config):
        if type(cfg).phase == "start":
            steps.append(cfg.describe())
    if field_has_surfaces(config.model) and automatic_bounds(config):
        source = (f"the {config.stages.classical_start.algorithm.upper()} start" if config.stages.classical_start is not None
                  else f"a NeAS-1M prior ({config.trainer.prior_epochs} epochs)")
        rule = RULE_WORDS[config.bounds_k_rule]
        extra = (f", the best of {config.bounds_gmm_restarts} GMM starts" if config.bounds_gmm_restarts != 1 else "") + \
                (f", components at least {config.bounds_min_std:g} x the 99.5th percentile wide" if config.bounds_min_std else "")
        top = f"the top bound {config.bounds_upper_factor:g} x the {config.bounds_upper_percentile:g}th percentile" + \
              (f" or the {config.bounds_cover_percentile:g}th, whichever is higher" if config.bounds_cover_percentile else "")
        from .engine.bounds_stage import at_noise_k_rule

        noisy = at_noise_k_rule(config)
        if noisy is not None and config.stages.classical_start is not None:
            top += f"; {RULE_WORDS[noisy]} on the start after an edge-preserving filter where it fits the views to their noise"
        steps.append(f"bounds: {rule}, K = 1..{config.bounds_max_materials}{extra}, on the voxel values of {source}; {top}")
    steps += [cfg.describe() for cfg in stage_configs(config) if type(cfg).phase == "before-training"]
    steps.append(f"training: {config.trainer.epochs} epochs")
    steps += [cfg.describe() for cfg in stage_configs(config) if type(cfg).phase == "after-training"]
    lines += [f"  {i + 1}. {line}" for i, line in enumerate(steps)]
    m, t = config.model, config.trainer
    paper = {"s_init": 20.0, "lambda_eikonal": 0.01, "occupancy_grid": False, "lr_decay_at": 0.5}
    differs = [f"{k} {v:g}" if not isinstance(v, bool) else ("the visual hull" if v else "no visual hull")
               for k, v in (("s_init", m.s_init), ("lambda_eikonal", m.lambda_eikonal), ("occupancy_grid", m.occupancy_grid),
                            ("lr_decay_at", t.lr_decay_at)) if v != paper[k]]
    if differs:
        lines.append(f"settings beside the paper's: {', '.join(differs)} (the paper's with --procedure paper)")
    if t.eval_projections == "volume":
        lines.append("evaluation: 2D metrics on the held-out views projected from the volume at the voxel centres (Joseph projector, "
                     "as for the classical methods), not rendered through the field (--trainer.eval-projections rendered for the paper's)")
    if m.quadrature == "voxel-planes":
        lines.append("quadrature: one sample where each ray crosses each voxel-centre plane of its dominant axis (Joseph's rule "
                     "on the scene's voxel grid), not the paper's jittered bins (--model.quadrature bins for the paper's)")
    return lines
