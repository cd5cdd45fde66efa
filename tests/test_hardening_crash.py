"""SIGKILL during training (also in the middle of writing a checkpoint), then --resume:
a damaged checkpoint is never loaded and the final metrics equal an uninterrupted run's."""

import json
import random
import shutil
import signal
import subprocess
import sys
import os
import time
from pathlib import Path

import pytest

from kneas_method.data.naf import save_naf
from kneas_method.data.simulate import SimulationConfig, simulate_phantom
from test_resume import EXACT, kneas_train, only_run_dir

ARGS = ["--preset", "tiny", "--seed", "3", "--trainer.epochs", "6", "--trainer.checkpoint-every", "1",
        "--trainer.eval-every", "2"]

# Runs kneas-train with torch.save instrumented: the KILL_AT_SAVE-th checkpoint write stops half way and the
# process SIGKILLs itself (no cleanup, no finally blocks), as a power cut in the middle of a write would.
KILL_MID_WRITE = """
import io, os, signal, torch
n = int(os.environ["KILL_AT_SAVE"]); calls = [0]; real = torch.save
def save(obj, f, *a, **k):
    if hasattr(f, "write"):
        calls[0] += 1
        if calls[0] == n:
            buf = io.BytesIO(); real(obj, buf, *a, **k); data = buf.getvalue()
            f.write(data[: len(data) // 2]); f.flush(); os.fsync(f.fileno())
            os.kill(os.getpid(), signal.SIGKILL)
    return real(obj, f, *a, **k)
torch.save = save
from kneas_method.cli.train import main; main()
"""


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    path = tmp_path_factory.mktemp("crash-scene") / "tinyfoot.pickle"
    save_naf(simulate_phantom("foot", SimulationConfig(n_voxel=16, voxel_mm=15.0, n_detector=16, n_train=4, n_val=4)), path)
    return path


@pytest.fixture(scope="module")
def straight(scene, tmp_path_factory):
    """Metrics of an uninterrupted run, and how long it took."""
    out = tmp_path_factory.mktemp("straight")
    t0 = time.time()
    proc = kneas_train(["k-neas", "--scene", str(scene), *ARGS, "--output-dir", str(out)])
    text, _ = proc.communicate(timeout=300)
    assert proc.returncode == 0, text
    return json.loads((only_run_dir(out / "tinyfoot" / "k-neas") / "metrics.json").read_text()), time.time() - t0


def assert_same_metrics(run_dir: Path, reference: dict):
    metrics = json.loads((run_dir / "metrics.json").read_text())
    for key in EXACT:
        if key in reference:
            assert metrics[key] == reference[key], key


def resume(run_dir: Path) -> str:
    proc = kneas_train(["--resume", str(run_dir)])
    text, _ = proc.communicate(timeout=300)
    assert proc.returncode == 0, text
    assert "Traceback" not in text
    return text


def test_kill_mid_checkpoint_write_then_torn_file_then_resume(scene, straight, tmp_path):
    reference, _ = straight
    out = tmp_path / "out"
    cmd = [sys.executable, "-c", KILL_MID_WRITE, "k-neas", "--scene", str(scene), *ARGS, "--output-dir", str(out)]
    env = dict(os.environ, PYTHONUNBUFFERED="1", OMP_NUM_THREADS="1", KILL_AT_SAVE="5")
    proc = subprocess.run(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, timeout=300)
    assert proc.returncode == -signal.SIGKILL, proc.stdout
    # the half-written file is a temporary next to the complete ones; it never carries a checkpoint name
    ckpt_dirs = [p for p in out.rglob("checkpoints") if p.is_dir()]
    leftovers = [p for d in ckpt_dirs for p in d.iterdir() if p.name.endswith(".tmp")]
    assert len(leftovers) == 1, [list(d.iterdir()) for d in ckpt_dirs]
    run_dir = only_run_dir(out / "tinyfoot" / "k-neas")
    complete = sorted(leftovers[0].parent.glob("step-*.ckpt"))
    assert complete, "the kill came before any complete checkpoint"

    # worse than the atomic write allows: also tear the newest complete checkpoint (a disk that lost its tail)
    newest = complete[-1]
    newest.write_bytes(newest.read_bytes()[: newest.stat().st_size // 3])
    text = resume(run_dir)
    assert "skipped damaged checkpoint" in text and newest.name in text
    older = complete[-2].name if len(complete) > 1 else None
    if older is not None:
        assert f"resuming from {leftovers[0].parent / older}" in text.replace("\n", "")
    assert_same_metrics(run_dir, reference)


def _checkpoints(out: Path) -> set:
    return {(str(p), p.stat().st_mtime_ns) for p in out.rglob("step-*.ckpt")} if out.is_dir() else set()


@pytest.mark.slow
def test_random_sigkills_then_resume_match_straight_run(scene, straight, tmp_path):
    """SIGKILL the run at random moments (seeded): each time, a random 0-0.12 s (a few steps) after it has written a new
    checkpoint (so every cycle makes progress), in the prior or the model stage, mid-step, mid-validation or
    mid-write; resume each time until it finishes."""
    reference, _ = straight
    rng = random.Random(20240607)
    out = tmp_path / "out"
    parent = out / "tinyfoot" / "k-neas"
    kills = resumes = fresh_starts = 0
    budget = time.time() + 120
    while True:
        runs = [p for p in parent.iterdir() if p.is_dir()] if parent.is_dir() else []
        if runs and (runs[0] / "config.json").is_file():
            proc = kneas_train(["--resume", str(runs[0])])
            resumes += 1
        else:  # killed before the run folder was complete: nothing to resume, start again
            shutil.rmtree(out, ignore_errors=True)
            proc = kneas_train(["k-neas", "--scene", str(scene), *ARGS, "--output-dir", str(out)])
            fresh_starts += 1
        if kills < 6 and time.time() < budget:
            seen = _checkpoints(out)
            while proc.poll() is None and not (_checkpoints(out) - seen):
                time.sleep(0.02)
            if proc.poll() is None:
                time.sleep(rng.uniform(0.0, 0.12))
            if proc.poll() is None:
                proc.kill()
                proc.communicate(timeout=60)
                kills += 1
                continue
        text, _ = proc.communicate(timeout=300)
        assert proc.returncode == 0, text
        assert "Traceback" not in text
        break
    assert kills >= 3, kills
    run_dir = only_run_dir(parent)
    assert_same_metrics(run_dir, reference)
    print(f"kills {kills}, resumes {resumes}, fresh starts {fresh_starts}")
