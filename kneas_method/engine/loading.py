"""Load a finished run (or one checkpoint) for evaluation and export.

:func:`load_run` takes a run folder ``DIR/<scene>/<method>/<timestamp>/`` or a
checkpoint file inside it (``checkpoints/step-XXXXXXXX.ckpt``, or a ``.ckpt``
copied anywhere next to the run's ``config.json``) and rebuilds what was
trained:

* ``config.json`` -> the method's :class:`~kneas_method.methods.TrainConfig`
  (``update_from_dict`` on the registered method's defaults);
* the scene (``config.scene``, with ``config.views`` training views) or the one
  passed in;
* the model, built on the scene's scale, with the checkpoint's weights loaded
  through ``map_location="cpu"`` (so a run trained on a GPU opens on a machine
  without one), then moved to ``device``; or, for FDK runs, ``volume.npy``.

A hash grid trained with tiny-cuda-nn stores its table as
``...encoding.encoding.params``; loading it into the torch hash grid (any
machine without CUDA) converts it to ``...encoding.table``, and back.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional, Union

import numpy as np
import torch

from ..device import resolve_device
from ..errors import CheckpointError, KneasError, SceneError

RESUME_HINT = "training must finish, or be resumed with `kneas-train --resume {run}`"
RETRAIN_HINT = "the run finished (metrics.json) but its files are gone or damaged, so it cannot be resumed; train it again with `kneas-train --config {run}/config.json`"


def missing_hint(run_dir: Path) -> str:
    """What to do about a run folder whose volume or checkpoints are missing or damaged: resume an
    unfinished run; train a finished one again from its config (a finished run is not resumed)."""
    return (RETRAIN_HINT if (Path(run_dir) / "metrics.json").is_file() else RESUME_HINT).format(run=run_dir)

# settings that ``--resume`` may change: they do not change what is trained
RESUME_SAFE = ("device", "resume", "dry_run", "trainer.eval_chunk")


def config_from_dict(data: Any, where: str):
    """A run config from the dict of a ``config.json`` (``where`` names the file in errors):
    the registered method's defaults with the file's values applied and checked."""
    from .. import registry
    from ..config import update_from_dict

    if not isinstance(data, dict) or not isinstance(data.get("method"), str):
        raise KneasError(f"{where} has no 'method' entry; it is not a kneas run config (config.json)")
    from .legacy_config import upgrade

    data = upgrade(data, _attenuation_has_width)
    method = data["method"]
    specs = registry.methods()
    if method not in specs:
        raise KneasError(f"{where} is a run of method {method!r}, which is not installed here; installed: {', '.join(specs)}")
    base = dataclasses.replace(specs[method].config, method=method)
    data = _drop_other_kind(base, data)
    return stages_as_skipped(update_from_dict(base, data, where=where))


def stages_as_skipped(config):
    """A config whose procedure's stages are null (a resolved config.json's stages the run did not run)
    with those stages' default settings and their names in ``skip_stages`` instead: the same run, and
    the command line's ``--stages.<stage>.*`` flags exist for every stage."""
    from ..methods import TrainConfig
    from ..presets import procedures
    from ..stages import BUILT_IN

    if not isinstance(config, TrainConfig) or config.procedure not in procedures():
        return config
    listed = procedures()[config.procedure].stages
    defaults = type(config.stages)()
    off = [name for name in listed if name in BUILT_IN and getattr(config.stages, BUILT_IN[name]) is None]
    if not off:
        return config
    stages = dataclasses.replace(config.stages, **{BUILT_IN[n]: getattr(defaults, BUILT_IN[n]) for n in off})
    return dataclasses.replace(config, stages=stages, skip_stages=tuple(dict.fromkeys(tuple(config.skip_stages) + tuple(off))))


def _attenuation_has_width(method: str, model: dict) -> bool:
    """True when the attenuation network a config.json's ``model`` names has a ``hidden_dim``."""
    from .. import registry
    from ..model import build_component, field_has_surfaces

    specs = registry.methods()
    if method not in specs:
        return False
    try:
        base = specs[method].config.model
        surfaces = field_has_surfaces(dataclasses.replace(base, field=model.get("field", base.field),
                                                          field_options=model.get("field_options", base.field_options)))
        name = model.get("attenuation", base.attenuation)
        return surfaces and "hidden_dim" in {f.name for f in dataclasses.fields(build_component("attenuations", name))}
    except (KneasError, AttributeError, TypeError):  # not installed or not a surface model: nothing to keep
        return False


def _drop_other_kind(base, data: dict) -> dict:
    """Older kneas wrote FDK runs with the neural settings too; a classical config ignores them."""
    from ..methods import TrainConfig

    if isinstance(base, TrainConfig):
        return data
    own = {f.name for f in dataclasses.fields(base)}
    neural = {f.name for f in dataclasses.fields(TrainConfig)} - own
    return {k: v for k, v in data.items() if k not in neural}


def _unique_keys(pairs: list) -> dict:
    """A JSON object's pairs -> dict, refusing a key given twice (``json`` would keep the last silently)."""
    out = {}
    for key, value in pairs:
        if key in out:
            raise ValueError(f"the setting {key!r} is given twice in one object; keep one of them")
        out[key] = value
    return out


def read_config_file(path: Union[str, Path]):
    """A run config from a JSON file (``kneas-train --config FILE``)."""
    path = Path(path)
    if not path.is_file():
        raise KneasError(f"config file {path} does not exist; give the config.json of a run folder")
    try:
        data = json.loads(path.read_text(encoding="utf-8"), object_pairs_hook=_unique_keys)
    except (OSError, ValueError) as exc:
        raise KneasError(f"config file {path} is not valid JSON ({exc}); fix or regenerate it") from None
    return config_from_dict(data, str(path))


def read_run_config(run_dir: Path):
    """The run's config from ``RUN_DIR/config.json`` (KneasError when missing or foreign)."""
    path = Path(run_dir) / "config.json"
    if not path.is_file():
        raise KneasError(f"{run_dir} has no config.json, so it is not a kneas run folder; give the folder kneas-train "
                         "wrote (DIR/<scene>/<method>/<timestamp>: it says 'run folder: ...' when it starts)")
    try:
        data = json.loads(path.read_text(encoding="utf-8"), object_pairs_hook=_unique_keys)
    except (OSError, ValueError) as exc:
        raise KneasError(f"{path} is not valid JSON ({exc}); the run folder is damaged, train the run again") from None
    return config_from_dict(data, str(path))


def resume_config(run_dir: Union[str, Path], given=None):
    """The config a ``--resume RUN_DIR`` run continues with: the run's own ``config.json``,
    plus the settings given on the command line that do not change what is trained
    (``RESUME_SAFE``). ``given`` is the command line parsed on top of the saved config.

    Raises:
        KneasError: one line naming every other changed setting, and how to start a new
        run with it instead.
    """
    from ..config import to_dict

    run_dir = Path(run_dir)
    saved = read_run_config(run_dir)
    if given is None:
        return dataclasses.replace(saved, resume=str(run_dir))
    changed = [k for k, (a, b) in _flat_diff(to_dict(saved), to_dict(given)).items() if k not in RESUME_SAFE]
    if changed:
        diff = _flat_diff(to_dict(saved), to_dict(given))
        what = ", ".join(f"{k} ({diff[k][0]!r} -> {diff[k][1]!r})" for k in changed)
        flags = " ".join(f"--{k.replace('_', '-')} {_flag_value(diff[k][1])}" for k in changed)
        raise KneasError(f"--resume continues {run_dir} with its own settings, but the command line changes {what}; "
                         f"start a new run with them instead: kneas-train --config {run_dir / 'config.json'} {flags}")
    return dataclasses.replace(given, resume=str(run_dir))


def _flag_value(value) -> str:
    if isinstance(value, (list, tuple)):
        return " ".join(str(v) for v in value)
    return str(value)


def _flat_diff(a: dict, b: dict, prefix: str = "") -> dict[str, tuple]:
    """``{"trainer.epochs": (2, 3), ...}``: leaves of two nested dicts that differ."""
    out: dict[str, tuple] = {}
    for key in sorted(set(a) | set(b)):
        va, vb = a.get(key), b.get(key)
        name = f"{prefix}{key}"
        if isinstance(va, dict) and isinstance(vb, dict) and key not in ("field_options", "encoding_options",
                                                                          "attenuation_options", "selector_options"):
            out.update(_flat_diff(va, vb, name + "."))
        elif va != vb:
            out[name] = (va, vb)
    return out


HOLDOUT_FRACTION, HOLDOUT_AT_MOST = 0.1, 10  # training views held out of a scene that has none


def holdout_views(scene, fraction: float = HOLDOUT_FRACTION, at_most: int = HOLDOUT_AT_MOST):
    """A scene with no held-out views (real scans): ``fraction`` of its training views (at least 1,
    at most ``at_most``), evenly spread over the scan, are held out for the 2D metrics and the
    rest kept for training. Deterministic; recorded in ``scene.meta["holdout"]``."""
    n = len(scene.train)
    if n < 2:
        raise KneasError(f"scene {scene.name!r} has {n} projection(s) and no held-out views; at least 2 projections are needed")
    k = max(1, min(at_most, int(round(fraction * n))))
    held = np.unique(np.round(np.linspace(0, n - 1, k + 2)[1:-1]).astype(int))
    keep = np.setdiff1d(np.arange(n), held)
    meta = {**scene.meta, "holdout": {"held_out_training_views": [int(i) for i in held], "of": n,
                                      "note": "the scene has no held-out views: these training views were held out for the 2D metrics"}}
    return dataclasses.replace(scene, train=scene.train.subset(keep), val=scene.train.subset(held), meta=meta)


def load_scene(config, scene=None, *, say: Optional[Callable[[str], None]] = None):
    """The scene a run trains or is evaluated on.

    ``scene=None``: the run's own (``config.scene`` through ``resolve_scene`` with
    ``config.data_dir``, then ``config.views`` training views); a name, a path or a
    :class:`Scene`: that scene, as given. A scene without held-out views gets some of
    its training views held out (:func:`holdout_views`). ``say`` receives progress lines.
    """
    from ..data.scene import Scene
    from ..data.scenes import resolve_scene

    note = (lambda msg: say(f"  {msg}")) if say is not None else None
    if isinstance(scene, Scene):
        sc = scene
    elif scene is not None:
        sc = resolve_scene(str(scene), data_dir=config.data_dir, progress=note)
    else:
        sc = resolve_scene(config.scene, data_dir=config.data_dir, progress=note)
        full = len(sc.train)
        sc = sc.subsample_views(config.views)
        if say is not None:
            say(f"scene: {sc.name} from {sc.source}; {len(sc.train)} of {full} training views, {len(sc.val)} held-out views, "
                f"volume {tuple(sc.geometry.n_voxel)}, detector {tuple(sc.geometry.n_detector)}")
    if len(sc.val) == 0:
        sc = holdout_views(sc)
        if say is not None:
            say(f"scene: no held-out views; {len(sc.val)} of the training views are held out for the 2D metrics")
    return sc


@dataclass
class LoadedRun:
    """A run rebuilt from disk.

    Attributes:
        config: the run's resolved TrainConfig.
        model: the trained ``CTModel`` in eval mode on the requested device, or
            None for FDK runs.
        volume: ``[nx, ny, nz]`` float32 attenuation in data units (FDK runs), or None.
        scene: the scene it is evaluated on (training scene unless another was given).
        run_dir: the run folder.
        checkpoint_path: the checkpoint loaded (None for FDK runs).
        step: the checkpoint's training step (None for FDK runs).
        notes: one-line remarks for the user (skipped damaged checkpoints, ...).
        fitted: a classical run's ``(geometry, volume)`` on the longer box its views were fitted on
            (``volume_fitted_box.npy``, ``data.truncation.FittingBox``), or None.
    """

    config: Any
    model: Optional[torch.nn.Module]
    volume: Optional[np.ndarray]
    scene: Any
    run_dir: Path
    checkpoint_path: Optional[Path]
    step: Optional[int] = None
    notes: list[str] = field(default_factory=list)
    fitted: Optional[tuple] = None

    @property
    def method(self) -> str:
        return self.config.method

    @property
    def has_surfaces(self) -> bool:
        """True when the run's model has signed distance fields (materials, meshes from SDFs)."""
        return self.model is not None and self.model.has_surfaces


def _run_dir_of(path: Path) -> tuple[Path, Optional[Path]]:
    """``(run_dir, checkpoint file or None)`` for a run folder or a checkpoint path."""
    if path.is_dir():
        return path, None
    if path.is_file():
        parent = path.parent
        run = parent.parent if parent.name == "checkpoints" and not (parent / "config.json").is_file() else parent
        if path.suffix != ".ckpt" and not (run / "config.json").is_file():
            raise KneasError(f"{path} is a file, not a run folder or a checkpoint (.ckpt); give the folder kneas-train "
                             "wrote (DIR/<scene>/<method>/<timestamp>) or a checkpoint in it")
        return run, path
    raise KneasError(f"{path} does not exist; give a run folder (DIR/<scene>/<method>/<timestamp>) or a checkpoint file")


def _check_same_box(config, scene, notes: list[str]) -> None:
    """A model's coordinates are the training scene's model units: another scene must share its volume box."""
    from ..data.scenes import resolve_scene

    try:
        train_scene = resolve_scene(config.scene, data_dir=config.data_dir)
    except KneasError:
        notes.append(f"training scene {config.scene!r} is not available here; assuming {scene.name!r} has the same volume box")
        return
    a, b = train_scene.geometry, scene.geometry
    if not (np.allclose(a.scale, b.scale, rtol=1e-6) and np.allclose(a.off_origin, b.off_origin, atol=1e-9)):
        box = lambda g: tuple(round(n * d * g.mm_per_unit, 3) for n, d in zip(g.n_voxel, g.d_voxel))  # noqa: E731
        raise KneasError(
            f"scene {scene.name!r} has a {box(b)} mm volume box but the model was trained on {config.scene!r} with {box(a)} mm "
            "(or another origin); its coordinates would not line up; evaluate on a scene with the same volume box"
        )


def convert_hash_tables(state: dict, model: torch.nn.Module) -> dict:
    """Rename hash-grid tables between the tiny-cuda-nn (``encoding.encoding.params``)
    and torch (``encoding.table [n_entries, F]``) layouts to fit ``model``."""
    want = model.state_dict()
    state = dict(state)
    for key, value in list(state.items()):
        if key.endswith("encoding.encoding.params"):
            target = key[: -len("encoding.params")] + "table"
            if target in want and key not in want:
                state[target] = value.reshape(want[target].shape).to(want[target].dtype)
                del state[key]
        elif key.endswith("encoding.table"):
            target = key[: -len("table")] + "encoding.params"
            if target in want and key not in want:
                state[target] = value.reshape(-1).to(want[target].dtype)
                del state[key]
    return state


def _cpu_encoding(config, device: torch.device):
    """On a machine without CUDA, a hash grid pinned to tinycudann falls back to torch."""
    opts = config.model.encoding_options
    if device.type != "cuda" and isinstance(opts, dict) and opts.get("implementation") == "tcnn":
        model = dataclasses.replace(config.model, encoding_options={**opts, "implementation": "torch"})
        return dataclasses.replace(config, model=model), True
    return config, False


def _fitted_volume(run_dir: Path, scene) -> Optional[tuple]:
    """A classical run's reconstruction on the longer box its views were fitted on, with that box's
    geometry, where the run wrote one that fits ``scene``'s (``classical_pipeline.FITTED_VOLUME``); else None."""
    from ..data.truncation import fitting_scene
    from .classical_pipeline import FITTED_VOLUME

    path = Path(run_dir) / FITTED_VOLUME
    if not path.is_file():
        return None
    box = fitting_scene(scene)
    try:
        volume = np.load(path, allow_pickle=False).astype(np.float32, copy=False)
    except (OSError, ValueError):
        return None
    return (box.scene.geometry, volume) if box.slices and tuple(volume.shape) == tuple(box.scene.geometry.n_voxel) else None


def load_run(
    run_dir_or_checkpoint: Union[str, Path],
    *,
    scene=None,
    device: Union[str, torch.device] = "cpu",
) -> LoadedRun:
    """Rebuild a trained run for evaluation/export.

    Args:
        run_dir_or_checkpoint: a run folder, or a ``.ckpt`` file (its run folder
            is the folder holding ``config.json``: the checkpoint's folder, or the
            parent of ``checkpoints/``).
        scene: evaluate on this scene (a :class:`Scene`, a built-in name or a
            NAF pickle path) instead of the training scene; its volume box must
            match the training scene's.
        device: torch device for the model (``cpu`` by default; weights are always
            read with ``map_location="cpu"`` first).

    Returns:
        :class:`LoadedRun`.

    Raises:
        KneasError: a missing piece (config.json, checkpoint, volume.npy), named,
            with the fix (finish training or resume it with ``kneas-train --resume``).
    """
    from ..engine.checkpoint import list_checkpoints, load_checkpoint_file, load_latest_checkpoint

    device = resolve_device(str(device))
    path = Path(run_dir_or_checkpoint).expanduser()
    run_dir, ckpt_file = _run_dir_of(path)
    notes: list[str] = []
    config = dataclasses.replace(read_run_config(run_dir), resume=str(run_dir))
    try:
        sc = load_scene(config, scene)
    except SceneError as exc:
        if scene is not None:
            raise
        raise KneasError(f"the run's training scene cannot be opened here ({exc}); pass the scene with --scene") from None
    if scene is not None:
        _check_same_box(config, sc, notes)

    from ..methods import TrainConfig

    if not isinstance(config, TrainConfig):  # a classical run: its volume
        vol_path = run_dir / "volume.npy"
        if not vol_path.is_file():
            raise KneasError(f"{config.method} run {run_dir} has no volume.npy; " + missing_hint(run_dir))
        try:
            volume = np.load(vol_path, allow_pickle=False).astype(np.float32, copy=False)
        except (OSError, ValueError) as exc:
            raise KneasError(f"{vol_path} cannot be read ({exc}); run the {config.method} reconstruction again") from None
        if tuple(volume.shape) != tuple(sc.geometry.n_voxel):
            raise KneasError(f"{vol_path} has shape {volume.shape} but scene {sc.name!r} has {tuple(sc.geometry.n_voxel)} voxels; pass the scene it was reconstructed on")
        return LoadedRun(config, None, volume, sc, run_dir, None, None, notes, fitted=_fitted_volume(run_dir, sc))

    if ckpt_file is not None:
        state = load_checkpoint_file(ckpt_file, method=config.method, map_location="cpu")
        ckpt_path = ckpt_file
    else:
        folder = run_dir / "checkpoints"
        if not list_checkpoints(folder):
            raise KneasError(f"{run_dir} has no checkpoint in checkpoints/; " + missing_hint(run_dir))
        try:
            state, ckpt_path, skipped = load_latest_checkpoint(folder, method=config.method, map_location="cpu")
        except CheckpointError as exc:
            if "no complete checkpoint" in str(exc):
                raise KneasError(f"{run_dir} has only damaged checkpoints; " + missing_hint(run_dir)) from None
            raise
        notes += [f"skipped {s}" for s in skipped]

    from ..model import CTModel

    config, switched = _cpu_encoding(config, device)
    if switched:
        notes.append("the run used the tinycudann hash grid; loaded into the torch hash grid (no CUDA here)")
    model = CTModel(config.model, scale=sc.geometry.scale, device=device)
    weights = convert_hash_tables(state["model"], model)
    try:
        model.load_state_dict(weights)
    except RuntimeError as exc:
        first = str(exc).strip().splitlines()[0]
        raise CheckpointError(f"checkpoint {ckpt_path} does not fit the model described by {run_dir / 'config.json'} ({first[:200]}); "
                              "the run folder mixes files of different runs") from None
    model.to(device).eval()
    step = state.get("step")
    notes += unfinished_notes(state, config, run_dir)
    return LoadedRun(config, model, None, sc, run_dir, Path(ckpt_path), int(step) if step is not None else None, notes)


def unfinished_notes(state: dict, config, run_dir: Path) -> list[str]:
    """What a checkpoint lacks of a finished run (``state["extra"]``): a model stopped part-way
    through training, or one trained without the correction passes its config asks for."""
    extra = state.get("extra") or {}
    if not extra:  # a checkpoint written outside kneas-train: nothing to say
        return []
    step, total = state.get("step"), extra.get("total_steps")
    if extra.get("stage") == "prior":
        return [f"this checkpoint is the bounds' prior model (step {step}), not the run's own; finish the run with "
                f"kneas-train --resume {run_dir}"]
    if extra.get("complete") is False:
        return [f"training stopped at step {step} of {total}: these figures are an unfinished model's; finish it with "
                f"kneas-train --resume {run_dir}"]
    from ..model import field_has_surfaces
    from .trainer import stage_records

    correction = getattr(getattr(config, "stages", None), "correction", None)
    skipped = "correction" in getattr(config, "skip_stages", ())
    if correction is not None and not skipped and "correction" not in stage_records(extra) and field_has_surfaces(config.model):
        return [f"the {correction.passes} correction passes after training were not run (the run stopped before them); "
                f"finish it with kneas-train --resume {run_dir}"]
    return []
