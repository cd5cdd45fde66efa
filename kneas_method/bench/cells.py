"""Running one cell and recording it: ``OUT/cells/<cell id>/``.

Layout of a cell folder::

    cell.json                          status (done / failed), error tail, wall time, run dir, command
    train.log                          kneas-train's stdout + stderr
    <scene>/<method>/<timestamp>/      the ordinary kneas-train run folder (metrics.json, config.json, ...)

A cell is *complete* when a ``metrics.json`` exists under its folder; complete
cells are never run again, so a rerun continues where the last one stopped. A cell
whose run was stopped after its first checkpoint (Ctrl-C, a killed worker) is resumed
(``kneas-train --resume RUN_DIR``), not trained again.
"""

from __future__ import annotations

import dataclasses
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence

from ..engine.run_dir import read_json, safe_name, write_json
from .grid import DEFAULT_TRAIN_PREFIX, Cell

CELLS = "cells"
ERROR_TAIL_LINES = 20


def cell_dir(output_dir: str | Path, cell: Cell) -> Path:
    """``OUT/cells/<folder>``: the cell's own id, or the folder it shares (``Cell.folder``)."""
    return Path(output_dir) / CELLS / (cell.folder or cell.id)


def own_folders_first(output_dir: str | Path, cells: Sequence[Cell]) -> list[Cell]:
    """``cells``, each that already has a folder of its own under ``output_dir`` (it ran there before it
    was given a shared one, :attr:`Cell.folder`) keeping that folder, so what it did is not done again."""
    return [dataclasses.replace(c, folder=None) if c.folder and (Path(output_dir) / CELLS / c.id).is_dir() else c for c in cells]


def find_metrics(folder: str | Path, method: Optional[str] = None) -> Optional[Path]:
    """The newest ``metrics.json`` of a ``method`` run under ``folder/<scene>/<method>/<run>/``, or None.

    Only the cell's own method counts: kneas-train also writes metrics of helper
    runs beside it (e.g. the NeAS-1M prior in ``<scene>/neas-1m-prior/<hash>/``),
    which must not make a cell look complete.
    """
    folder = Path(folder)
    if not folder.is_dir():
        return None
    pattern = f"*/{safe_name(method)}/*/metrics.json" if method else "*/*/*/metrics.json"
    found = [p for p in folder.glob(pattern) if p.is_file()]
    if not found:
        return None
    return max(found, key=lambda p: p.stat().st_mtime)


def unfinished_run(folder: str | Path, method: str) -> Optional[Path]:
    """The newest ``method`` run under ``folder/<scene>/<method>/<run>/`` that has a checkpoint and
    no ``metrics.json`` (stopped part-way, resumable), or None."""
    runs = [p.parent for p in Path(folder).glob(f"*/{safe_name(method)}/*/config.json")
            if not (p.parent / "metrics.json").is_file() and any((p.parent / "checkpoints").glob("*.ckpt"))]
    return max(runs, key=lambda p: p.stat().st_mtime) if runs else None


def is_complete(output_dir: str | Path, cell: Cell) -> bool:
    return find_metrics(cell_dir(output_dir, cell), cell.method) is not None


@dataclass
class CellResult:
    """What one cell did. ``status``: ``done``, ``failed`` or ``skipped`` (already complete)."""

    cell_id: str
    status: str
    wall_time_s: float = 0.0
    run_dir: Optional[str] = None
    error: Optional[str] = None
    returncode: Optional[int] = None

    def to_dict(self) -> dict:
        return dict(self.__dict__)


def _tail(path: Path, lines: int = ERROR_TAIL_LINES) -> str:
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError:
        return ""
    return "\n".join(text.rstrip().splitlines()[-lines:])


def _die_with_parent() -> None:  # pragma: no cover - runs in the child
    """Linux: the training process is killed when the process that started it dies.

    So killing ``kneas-bench`` (or a Ray worker) mid-way leaves no orphan training
    that could finish later behind the rerun's back.
    """
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        libc.prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except Exception:
        pass


def run_cell(cell: Cell, output_dir: str | Path, prefix: Sequence[str] = DEFAULT_TRAIN_PREFIX,
             env: Optional[dict[str, str]] = None, timeout_s: Optional[float] = None) -> CellResult:
    """Run one cell as a ``kneas-train`` subprocess (unless already complete) and write its ``cell.json``.

    Never raises for a failing run: the failure (exit status + the last lines of
    ``train.log``) is recorded and returned, so the other cells go on.
    """
    folder = cell_dir(output_dir, cell)
    done = find_metrics(folder, cell.method)
    if done is not None:
        return CellResult(cell.id, "skipped", run_dir=str(done.parent))
    folder.mkdir(parents=True, exist_ok=True)
    stopped = unfinished_run(folder, cell.method)
    cmd = [*prefix, "--resume", str(stopped)] if stopped is not None else cell.command(folder, prefix)
    record = {"cell": cell.to_dict(), "command": cmd, "status": "running", "started": time.strftime("%Y-%m-%dT%H:%M:%S"),
              "host": os.uname().nodename, "cuda_visible_devices": (env or os.environ).get("CUDA_VISIBLE_DEVICES")}
    if stopped is not None:
        record["resumed"] = str(stopped)
    write_json(folder / "cell.json", record)
    log = folder / "train.log"
    t0 = time.monotonic()
    rc: Optional[int] = None
    error: Optional[str] = None
    try:
        with open(log, "a" if stopped is not None else "w", encoding="utf-8") as handle:
            handle.write("$ " + " ".join(cmd) + "\n")
            handle.flush()
            proc = subprocess.Popen(cmd, stdout=handle, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                    env=env, preexec_fn=_die_with_parent if sys.platform.startswith("linux") else None)
            try:
                rc = proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
                error = f"timed out after {timeout_s:.0f} s"
            except BaseException:
                proc.terminate()
                try:
                    proc.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    proc.kill()
                record.update(status="interrupted", wall_time_s=round(time.monotonic() - t0, 3))
                write_json(folder / "cell.json", record)
                raise
    except OSError as exc:
        error = f"could not start kneas-train: {exc}"
    wall = time.monotonic() - t0
    metrics = find_metrics(folder, cell.method)
    if metrics is not None:
        # metrics.json is what makes a cell complete; a non-zero exit after it is noted, not fatal.
        note = None if rc == 0 else f"kneas-train exited with status {rc} after writing metrics.json:\n{_tail(log)}"
        result = CellResult(cell.id, "done", wall, str(metrics.parent), note, rc)
    else:
        if error is None:
            why = f"kneas-train exited with status {rc}" if rc != 0 else "kneas-train exited 0 but wrote no metrics.json"
            error = why + (":\n" + _tail(log) if _tail(log) else "")
        result = CellResult(cell.id, "failed", wall, str(metrics.parent) if metrics else None, error, rc)
    record.update(status=result.status, wall_time_s=round(wall, 3), run_dir=result.run_dir, error=result.error,
                  returncode=rc, finished=time.strftime("%Y-%m-%dT%H:%M:%S"))
    write_json(folder / "cell.json", record)
    return result


def mark_interrupted(output_dir: str | Path, cell: Cell) -> None:
    """Record a cell whose run was stopped from outside (e.g. a cancelled Ray task) as interrupted."""
    path = cell_dir(output_dir, cell) / "cell.json"
    rec = read_cell_record(output_dir, cell)
    if rec and rec.get("status") == "running" and not is_complete(output_dir, cell):
        rec["status"] = "interrupted"
        write_json(path, rec)


def read_cell_record(output_dir: str | Path, cell: Cell) -> Optional[dict]:
    return read_record(cell_dir(output_dir, cell))


def read_record(folder: str | Path) -> Optional[dict]:
    """A cell folder's ``cell.json``, or None when it is missing or unreadable."""
    path = Path(folder) / "cell.json"
    if not path.is_file():
        return None
    try:
        return read_json(path, "cell record")
    except Exception:
        return None


def is_finished(folder: str | Path) -> bool:
    """The cell in ``folder`` ran to an end: its method's run has a ``metrics.json``, or its record says it failed.

    A running or interrupted cell is not finished: its records are partial, and a
    rerun starts or resumes it.
    """
    record = read_record(folder)
    if not isinstance(record, dict):
        return False
    cell = record.get("cell")
    method = cell.get("method") if isinstance(cell, dict) else None
    return record.get("status") == "failed" or (method is not None and find_metrics(folder, method) is not None)
