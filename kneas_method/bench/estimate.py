"""Cost estimates for ``kneas-bench --dry-run``.

How a cell's cost is estimated (printed with the dry run):

1. If cells with the same method, preset and view count are already complete
   in this output folder, the median of their recorded ``wall_time_s`` is used
   ("measured here").
2. Otherwise: ``seconds per step`` (the table below, for the preset and the
   device kind) x training steps + a fixed per-run overhead. Training steps =
   views x (epochs + prior epochs), one step per training projection per epoch
   (SPEC §3); the prior single-material model (SPEC §4) is trained only by
   methods with automatic bounds (neas-2m, kselector*, k-neas), not by neas-1m
   or naf, and only when the preset fits the bounds on a prior (``paper``,
   ``tiny``; the ``cpu`` preset fits them on FDK). Epochs come from the preset
   (``presets.TABLE``); extra ``--trainer.epochs`` / ``--trainer.prior-epochs``
   arguments are honoured. FDK costs only the overhead.

Where the figures come from (torch 2.13 CPU, 2 cores shared with other work,
so pessimistic): ``tiny`` from the first real ``kneas-bench table1 --preset
tiny`` cells (``train_time_s / steps`` = 0.038 s per step, evaluation and start-up
~60 s per run, at load ~10); ``cpu`` and ``paper`` from timing single k-neas
(K = 2) training steps (forward, eikonal, backward, Adam) on the built-in foot
scene at load ~3.5: paper 13 s (10.6-15.8 s); ``cpu`` from a quiet
``kneas-train k-neas --scene foot`` (6.3 steps/s; FDK + warm start +
evaluation + start-up ~2.7 min). The paper preset's per-run overhead is a guess. No GPU was available: GPU rows are ``None`` and
the estimate says so; a first completed cell then calibrates rule 1.
"""

from __future__ import annotations

import statistics
from pathlib import Path
from typing import Optional, Sequence

from .. import presets
from .cells import cell_dir, find_metrics
from .grid import Cell

DEFAULT_VIEWS = 50

# seconds per training step, by (preset, device kind). None = not measured.
SECONDS_PER_STEP: dict[tuple[str, str], Optional[float]] = {
    ("tiny", "cpu"): 0.04,
    ("cpu", "cpu"): 0.16,
    ("paper", "cpu"): 13.0,
    ("tiny", "gpu"): None,
    ("cpu", "gpu"): None,
    ("paper", "gpu"): None,
}
# fixed per-run overhead in seconds (interpreter + torch import, scene load or
# simulation, evaluation on the held-out views, volume metrics, figures), by preset.
OVERHEAD_S: dict[str, float] = {"tiny": 60.0, "cpu": 165.0, "paper": 300.0}
FDK_S = 10.0
PRIOR_METHODS_NO = ("neas-1m", "naf", "fdk")


def _extra_int(extra: Sequence[str], *names: str) -> Optional[int]:
    extra = list(extra)
    for i, a in enumerate(extra):
        for n in names:
            if a == n and i + 1 < len(extra):
                try:
                    return int(extra[i + 1])
                except ValueError:
                    return None
            if a.startswith(n + "="):
                try:
                    return int(a.split("=", 1)[1])
                except ValueError:
                    return None
    return None


def training_steps(cell: Cell, preset: str) -> int:
    table = presets.TABLE[preset]["trainer"]
    epochs = _extra_int(cell.extra, "--trainer.epochs") or table["epochs"]
    prior = _extra_int(cell.extra, "--trainer.prior-epochs", "--trainer.prior_epochs")
    prior = table["prior_epochs"] if prior is None else prior
    views = cell.views or DEFAULT_VIEWS
    uses_prior = cell.method not in PRIOR_METHODS_NO and presets.TABLE[preset]["run"]["bounds_volume"] == "prior"
    return views * (epochs + (prior if uses_prior else 0))


def device_kind() -> str:
    try:
        import torch

        return "gpu" if torch.cuda.is_available() else "cpu"
    except Exception:  # pragma: no cover
        return "cpu"


def measured_here(output_dir: str | Path, cells: Sequence[Cell]) -> dict[tuple, float]:
    """Median recorded wall time of completed cells, keyed by (method, preset, views)."""
    from ..engine.run_dir import read_json

    times: dict[tuple, list[float]] = {}
    for c in cells:
        m = find_metrics(cell_dir(output_dir, c), c.method)
        if m is None:
            continue
        try:
            wall = float(read_json(m, "metrics").get("wall_time_s"))
        except Exception:
            continue
        times.setdefault((c.method, c.preset, c.views), []).append(wall)
    return {k: statistics.median(v) for k, v in times.items()}


def estimate(cell: Cell, kind: Optional[str] = None, measured: Optional[dict[tuple, float]] = None) -> tuple[Optional[float], str]:
    """``(seconds or None, how)`` for one cell."""
    if measured and (cell.method, cell.preset, cell.views) in measured:
        return measured[(cell.method, cell.preset, cell.views)], "measured here"
    kind = kind or device_kind()
    preset = cell.preset
    if preset == "auto":
        preset = "paper" if kind == "gpu" else "cpu"
    if preset not in presets.TABLE:
        return None, f"unknown preset {preset}"
    if cell.method == "fdk":
        return FDK_S, "fixed FDK cost"
    steps = training_steps(cell, preset)
    sps = SECONDS_PER_STEP.get((preset, kind))
    if sps is None:
        return None, f"{steps} steps; no {kind.upper()} timing recorded for preset {preset}"
    return steps * sps + OVERHEAD_S.get(preset, 0.0), f"{steps} steps x {sps:g} s ({preset}, {kind}) + {OVERHEAD_S.get(preset, 0.0):g} s"


def format_seconds(s: Optional[float]) -> str:
    if s is None:
        return "?"
    if s < 90:
        return f"{s:.0f} s"
    if s < 5400:
        return f"{s / 60:.1f} min"
    return f"{s / 3600:.1f} h"
