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
from typing import Any, Optional, Union

import numpy as np
import torch

from ..errors import CheckpointError, KneasError, SceneError

RESUME_HINT = "training must finish, or be resumed with `kneas-train --resume {run}`"


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
    """

    config: Any
    model: Optional[torch.nn.Module]
    volume: Optional[np.ndarray]
    scene: Any
    run_dir: Path
    checkpoint_path: Optional[Path]
    step: Optional[int] = None
    notes: list[str] = field(default_factory=list)

    @property
    def method(self) -> str:
        return self.config.method


def _run_dir_of(path: Path) -> tuple[Path, Optional[Path]]:
    """``(run_dir, checkpoint file or None)`` for a run folder or a checkpoint path."""
    if path.is_dir():
        return path, None
    if path.is_file():
        parent = path.parent
        run = parent.parent if parent.name == "checkpoints" and not (parent / "config.json").is_file() else parent
        return run, path
    raise KneasError(f"{path} does not exist; give a run folder (DIR/<scene>/<method>/<timestamp>) or a checkpoint file")


def read_run_config(run_dir: Path):
    """The run's TrainConfig from ``config.json`` (KneasError when missing or foreign)."""
    from .. import registry
    from ..config import update_from_dict

    path = run_dir / "config.json"
    if not path.is_file():
        raise KneasError(
            f"{run_dir} has no config.json, so it is not a complete kneas run folder; "
            + RESUME_HINT.format(run=run_dir)
        )
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise KneasError(f"{path} is not valid JSON ({exc}); the run folder is damaged, train the run again") from None
    if not isinstance(data, dict) or not isinstance(data.get("method"), str):
        raise KneasError(f"{path} has no 'method' entry; it is not a kneas run config")
    method = data["method"]
    specs = registry.methods()
    if method in specs:
        base = dataclasses.replace(specs[method].config, method=method)
    elif method == "fdk":  # an FDK run read by a kneas without the fdk method entry point
        from ..methods import TrainConfig

        base = TrainConfig(method="fdk")
        known = {f.name for f in dataclasses.fields(TrainConfig)}
        data = {k: v for k, v in data.items() if k in known}
    else:
        raise KneasError(f"{path} is a run of method {method!r}, which is not installed here; installed: {', '.join(specs)}")
    return update_from_dict(base, data, where="config.json")


def _resolve_scene(config, scene, run_dir: Path, notes: list[str]):
    from ..data.scene import Scene
    from ..data.scenes import resolve_scene

    if isinstance(scene, Scene):
        return scene
    if scene is not None:
        return resolve_scene(str(scene))
    try:
        sc = resolve_scene(config.scene)
    except SceneError as exc:
        raise KneasError(f"the run's training scene cannot be opened here ({exc}); pass the scene with --scene") from None
    return sc.subsample_views(config.views)


def _check_same_box(config, scene, notes: list[str]) -> None:
    """A model's coordinates are the training scene's model units: another scene must share its volume box."""
    from ..data.scenes import resolve_scene

    try:
        train_scene = resolve_scene(config.scene)
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

    device = torch.device(device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise KneasError(f"device {device} asked for but no CUDA GPU is available; use --device cpu")
    path = Path(run_dir_or_checkpoint).expanduser()
    run_dir, ckpt_file = _run_dir_of(path)
    notes: list[str] = []
    config = read_run_config(run_dir)
    sc = _resolve_scene(config, scene, run_dir, notes)
    if scene is not None:
        _check_same_box(config, sc, notes)

    if config.method == "fdk" or getattr(config, "reconstructor", "neural") == "fdk":
        vol_path = run_dir / "volume.npy"
        if not vol_path.is_file():
            raise KneasError(f"FDK run {run_dir} has no volume.npy; " + RESUME_HINT.format(run=run_dir))
        try:
            volume = np.load(vol_path, allow_pickle=False).astype(np.float32, copy=False)
        except (OSError, ValueError) as exc:
            raise KneasError(f"{vol_path} cannot be read ({exc}); run the FDK reconstruction again") from None
        if tuple(volume.shape) != tuple(sc.geometry.n_voxel):
            raise KneasError(f"{vol_path} has shape {volume.shape} but scene {sc.name!r} has {tuple(sc.geometry.n_voxel)} voxels; pass the scene it was reconstructed on")
        return LoadedRun(config, None, volume, sc, run_dir, None, None, notes)

    if ckpt_file is not None:
        state = load_checkpoint_file(ckpt_file, method=config.method, map_location="cpu")
        ckpt_path = ckpt_file
    else:
        folder = run_dir / "checkpoints"
        if not list_checkpoints(folder):
            raise KneasError(f"{run_dir} has no checkpoint in checkpoints/; " + RESUME_HINT.format(run=run_dir))
        try:
            state, ckpt_path, skipped = load_latest_checkpoint(folder, method=config.method, map_location="cpu")
        except CheckpointError as exc:
            if "no complete checkpoint" in str(exc):
                raise KneasError(f"{run_dir} has only damaged checkpoints; " + RESUME_HINT.format(run=run_dir)) from None
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
    return LoadedRun(config, model, None, sc, run_dir, Path(ckpt_path), int(step) if step is not None else None, notes)
