"""Checkpoints: written atomically, loaded weights-only, never half-read.

A checkpoint is a plain dict of tensors, numbers and strings (so that
``torch.load(weights_only=True)`` reads it and a pickle payload is refused):

    {"format": CHECKPOINT_FORMAT, "kneas_version": str, "method": str,
     "step": int, "epoch": int, "model": state_dict, "optimizer": state_dict,
     "scheduler": state_dict, "datamanager": sampler state, "rng": {...}, "extra": {...}}

Files are named ``step-<step:08d>.ckpt`` in the run's ``checkpoints/`` folder.
Writing goes to a temporary file in the same folder, is flushed and fsynced,
then renamed over the final name, so a crash at any moment leaves either the
old set of files or the new complete one. Loading tries the newest file first
and falls back to older ones when a file is damaged.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import torch

from .. import __version__
from ..atomic import atomic_write
from ..errors import CheckpointError

CHECKPOINT_FORMAT = 1
_NAME = re.compile(r"^step-(\d{8})\.ckpt$")


def checkpoint_path(folder: str | Path, step: int) -> Path:
    return Path(folder) / f"step-{step:08d}.ckpt"


def list_checkpoints(folder: str | Path) -> list[Path]:
    """Complete-looking checkpoint files in ``folder``, oldest first."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    found = [(int(m.group(1)), p) for p in folder.iterdir() if (m := _NAME.match(p.name))]
    return [p for _, p in sorted(found)]


def atomic_torch_save(obj: Any, path: str | Path) -> Path:
    """``torch.save`` to ``path`` atomically (temp file, fsync, rename)."""
    return atomic_write(path, lambda handle: torch.save(obj, handle))


def save_checkpoint(folder: str | Path, state: dict, *, keep: int = 2) -> Path:
    """Write ``state`` (must contain ``step`` and ``method``) into ``folder`` (made on the first
    checkpoint, so runs without one, the classical methods', have no empty ``checkpoints/``) and
    prune to the newest ``keep``."""
    Path(folder).mkdir(parents=True, exist_ok=True)
    state = {"format": CHECKPOINT_FORMAT, "kneas_version": __version__, **state}
    path = atomic_torch_save(state, checkpoint_path(folder, int(state["step"])))
    for old in list_checkpoints(folder)[:-keep]:
        try:
            old.unlink()
        except OSError:
            pass
    return path


def load_checkpoint_file(path: str | Path, *, method: str | None = None, map_location="cpu") -> dict:
    """Load one checkpoint weights-only and check it belongs to ``method``.

    Raises:
        CheckpointError: missing, damaged, not a kneas checkpoint, a pickle
        payload (refused by weights-only loading), another method, or an
        incompatible format version.
    """
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} does not exist; pass a run folder or a .ckpt file written by kneas-train")
    try:
        state = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:  # damaged zip, or an unsafe pickle refused by weights_only
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        reason = first.split(". ")[0].rstrip(".")  # its first sentence, whole
        reason = reason if len(reason) <= 160 else reason[:157] + "..."
        raise CheckpointError(f"checkpoint {path} cannot be loaded safely ({reason}); it is damaged or not a kneas checkpoint") from None
    if not isinstance(state, dict) or "format" not in state or "model" not in state:
        raise CheckpointError(f"{path} is not a kneas checkpoint (no format/model entries)")
    if state["format"] != CHECKPOINT_FORMAT:
        raise CheckpointError(
            f"checkpoint {path} has format {state['format']} (kneas {state.get('kneas_version', '?')}), "
            f"but this kneas {__version__} reads format {CHECKPOINT_FORMAT}; retrain or use the matching kneas version"
        )
    if method is not None and state.get("method") != method:
        raise CheckpointError(f"checkpoint {path} was written by method {state.get('method')!r}, not {method!r}; pass a checkpoint of {method!r}")
    return state


def load_latest_checkpoint(folder: str | Path, *, method: str | None = None, map_location="cpu") -> tuple[dict, Path, list[str]]:
    """Newest loadable checkpoint in ``folder``.

    Returns ``(state, path, skipped)`` where ``skipped`` lists one-line reasons
    for newer files that were damaged and passed over.

    Raises:
        CheckpointError: when there is none (the message says where it looked),
        or when a checkpoint belongs to another method/version (never skipped).
    """
    skipped: list[str] = []
    files = list_checkpoints(folder)
    for path in reversed(files):
        try:
            return load_checkpoint_file(path, method=method, map_location=map_location), path, skipped
        except CheckpointError as exc:
            if "written by method" in str(exc) or "has format" in str(exc):
                raise
            skipped.append(str(exc))
    where = f"{folder}" + (f" ({len(files)} damaged)" if files else "")
    raise CheckpointError(f"no complete checkpoint in {where}; the run cannot be resumed, start it again without --resume")
