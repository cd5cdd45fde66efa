"""Progress and the end-of-run summary: plain lines in logs, rich bars on terminals."""

import io
import re
import subprocess
import sys

from rich.console import Console

from kneas_method.engine.progress import PlainProgress, stage_progress

from conftest import simulated_foot


def test_plain_progress_prints_periodic_and_final_lines():
    out = io.StringIO()
    console = Console(file=out, force_terminal=False, width=200)
    progress = stage_progress(console, unit="views")
    assert isinstance(progress, PlainProgress)
    progress.period = 0.0  # every update prints
    with progress:
        task = progress.add_task("evaluation", total=4, info="4 held-out views")
        for done in range(1, 5):
            progress.update(task, completed=done)
        progress.update(task, completed=4)  # finished: no second final line
    lines = out.getvalue().splitlines()
    assert lines[0].startswith("evaluation: views 1/4 (25%)") and lines[-1].startswith("evaluation: views 4/4 (100%)")
    assert len(lines) == 4 and "took" in lines[-1] and all("4 held-out views" in line for line in lines)
    quiet = PlainProgress(console, period=3600)
    t = quiet.add_task("model", total=10)
    before = out.getvalue()
    quiet.update(t, completed=5)  # within the period: silent
    assert out.getvalue() == before
    quiet.update(t, completed=10)  # the end is always printed
    assert out.getvalue().splitlines()[-1].startswith("model: steps 10/10 (100%)")


def test_terminal_gets_rich_bars():
    console = Console(file=io.StringIO(), force_terminal=True)
    assert not isinstance(stage_progress(console), PlainProgress)


def test_piped_run_log_is_plain_lines_with_evaluation_progress_and_summary(tmp_path):
    """``kneas-train ... | cat``: no carriage returns or escape codes; the evaluation shows
    ``views done/total``; the run ends with the summary block."""
    scene = simulated_foot(tmp_path, "pipefoot", 16, 15.0, n_train=4)
    proc = subprocess.run([sys.executable, "-m", "kneas_method.cli.train", "k-neas", "--scene", str(scene), "--preset", "tiny",
                           "--output-dir", str(tmp_path / "out")], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    log = proc.stdout
    assert "\r" not in log and "\x1b" not in log
    assert re.search(r"^evaluation: views 4/4 \(100%\)", log, re.M), log
    assert re.search(r"^model: steps 8/8 \(100%\)", log, re.M), log
    tail = log[log.rindex("time per stage:"):]
    assert "training" in tail and "evaluation" in tail and "total" in tail
    run_dir = [l for l in log.splitlines() if l.startswith("run folder: ")][-1].split(": ", 1)[1]
    for command in ("kneas-export mesh", "kneas-eval", "kneas-export figures"):
        assert f"{command} {run_dir}" in tail
