"""Ctrl-C saves a checkpoint and exits 130; --resume ends with exactly the metrics of a straight run."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from kneas_method.data.naf import save_naf
from kneas_method.data.simulate import SimulationConfig, simulate_phantom

EXACT = ("psnr2d", "ssim2d", "psnr3d", "ssim3d", "psnr3d_ls", "ssim3d_ls", "psnr2d_per_view", "alphas", "betas",
         "num_materials", "steps", "parameters")


def kneas_train(args, **kw):
    cmd = [sys.executable, "-c", "from kneas_method.cli.train import main; main()", *args]
    env = dict(os.environ, PYTHONUNBUFFERED="1", OMP_NUM_THREADS="1")
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env, **kw)


def only_run_dir(parent: Path) -> Path:
    runs = [p for p in parent.iterdir() if p.is_dir()]
    assert len(runs) == 1, runs
    return runs[0]


@pytest.mark.parametrize("procedure", [
    [],  # the paper's: prior -> GMM -> model
    ["--procedure", "refine-classical", "--stages.classical-start.algorithm", "fdk", "--stages.warm-start.steps", "10",
     "--skip-stages", "correction", "smoothing", "materials-refit", "time-budget"],  # the cpu preset's procedure (FDK for speed)
], ids=["prior-bounds", "fdk-bounds-warm-start"])
def test_interrupt_then_resume_matches_straight_run(tmp_path, procedure):
    scene = tmp_path / "tinyfoot.pickle"
    save_naf(simulate_phantom("foot", SimulationConfig(n_voxel=16, voxel_mm=15.0, n_detector=16, n_train=4, n_val=4)), scene)
    common = ["k-neas", "--scene", str(scene), "--preset", "tiny", "--seed", "3", "--trainer.epochs", "12",
              "--trainer.checkpoint-every", "1", "--trainer.eval-every", "4", *procedure]

    # straight run
    straight = kneas_train([*common, "--output-dir", str(tmp_path / "a")])
    out_a, _ = straight.communicate(timeout=300)
    assert straight.returncode == 0, out_a
    metrics_a = json.loads((only_run_dir(tmp_path / "a" / "tinyfoot" / "k-neas") / "metrics.json").read_text())

    # interrupted run: SIGINT once the model stage has written its first checkpoint
    proc = kneas_train([*common, "--output-dir", str(tmp_path / "b")])
    parent = tmp_path / "b" / "tinyfoot" / "k-neas"
    deadline = time.time() + 300
    while time.time() < deadline and proc.poll() is None:
        if parent.is_dir() and any(parent.glob("*/checkpoints/step-*.ckpt")):
            break
        time.sleep(0.05)
    assert proc.poll() is None, "the run ended before it could be interrupted"
    proc.send_signal(signal.SIGINT)
    out_b, _ = proc.communicate(timeout=300)
    assert proc.returncode == 130, out_b
    run_dir = only_run_dir(parent)
    assert "interrupted at step" in out_b and f"kneas-train --resume {run_dir}" in out_b
    assert not (run_dir / "metrics.json").exists() and (run_dir / "bounds.json").is_file()
    step = int(out_b.split("interrupted at step ")[1].split(":")[0])
    assert 0 < step < 12 * 4

    # resume: bounds stage known to be done, ends with the straight run's numbers
    resumed = kneas_train(["--resume", str(run_dir)])
    out_c, _ = resumed.communicate(timeout=300)
    assert resumed.returncode == 0, out_c
    assert "bounds: already estimated for this run" in out_c and "model: resuming from" in out_c
    metrics_b = json.loads((run_dir / "metrics.json").read_text())
    for key in EXACT:
        assert metrics_b[key] == metrics_a[key], key
    # resuming a finished run does nothing
    again = kneas_train(["--resume", str(run_dir)])
    out_d, _ = again.communicate(timeout=300)
    assert again.returncode == 0 and "already complete" in out_d
