"""Cost estimates for ``kneas-bench --dry-run``.

How a cell's cost is estimated (printed with the dry run):

1. If cells with the same method, preset and view count are already complete
   in this output folder, the median of their recorded ``wall_time_s`` is used
   ("measured here").
2. Otherwise: ``seconds per step`` (the table below, for the preset and the
   device kind) x training steps + a fixed per-run overhead. Training steps =
   views x (epochs + prior epochs), one step per training projection per epoch
   (SPEC §3); the prior single-material model (SPEC §4) is trained only by
   methods with automatic bounds (neas-2m, kselector*, k-neas), not by neas-1m,
   naf or the classical references, and only when the preset fits the bounds on
   a prior (``paper``, ``tiny``; the ``cpu`` preset fits them on ASD-POCS). Epochs
   come from the preset (``presets.TABLE``); extra ``--trainer.epochs`` /
   ``--trainer.prior-epochs`` arguments are honoured.
3. The classical references (``grid.REFERENCE_METHODS``: fdk, sart, os-sart,
   cgls, asd-pocs) train nothing: seconds per iteration at 50 views x
   iterations x views / 50 + a fixed per-run overhead (start-up, evaluation),
   the same for every preset and device. Iterations are the algorithm's default
   (``classical.reconstruct.DEFAULT_ITERATIONS``) unless ``--reconstruction.iterations``
   is among the extra arguments; FDK counts as one "iteration".

Where the figures come from (torch 2.13 CPU, 2 cores shared with other work,
so pessimistic): ``tiny`` from the first real ``kneas-bench table1 --preset
tiny`` cells (``train_time_s / steps`` = 0.038 s per step, evaluation and start-up
~60 s per run, at load ~10); ``cpu`` and ``paper`` from timing single k-neas
(K = 2) training steps (forward, eikonal, backward, Adam) on the built-in foot
scene at load ~3.5: paper 13 s (10.6-15.8 s); ``cpu`` from a quiet
``kneas-train k-neas --scene foot`` (6.3 steps/s at 256 + 64 rays; 0.6 of that
step's cost at today's 128 + 32; FDK + warm start + evaluation + start-up ~2.7 min). The paper preset's per-run overhead is a guess. No GPU was available: GPU rows are ``None`` and
the estimate says so; a first completed cell then calibrates rule 1. Classical
references (CPU, built-in foot, 50 views, 2 cores, quiet; ``python benchmarks/classical.py
--scenes foot,jaw,chest,abdomen --dice``): fdk 0.9 s, sart 6.4 s (5 iterations), os-sart
9.6 s (10), cgls 26.1 s (30), asd-pocs 13.8 s (10); the overhead (start-up, simulation cache
read, evaluation of 50 held-out views, figures) ~25 s.
"""

from __future__ import annotations

import statistics
from pathlib import Path
from typing import Optional, Sequence

from .. import presets
from .cells import cell_dir, find_metrics
from .grid import ORACLE_ITERATIONS, REFERENCE_METHODS, Cell, is_reference

DEFAULT_VIEWS = 50

# seconds per training step, by (preset, device kind). None = not measured.
SECONDS_PER_STEP: dict[tuple[str, str], Optional[float]] = {
    ("tiny", "cpu"): 0.04,
    ("cpu", "cpu"): 0.10,  # 0.16 at 256 + 64 rays (the cpu preset before 2026-11-26); a step of 128 + 32 costs ~0.6 of one
    ("paper", "cpu"): 13.0,
    ("tiny", "gpu"): None,
    ("cpu", "gpu"): None,
    ("paper", "gpu"): None,
}
# fixed per-run overhead in seconds (interpreter + torch import, scene load or
# simulation, evaluation on the held-out views, volume metrics, figures), by preset.
OVERHEAD_S: dict[str, float] = {"tiny": 60.0, "cpu": 165.0, "paper": 300.0}
# classical references: seconds per iteration at 50 views (CPU; fdk: the whole filtered back-projection)
# and a fixed per-run overhead (start-up, evaluation on the held-out views).
CLASSICAL_S_PER_ITERATION: dict[str, float] = {"fdk": 1.0, "sart": 1.3, "os-sart": 1.0, "cgls": 0.9, "asd-pocs": 0.6}
# seconds per iteration whatever the view count: ASD-POCS's 20 TV steps on the 128^3 grid (2 cores: 0.88,
# 0.90, 1.2 and 1.4 s per iteration at 5, 10, 20 and 50 views on the built-in chest, 2026-12-03)
CLASSICAL_S_PER_ITERATION_FIXED: dict[str, float] = {"asd-pocs": 0.8}
CLASSICAL_OVERHEAD_S = 25.0
# the refine-classical procedure's band-correction passes (12 of them, about 20 s each on a 128^3 grid on
# 2 cores, at any view count), and what a run under the time budget takes beyond it (the evaluation):
# with them the built-in chest's cells of kneas-bench views (5, 10, 20, 50 views, 2026-12-03) were
# estimated 475, 515, 595 and 625 s and took 423-432, 500-554, 549-550 and 624-627 s.
CORRECTION_S = 270.0
BUDGET_OVERRUN_S = 25.0
# methods that train no NeAS-1M prior (the classical references train nothing)
PRIOR_METHODS_NO = ("neas-1m", "naf", *REFERENCE_METHODS)


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


def _procedure_stages(cell: Cell, preset: str) -> list[str]:
    """The stages a cell's run goes through: its ``--procedure`` (or the preset's), less ``--skip-stages``."""
    extra = list(cell.extra)
    name = presets.TABLE[preset]["procedure"]
    skip: list[str] = []
    for i, a in enumerate(extra):
        if a == "--procedure" and i + 1 < len(extra):
            name = extra[i + 1]
        elif a.startswith("--procedure="):
            name = a.split("=", 1)[1]
        elif a == "--skip-stages":
            for b in extra[i + 1:]:
                if b.startswith("--"):
                    break
                skip.append(b)
    try:
        stages = presets.procedure_of(name).stages
    except Exception:  # an unknown procedure: the run itself will say so
        return []
    return [s for s in stages if s not in skip]


def training_steps(cell: Cell, preset: str) -> int:
    table = presets.TABLE[preset]["trainer"]
    epochs = _extra_int(cell.extra, "--trainer.epochs") or table["epochs"]
    prior = _extra_int(cell.extra, "--trainer.prior-epochs", "--trainer.prior_epochs")
    prior = table["prior_epochs"] if prior is None else prior
    views = cell.views or DEFAULT_VIEWS
    uses_prior = cell.method not in PRIOR_METHODS_NO and "classical-start" not in _procedure_stages(cell, preset)
    return views * (epochs + (prior if uses_prior else 0))


def classical_iterations(cell: Cell) -> int:
    """Iterations of a classical reference cell: an oracle's :data:`~.grid.ORACLE_ITERATIONS`, else
    ``--reconstruction.iterations`` or the algorithm's default (fdk: 1)."""
    if cell.method == "fdk":
        return 1
    if cell.oracle:
        return ORACLE_ITERATIONS
    from ..classical.reconstruct import DEFAULT_ITERATIONS

    given = _extra_int(cell.extra, "--reconstruction.iterations")
    return given or DEFAULT_ITERATIONS.get(cell.method, 1)


def classical_estimate(cell: Cell) -> tuple[Optional[float], str]:
    """``(seconds, how)`` for a classical reference cell (rule 3 of the module docstring)."""
    per_iteration = CLASSICAL_S_PER_ITERATION.get(cell.method)
    if per_iteration is None:
        return None, f"no timing recorded for the classical method {cell.method}"
    views = cell.views or DEFAULT_VIEWS
    iterations = classical_iterations(cell)
    fixed = CLASSICAL_S_PER_ITERATION_FIXED.get(cell.method, 0.0)
    seconds = (per_iteration * views / DEFAULT_VIEWS + fixed) * iterations + CLASSICAL_OVERHEAD_S
    what = ("reconstruction" if cell.method == "fdk" else
            f"{iterations} iterations x ({per_iteration:g} s" + (f" + {fixed:g} s TV" if fixed else "") + ")")
    scaled = f", the views' part x {views}/{DEFAULT_VIEWS}" if views != DEFAULT_VIEWS else ""
    return seconds, f"classical {cell.method}: {what} (CPU, {DEFAULT_VIEWS} views){scaled} + {CLASSICAL_OVERHEAD_S:g} s"


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
    if is_reference(cell.method):
        return classical_estimate(cell)
    steps = training_steps(cell, preset)
    sps = SECONDS_PER_STEP.get((preset, kind))
    if sps is None:
        return None, f"{steps} steps; no {kind.upper()} timing recorded for preset {preset}"
    seconds = steps * sps + OVERHEAD_S.get(preset, 0.0)
    how = f"{steps} steps x {sps:g} s ({preset}, {kind}) + {OVERHEAD_S.get(preset, 0.0):g} s"
    stages = _procedure_stages(cell, preset)
    if "correction" in stages and kind == "cpu":
        seconds += CORRECTION_S
        how += f" + {CORRECTION_S:g} s of correction passes"
    if "time-budget" in stages:
        from ..stages.time_budget import TimeBudgetConfig

        cap = TimeBudgetConfig().seconds + BUDGET_OVERRUN_S
        if seconds > cap:
            seconds, how = cap, how + f", capped by the time budget at {cap:g} s"
    return seconds, how


def format_seconds(s: Optional[float]) -> str:
    if s is None:
        return "?"
    if s < 90:
        return f"{s:.0f} s"
    if s < 5400:
        return f"{s / 60:.1f} min"
    return f"{s / 3600:.1f} h"
