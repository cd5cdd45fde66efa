"""Progress of the long stages, and the summary table.

:func:`stage_progress` gives rich bars (description, bar, N/M, rate, elapsed, ETA, loss
terms) when the console is a terminal, and :class:`PlainProgress` otherwise (a pipe, a
file, ``nohup``, a cluster job): plain text lines, one every ``KNEAS_PROGRESS_SECONDS``
seconds (default 10) and one when a stage ends, each with the stage, done/total, rate,
ETA and the loss terms, with no carriage returns or escape codes.
"""

from __future__ import annotations

import math
import os
import time
from typing import Mapping, Optional

from rich.progress import BarColumn, MofNCompleteColumn, Progress, ProgressColumn, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table
from rich.text import Text


class RateColumn(ProgressColumn):
    """``12.3 steps/s`` (or ``s/step`` when slower than one per second)."""

    def __init__(self, unit: str = "steps"):
        super().__init__()
        self.unit = unit

    def render(self, task) -> Text:
        speed = task.finished_speed or task.speed
        if not speed:
            return Text(f"-- {self.unit}/s", style="cyan")
        if speed < 1:
            return Text(f"{1 / speed:.2f} s/{self.unit.rstrip('s')}", style="cyan")
        return Text(f"{speed:.1f} {self.unit}/s", style="cyan")


def _duration(seconds: float) -> str:
    seconds = max(0.0, float(seconds))
    if seconds < 60:
        return f"{seconds:.0f} s"
    m, s = divmod(int(round(seconds)), 60)
    if m < 60:
        return f"{m} min {s:02d} s"
    h, m = divmod(m, 60)
    return f"{h} h {m:02d} min"


class PlainProgress:
    """Progress as plain text lines (for logs): the subset of rich's ``Progress`` the stages use.

    ``add_task(description, total, completed=0, info="")`` -> task id;
    ``update(task, completed=..., info=..., advance=...)``; a context manager; ``console``.
    A line is printed at most every ``period`` seconds, and when a task completes.
    """

    def __init__(self, console, unit: str = "steps", period: Optional[float] = None):
        self.console = console
        self.unit = unit
        self.period = float(os.environ.get("KNEAS_PROGRESS_SECONDS", 10.0)) if period is None else float(period)
        self._tasks: dict[int, dict] = {}

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def add_task(self, description: str, total: Optional[float] = None, completed: float = 0, info: str = "",
                 unit: Optional[str] = None, **_) -> int:
        """A new task; ``unit`` overrides the progress's unit for this task's lines."""
        task = len(self._tasks)
        now = time.perf_counter()
        self._tasks[task] = {"description": description, "total": total, "completed": completed, "start_done": completed,
                             "start": now, "last_print": now, "info": info, "finished": False, "unit": unit or self.unit}
        return task

    def update(self, task: int, completed: Optional[float] = None, advance: Optional[float] = None,
               info: Optional[str] = None, total: Optional[float] = None, **_) -> None:
        t = self._tasks[task]
        if total is not None:
            t["total"] = total
        if advance is not None:
            t["completed"] += advance
        if completed is not None:
            t["completed"] = completed
        if info is not None:
            t["info"] = info
        now = time.perf_counter()
        done = t["total"] is not None and t["completed"] >= t["total"]
        if t["finished"] or not (done or now - t["last_print"] >= self.period):
            return
        t["last_print"], t["finished"] = now, done
        self.console.print(self.line(task), soft_wrap=True, markup=False, highlight=False)

    def line(self, task: int) -> str:
        """``model: steps 120/2000 (6%), 6.3 steps/s, eta 5 min 02 s, intensity 1.2e-05``."""
        t = self._tasks[task]
        unit = t["unit"]
        elapsed = max(time.perf_counter() - t["start"], 1e-9)
        rate = (t["completed"] - t["start_done"]) / elapsed
        total = t["total"]
        parts = [f"{t['description']}: {unit} {t['completed']:.0f}" + (f"/{total:.0f} ({100 * t['completed'] / max(total, 1):.0f}%)" if total else "")]
        if rate > 0:
            parts.append(f"{rate:.2f} {unit}/s" if rate >= 1 else f"{1 / rate:.2f} s per {unit.rstrip('s')}")
            if total:
                parts.append(f"eta {_duration((total - t['completed']) / rate)}" if t["completed"] < total else f"took {_duration(elapsed)}")
        if t["info"]:
            parts.append(str(t["info"]))
        return ", ".join(parts)


def stage_progress(console, unit: str = "steps"):
    """Progress of one stage on ``console`` (None: kneas's console): rich bars on a terminal,
    :class:`PlainProgress` lines otherwise."""
    if console is None:
        from ..console import console
    if not console.is_terminal:
        return PlainProgress(console, unit)
    return Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(bar_width=28),
        MofNCompleteColumn(),
        RateColumn(unit),
        TimeElapsedColumn(),
        TextColumn("eta"),
        TimeRemainingColumn(),
        TextColumn("{task.fields[info]}"),
        console=console,
        transient=False,
        refresh_per_second=4,
    )


def format_losses(losses: Mapping[str, float]) -> str:
    """``intensity 1.2e-03 eikonal 4.0e-04 total ...`` (compact)."""
    return " ".join(f"{k} {v:.2e}" for k, v in losses.items())


def _fmt(value) -> str:
    if isinstance(value, bool) or value is None:
        return str(value)
    if isinstance(value, int):
        return f"{value:,}"
    if isinstance(value, float):
        if math.isinf(value) or math.isnan(value):
            return str(value)
        if abs(value) >= 1000 or (abs(value) < 1e-3 and value != 0):
            return f"{value:.4g}"
        return f"{value:.4f}"
    return str(value)


SUMMARY_KEYS = ("psnr2d", "ssim2d", "psnr3d", "ssim3d", "psnr3d_ls", "ssim3d_ls", "psnr3d_truth_peak", "ssim3d_truth_range", "num_materials", "parameters",
                "steps", "wall_time_s", "preset", "scene_source")


def summary_table(metrics: Mapping, title: str = "metrics") -> Table:
    """A two-column rich Table of the headline metrics (those present)."""
    table = Table(title=title, show_header=True, header_style="bold")
    table.add_column("metric")
    table.add_column("value", justify="right")
    for key in SUMMARY_KEYS:
        if key in metrics and not isinstance(metrics[key], (list, dict)):
            table.add_row(key, _fmt(metrics[key]))
    return table
