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
   On the CPU every figure of rule 2 and 3 is then scaled by this machine's speed:
   :func:`probe_seconds` (a fixed slice of a ``cpu``-preset training step, on one
   thread, ~0.2 s) against :data:`PROBE_REFERENCE_S`, its time where the figures
   were measured. The same VM type ran the same cells 1.8 times slower on one day
   than on another (its host's load), which no fixed figure follows.
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
scene at load ~3.5: paper 13 s (10.6-15.8 s); ``cpu`` from the first cells of
``kneas-bench table1 --preset cpu`` on a quiet machine (2026-12-04; the probe's
reference was timed there the same hour). The paper preset's per-run overhead is a guess. No GPU was available: GPU rows are ``None`` and
the estimate says so; a first completed cell then calibrates rule 1. Classical
references: the same table's reference and oracle cells (the comments at the figures).
"""

from __future__ import annotations

import statistics
from pathlib import Path
from typing import Optional, Sequence

from .. import presets
from .aggregate import _float
from .cells import cell_dir, find_metrics, read_cell_record
from .grid import ORACLE_ITERATIONS, REFERENCE_METHODS, Cell, is_reference

DEFAULT_VIEWS = 50

# seconds per training step, by (preset, device kind). None = not measured.
SECONDS_PER_STEP: dict[tuple[str, str], Optional[float]] = {
    ("tiny", "cpu"): 0.04,
    ("cpu", "cpu"): 0.041,  # train_time_s / steps of kneas-bench table1's first cells (abdomen, 4000 steps, 2026-12-04)
    ("paper", "cpu"): 13.0,
    ("tiny", "gpu"): None,
    ("cpu", "gpu"): None,
    ("paper", "gpu"): None,
}
# fixed per-run overhead in seconds (interpreter + torch import, scene load or
# simulation, evaluation on the held-out views, volume metrics, figures), by preset.
OVERHEAD_S: dict[str, float] = {"tiny": 60.0, "cpu": 55.0, "paper": 300.0}
# classical references: seconds per iteration at 50 views (CPU; fdk: the whole filtered back-projection)
# and a fixed per-run overhead (start-up, evaluation on the held-out views). From kneas-bench table1's
# reference cells on the built-in abdomen and jaw (2026-12-04, 2 cores, quiet): fdk 5 s, sart 8 s (5
# iterations) and 28-29 s (40), os-sart 10-12 s (10), cgls 20 s (30), asd-pocs 14-16 s (10) and 45-46 s (40).
CLASSICAL_S_PER_ITERATION: dict[str, float] = {"fdk": 0.3, "sart": 0.59, "os-sart": 0.6, "cgls": 0.5, "asd-pocs": 0.42}
# seconds per iteration whatever the view count: ASD-POCS's 20 TV steps on the 128^3 grid (0.88, 0.90, 1.2
# and 1.4 s per iteration at 5, 10, 20 and 50 views on the built-in chest on 2026-12-03, a day the same
# cells ran 1.4 times slower than on 2026-12-04)
CLASSICAL_S_PER_ITERATION_FIXED: dict[str, float] = {"asd-pocs": 0.59}
CLASSICAL_OVERHEAD_S = 5.0
# the refine-classical procedure's band-correction passes (12 of them, about 10 s each on a 128^3 grid on
# 2 cores, at any view count), and what a run under the time budget takes beyond it (the evaluation).
# The cpu figures: kneas-bench table1's abdomen cells (neas-1m, k-neas K = 1, neas-2m; 2026-12-04, 2 cores,
# quiet) took 347, 369 and 382 s: training 159-163 s, correction 122-139 s, bounds 26-27 s, the rest
# (start-up, ASD-POCS, warm start, smoothing, evaluation) 48-61 s.
CORRECTION_S = 130.0
BUDGET_OVERRUN_S = 25.0
# methods that train no NeAS-1M prior (the classical references train nothing)
PRIOR_METHODS_NO = ("neas-1m", "naf", *REFERENCE_METHODS)
# the bounds' mixture fits on the start's histogram (methods with automatic bounds, as the prior)
BOUNDS_S = 27.0
# The machine-speed probe (probe_seconds): the points of one cpu-preset training step ((128 + 32) rays x 64
# samples), and its median seconds on the machine and day the CPU figures above were measured.
PROBE_POINTS = 10240
PROBE_REPEATS = 7
PROBE_REFERENCE_S = 0.021  # 2026-12-04, 2 cores, quiet (the probe on one of them)
# The probe's grid: the cpu preset's of 2026-12-04, when PROBE_REFERENCE_S was measured (fixed, so that the
# ratio measures the machine, not the preset).
PROBE_HASHGRID = {"num_levels": 6, "features_per_level": 2, "log2_hashmap_size": 16, "base_resolution": 16, "per_level_scale": 1.75}


def uses_bounds(cell: Cell) -> bool:
    """Whether the cell's run estimates bounds (on its prior, or on the classical start)."""
    return cell.method not in PRIOR_METHODS_NO


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
    """Median wall time of completed cells, keyed by :func:`measured_key`: the cell's own (``cell.json``,
    start-up included), else its run's (``metrics.json``)."""
    from ..engine.run_dir import read_json

    times: dict[tuple, list[float]] = {}
    for c in cells:
        m = find_metrics(cell_dir(output_dir, c), c.method)
        if m is None:
            continue
        wall = _float((read_cell_record(output_dir, c) or {}).get("wall_time_s"))
        if wall is None:
            try:
                wall = _float(read_json(m, "metrics").get("wall_time_s"))
            except Exception:
                wall = None
        if wall is not None:
            times.setdefault(measured_key(c), []).append(wall)
    return {k: statistics.median(v) for k, v in times.items()}


def measured_key(cell: Cell) -> tuple:
    """Cells that cost alike: same method, preset, view count, and oracle or not (40 iterations, not the default)."""
    return (cell.method, cell.preset, cell.views, cell.oracle)


def probe_seconds(repeats: int = PROBE_REPEATS) -> float:
    """Seconds of a fixed piece of work shaped as a ``cpu``-preset training step: the preset's hash grid and
    a 32-wide MLP, forward and backward, on :data:`PROBE_POINTS` points (the median of ``repeats`` runs,
    after one to warm up), on one thread."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # one thread: another process on the machine moves it little (two threads fight it 20-fold)
    try:
        return _probe(repeats)
    finally:
        torch.set_num_threads(threads)


def _probe(repeats: int) -> float:
    import time

    import torch

    from ..fields.hash_grid import HashGridConfig, HashGridEncoding

    generator = torch.Generator().manual_seed(0)
    grid = HashGridEncoding(HashGridConfig(**PROBE_HASHGRID, implementation="torch"))
    mlp = torch.nn.Sequential(torch.nn.Linear(grid.n_output_dims, 32), torch.nn.ReLU(), torch.nn.Linear(32, 32),
                              torch.nn.ReLU(), torch.nn.Linear(32, 1))
    points = torch.rand(PROBE_POINTS, 3, generator=generator) * 2 - 1
    times = []
    for i in range(repeats + 1):
        t0 = time.perf_counter()
        mlp(grid(points)).square().mean().backward()
        if i:
            times.append(time.perf_counter() - t0)
    return statistics.median(times)


def machine_speed(kind: str) -> tuple[float, str]:
    """``(factor, how)``: how much longer than on the machine the figures above were measured on a CPU
    run takes here now (:func:`probe_seconds` / :data:`PROBE_REFERENCE_S`); 1 on a GPU, unmeasured."""
    if kind != "cpu":
        return 1.0, "GPU figures unscaled"
    probe = probe_seconds()
    factor = probe / PROBE_REFERENCE_S
    return factor, (f"this machine now: {probe * 1000:.0f} ms for a probe that took {PROBE_REFERENCE_S * 1000:.0f} ms where the "
                    f"figures were measured, so CPU figures x {factor:.2f}")


def estimate(cell: Cell, kind: Optional[str] = None, measured: Optional[dict[tuple, float]] = None,
             speed: float = 1.0) -> tuple[Optional[float], str]:
    """``(seconds or None, how)`` for one cell; ``speed``: :func:`machine_speed`'s factor, applied to every
    figure of the tables above (not to the time budget, a wall-clock cap, nor to cells measured here)."""
    if measured and measured_key(cell) in measured:
        return measured[measured_key(cell)], "measured here"
    return _formula(cell, kind, speed)


def _formula(cell: Cell, kind: Optional[str], speed: float) -> tuple[Optional[float], str]:
    kind = kind or device_kind()
    preset = cell.preset
    if preset == "auto":
        preset = "paper" if kind == "gpu" else "cpu"
    if preset not in presets.TABLE:
        return None, f"unknown preset {preset}"
    scaled = f", x {speed:.2f} for this machine" if speed != 1.0 else ""
    if is_reference(cell.method):
        seconds, how = classical_estimate(cell)
        return (None if seconds is None else seconds * speed), how + scaled
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
    if uses_bounds(cell) and "classical-start" in stages:  # the mixtures fitted on the start's histogram
        seconds += BOUNDS_S
        how += f" + {BOUNDS_S:g} s of bounds"
    seconds *= speed
    how += scaled
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
