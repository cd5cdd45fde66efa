"""Run folders: ``DIR/<scene>/<method>/<timestamp>/`` and what goes in them.

Layout of a run folder::

    config.json        the resolved TrainConfig (``kneas-train --config`` re-runs it)
    checkpoints/       step-XXXXXXXX.ckpt (atomic, weights-only; neural methods only)
    metrics.json       final metrics (SPEC §5) and run facts
    bounds.json        attenuation bounds used (methods with bounds)
    figures/           PNGs: loss curves, projections, slices, GMM fit
    log.jsonl          one JSON line per logged step
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

from ..atomic import atomic_write
from ..errors import KneasError

MIN_FREE_BYTES = 200 * 1024 * 1024


def timestamp() -> str:
    return time.strftime("%Y%m%d-%H%M%S")


def check_writable(folder: str | Path, needed_bytes: int = MIN_FREE_BYTES, flag: str = "--output-dir") -> Path:
    """Create ``folder`` if needed and prove it is writable with enough free space.

    Raises:
        KneasError: before any work starts, naming the folder and the fix
        (``flag``: the option that chooses another folder).
    """
    folder = Path(folder)
    blocker = next((p for p in (folder, *folder.parents) if p.exists() and not p.is_dir()), None)
    if blocker is not None:
        raise KneasError(f"output folder {folder} cannot be made: {blocker} is a file, not a folder; choose another with {flag}")
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".kneas-write-test-", dir=folder)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise KneasError(f"output folder {folder} is not writable ({exc.strerror or exc}); choose another with {flag}") from None
    free = shutil.disk_usage(folder).free
    if free < needed_bytes:
        raise KneasError(
            f"output folder {folder} has only {free / 2**20:.0f} MiB free, about {needed_bytes / 2**20:.0f} MiB are needed; "
            f"free some space or choose another folder with {flag}"
        )
    return folder


def create_run_dir(output_dir: str | Path, scene: str, method: str, needed_bytes: int = MIN_FREE_BYTES) -> Path:
    """A new run folder ``output_dir/<scene>/<method>/<timestamp>[-N]`` holding an empty ``figures/``
    (``checkpoints/`` is made by the first checkpoint)."""
    parent = check_writable(Path(output_dir) / safe_name(scene) / safe_name(method), needed_bytes)
    base = timestamp()
    for n in range(1000):
        run = parent / (base if n == 0 else f"{base}-{n}")
        try:
            run.mkdir()
        except FileExistsError:
            continue
        (run / "figures").mkdir()
        return run
    raise KneasError(f"could not create a new run folder under {parent}")


def safe_name(name: str) -> str:
    """A folder name from a scene or method name: letters, digits, ``-_.``; others become ``_``."""
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in str(name)) or "x"


def _json_default(value: Any):
    if hasattr(value, "tolist"):
        return value.tolist()
    if hasattr(value, "item"):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def _finite(obj: Any) -> Any:
    """Replace non-finite floats by strings so the file is strict JSON."""
    if isinstance(obj, float) and not math.isfinite(obj):
        return "inf" if obj > 0 else ("-inf" if obj < 0 else "nan")
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    return obj


def write_json(path: str | Path, obj: Any) -> Path:
    """Write JSON atomically (temp file + rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps(_finite(json.loads(json.dumps(obj, default=_json_default))), indent=2, sort_keys=False)
    atomic_write(path, lambda handle: handle.write((text + "\n").encode()))
    return path


def read_json(path: str | Path, what: str = "file") -> Any:
    path = Path(path)
    if not path.is_file():
        raise KneasError(f"{what} {path} does not exist")
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise KneasError(f"{what} {path} is not valid JSON ({exc}); fix or delete it") from None


def save_run_config(run_dir: str | Path, config) -> Path:
    """``RUN_DIR/config.json``: the resolved config, as ``kneas-train --config`` re-runs it."""
    import dataclasses

    from ..config import to_dict

    return write_json(Path(run_dir) / "config.json", to_dict(dataclasses.replace(config, resume=None, dry_run=False)))
