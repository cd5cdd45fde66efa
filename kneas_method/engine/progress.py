"""Progress display for the training stages (rich): bars, steps/s, ETA, loss terms, summary table."""

from __future__ import annotations

import math
from typing import Mapping

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


def stage_progress(console, unit: str = "steps") -> Progress:
    """A rich Progress for one stage: description, bar, N/M, rate, elapsed, ETA, info (loss terms)."""
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


SUMMARY_KEYS = ("psnr2d", "ssim2d", "psnr3d", "ssim3d", "psnr3d_ls", "ssim3d_ls", "num_materials", "parameters",
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
