"""`kneas-train METHOD [options]`: train a registered method (or --dry-run it).

Subcommands come from the ``kneas.methods`` registry, so a plugin's method
appears here without any change to kneas. ``--config FILE`` starts from a saved
run configuration (``config.json`` of a run folder); further options override it.

Examples::

    kneas-train k-neas --scene foot
    kneas-train neas-1m --dry-run --preset paper
    kneas-train k-neas --num-materials 4 --dry-run --preset paper
    kneas-train --config outputs/foot/k-neas/<timestamp>/config.json
    kneas-train --resume outputs/foot/k-neas/<timestamp>
"""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path
from typing import Optional, Sequence

from .. import presets, registry
from ..config import to_dict
from ..data.scenes import check_scene_spec
from ..engine.loading import read_config_file, read_run_config, resume_config
from ..engine.pipeline import train
from ..errors import ConfigError
from ..methods import TrainConfig
from .common import run_cli, tyro_cli


def _pop_option(argv: list[str], name: str, example: str) -> tuple[Optional[str], list[str]]:
    """``name VALUE`` or ``name=VALUE`` taken out of ``argv`` -> (VALUE or None, the other arguments)."""
    out, value, i = [], None, 0
    while i < len(argv):
        a = argv[i]
        if a == name:
            if i + 1 >= len(argv):
                raise ConfigError(f"{name} needs a value: {name} {example}")
            value = argv[i + 1]
            i += 2
            continue
        if a.startswith(name + "="):
            value = a.split("=", 1)[1]
        else:
            out.append(a)
        i += 1
    return value, out


def parse_args(argv: Sequence[str]):
    """Command line -> the (unresolved) run config of the chosen method.

    ``--config FILE`` starts from a saved config; ``--resume RUN_DIR`` from the run's own
    ``config.json``, and only settings that do not change what is trained may be given
    with it (``loading.resume_config`` refuses the others in one line)."""
    argv = list(argv)
    resume, argv = _pop_option(argv, "--resume", "outputs/foot/k-neas/<timestamp>")
    config_file, argv = _pop_option(argv, "--config", "path/to/config.json")
    if resume is not None:
        if not (Path(resume) / "config.json").is_file():
            raise ConfigError(f"--resume {resume}: no config.json there; give a run folder written by kneas-train "
                              "(DIR/<scene>/<method>/<timestamp>)")
        if config_file is not None:
            raise ConfigError("give either --resume RUN_DIR or --config FILE, not both (a resumed run uses its own config.json)")
        start = read_run_config(Path(resume))
    elif config_file is not None:
        start = read_config_file(config_file)
    else:
        start = None
    if any(token == "--method" or token.startswith("--method=") for token in argv):
        raise ConfigError("the method is the subcommand (kneas-train METHOD [options]); drop --method")
    specs = registry.methods()
    defaults = {name: dataclasses.replace(spec.config, method=name) for name, spec in specs.items()}
    descriptions = {name: spec.description for name, spec in specs.items()}
    if start is not None:
        defaults[start.method] = start
        if not argv or argv[0].startswith("-") and argv[0] not in ("-h", "--help"):
            argv.insert(0, start.method)
        elif resume is not None and argv[0] in defaults and argv[0] != start.method:
            raise ConfigError(f"--resume {resume} is a {start.method} run; drop the method name {argv[0]!r}")
        elif argv[0] in defaults and argv[0] != start.method:
            raise ConfigError(f"--config {config_file} holds {start.method} settings, and they would not apply to {argv[0]}; "
                              f"drop the method name {argv[0]!r} (or give {start.method}), or drop --config to train "
                              f"{argv[0]} with its defaults and --scene/--views/--seed of your choice")
    config = tyro_cli(defaults, descriptions, argv, prog="kneas-train", what="method",
                      description="Train a kneas method (subcommand = registered method). Two more forms: "
                                  "kneas-train --config FILE [options] starts from a saved config.json (a run's, "
                                  "or your own; its method is the run's); kneas-train --resume RUN_DIR continues an interrupted run.")
    if resume is not None:
        config = resume_config(resume, config)
    return config


def dry_run(config) -> int:
    """Build the model (no scene data, bounds = placeholders), print the config and ``parameters: N``."""
    print(f"method: {config.method}  scene: {config.scene}  views: {config.views or 'all'}  seed: {config.seed}")
    if not isinstance(config, TrainConfig):
        print(f"classical reconstruction: {config.algorithm} ({json.dumps(to_dict(config.reconstruction), separators=(',', ':'))}); "
              "no model, no training")
        print("parameters: 0")
        return 0
    model = config.model.setup(scale=1.0)
    m = config.model
    if model.has_surfaces:
        k_note = ""
        if presets.k_from_data(config):
            k_note = (" (method default; K is read from the bounds file at training time)" if config.bounds else
                      " (method default; K is chosen from the bounds volume at training time, --num-materials K fixes it)")
        print(f"model: field={m.field} encoding={m.encoding} attenuation={m.attenuation} selector={m.selector} K={model.num_materials}{k_note} floater={'on' if m.floater else 'off'} bounds={config.bounds or config.bounds_source}")
    else:
        print(f"model: field={m.field} encoding={m.encoding} (no surfaces)")
    print(f"encoding: {json.dumps(m.encoding_options, separators=(',', ':'))}")
    print(f"samples: {m.num_samples} train / {m.num_eval_samples} eval  rays: {config.datamanager.num_object_rays} object + {config.datamanager.num_air_rays} air  eikonal: {m.eikonal_mode or 'auto'} x{m.eikonal_fraction}")
    t = config.trainer
    print(f"trainer: epochs={t.epochs} prior_epochs={t.prior_epochs} lr={t.lr} decay x{t.lr_decay_factor} at {t.lr_decay_at:.0%}")
    print(f"stages: {', '.join(presets.stage_names(config)) or 'none beside the bounds and training'}")
    print(f"parameters: {model.num_parameters():,}")
    if model.has_surfaces and presets.k_from_data(config):
        extra = dataclasses.replace(m, num_materials=model.num_materials + 1).setup(scale=1.0).num_parameters() - model.num_parameters()
        print(f"parameters per further material: {extra:+,} (the count above is at K = {model.num_materials}; "
              "training takes K from the bounds)")
    return 0


def _unused_stage_settings(given, resolved) -> list[str]:
    """Stages whose settings ``given`` changes from their defaults but that ``resolved`` does not run."""
    from ..stages import BUILT_IN

    if not isinstance(given, TrainConfig):
        return []
    defaults = type(given.stages)()
    return [name for name, attr in BUILT_IN.items()
            if getattr(given.stages, attr) not in (None, getattr(defaults, attr)) and getattr(resolved.stages, attr) is None]


def run(config) -> int:
    _, reason = presets.choose(config.preset)
    given, config = config, presets.resolve(config)
    if not config.dry_run:
        check_scene_spec(config.scene)  # a wrong --scene is the whole answer, before the preset's notes
    print(reason)
    for line in presets.describe(config):
        print(line)
    for name in _unused_stage_settings(given, config):
        print(f"note: --stages.{name}.* settings are given, but this run does not run the {name} stage "
              f"(--add-stages {name} runs it)")
    if config.dry_run:
        return dry_run(config)
    return train(config)


def main(argv: Optional[Sequence[str]] = None) -> None:
    """Console entry point ``kneas-train``."""
    run_cli(lambda: run(parse_args(sys.argv[1:] if argv is None else argv)))


__all__ = ["main", "parse_args", "run", "dry_run", "to_dict"]


if __name__ == "__main__":  # pragma: no cover
    main()
