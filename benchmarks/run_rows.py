"""Shared by the per-run benchmarks (``ceiling.py``, ``error_anatomy.py``): one JSON row per run folder."""

from __future__ import annotations

import json
import platform
import time
from collections.abc import Callable, Sequence
from pathlib import Path


def run_rows(runs: Sequence[Path], row_of: Callable[[Path], dict], out: Path | None = None) -> list[dict]:
    """``row_of(run)`` for each run folder, timed (``wall_s``) and printed as one JSON line; with
    ``out``, all rows and the machine written there as JSON."""
    rows = []
    for run in runs:
        t0 = time.perf_counter()
        row = row_of(run)
        row["wall_s"] = round(time.perf_counter() - t0, 1)
        rows.append(row)
        print(json.dumps(row), flush=True)
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps({"machine": f"{platform.machine()} {platform.system()}", "rows": rows}, indent=2), encoding="utf-8")
    return rows
