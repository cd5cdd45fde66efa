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
from ..config import to_dict, update_from_dict
from ..errors import ConfigError, KneasError
from ..methods import TrainConfig
from .common import run_cli


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


def load_config_file(path: str) -> dict:
    """A saved run configuration (JSON) as a dict."""
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"config file {path} does not exist; give the config.json of a run folder")
    try:
        data = json.loads(p.read_text())
    except ValueError as exc:
        raise ConfigError(f"config file {path} is not valid JSON ({exc}); fix or regenerate it") from exc
    if not isinstance(data, dict) or not isinstance(data.get("method"), str):
        raise ConfigError(f"config file {path} has no 'method' entry; it must be a kneas run config (config.json)")
    return data


def parse_args(argv: Sequence[str]) -> TrainConfig:
    """Command line -> (unresolved) :class:`TrainConfig`."""
    import tyro

    argv = list(argv)
    resume, argv = _pop_option(argv, "--resume", "outputs/foot/k-neas/<timestamp>")
    config_file, argv = _pop_option(argv, "--config", "path/to/config.json")
    if resume is not None:
        run = Path(resume)
        if not (run / "config.json").is_file():
            raise ConfigError(f"--resume {resume}: no config.json there; give a run folder written by kneas-train "
                              "(DIR/<scene>/<method>/<timestamp>)")
        if config_file is not None:
            raise ConfigError("give either --resume RUN_DIR or --config FILE, not both (a resumed run uses its own config.json)")
        config_file = str(run / "config.json")
    specs = registry.methods()
    defaults = {name: dataclasses.replace(spec.config, method=name) for name, spec in specs.items()}
    descriptions = {name: spec.description for name, spec in specs.items()}
    if config_file is not None:
        data = load_config_file(config_file)
        method = data["method"]
        if method not in defaults:
            raise ConfigError(f"config file {config_file} is for method {method!r}, which is not installed; available: {', '.join(defaults)}")
        defaults[method] = update_from_dict(defaults[method], data)
        if not argv or argv[0].startswith("-") and argv[0] not in ("-h", "--help"):
            argv.insert(0, method)
    sub = tyro.extras.subcommand_type_from_defaults(defaults, descriptions)
    config = tyro.cli(sub, args=argv, prog="kneas-train", description="Train a kneas method (subcommand = registered method).")
    if resume is not None:
        config = dataclasses.replace(config, resume=str(resume))
    return config


def dry_run(config: TrainConfig) -> int:
    """Build the model (no scene data, bounds = placeholders), print the config and ``parameters: N``."""
    print(f"method: {config.method}  scene: {config.scene}  views: {config.views or 'all'}  seed: {config.seed}")
    if config.reconstructor == "fdk":
        print(f"reconstructor: fdk (filter {config.fdk_filter}); no model, no training")
        print("parameters: 0")
        return 0
    model = config.model.setup(scale=1.0)
    m = config.model
    if model.has_sdf:
        k_note = ""
        if presets.k_is_chosen(config):
            k_note = (" (method default; K is read from the bounds file at training time)" if config.bounds else
                      " (method default; K is chosen by BIC at training time, --num-materials K fixes it)")
        print(f"model: field={m.field} encoding={m.encoding} attenuation={m.attenuation} selector={m.selector} K={model.num_materials}{k_note} floater={'on' if m.floater else 'off'} bounds={config.bounds or config.bounds_source}")
    else:
        print(f"model: field={m.field} encoding={m.encoding} (no surfaces)")
    print(f"encoding: {json.dumps(m.encoding_options, separators=(',', ':'))}")
    print(f"samples: {m.num_samples} train / {m.num_eval_samples} eval  rays: {config.datamanager.num_object_rays} object + {config.datamanager.num_air_rays} air  eikonal: {m.eikonal_mode or 'auto'} x{m.eikonal_fraction}")
    t = config.trainer
    print(f"trainer: epochs={t.epochs} prior_epochs={t.prior_epochs} lr={t.lr} decay x{t.lr_decay_factor} at {t.lr_decay_at:.0%}")
    warm = f"fit to the FDK volume for {t.warm_start_steps} steps" if t.warm_start == "fdk" and t.warm_start_steps else "none (train from the initialisation)"
    print(f"warm start: {warm}" + (f"  bounds volume: {config.bounds_volume}" if model.has_sdf and config.bounds_source == "auto" and not config.bounds else ""))
    print(f"parameters: {model.num_parameters():,}")
    return 0


def train(config: TrainConfig) -> int:
    """Train: ``kneas_method.engine.train(config: TrainConfig) -> int | None`` (a function
    exported by ``kneas_method.engine`` or a module ``engine/train.py`` with ``train``), imported lazily."""
    import importlib
    import inspect

    engine = importlib.import_module("kneas_method.engine")
    fn = getattr(engine, "train", None)
    if fn is None:
        try:
            fn = importlib.import_module("kneas_method.engine.train")
        except ModuleNotFoundError as exc:
            if exc.name != "kneas_method.engine.train":
                raise
            raise KneasError("training is not built yet in this version of kneas; use --dry-run to check a configuration") from None
    if inspect.ismodule(fn):
        fn = fn.train
    return fn(config) or 0


def run(config: TrainConfig) -> int:
    _, reason = presets.choose(config.preset)
    config = presets.resolve(config)
    print(reason)
    for note in presets.procedure_notes(config):
        print(note)
    if config.dry_run:
        return dry_run(config)
    return train(config)


def main(argv: Optional[Sequence[str]] = None) -> None:
    """Console entry point ``kneas-train``."""
    run_cli(lambda: run(parse_args(sys.argv[1:] if argv is None else argv)))


__all__ = ["main", "parse_args", "run", "dry_run", "to_dict"]


if __name__ == "__main__":  # pragma: no cover
    main()
