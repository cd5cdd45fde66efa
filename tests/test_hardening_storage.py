"""Storage failures, foreign checkpoints and bad numbers, attacked through kneas-train / the Trainer."""

import dataclasses
import errno
import json

import pytest
import torch

from kneas_method.engine import checkpoint as ckpt_mod
from kneas_method.engine import run_dir as run_dir_mod
from kneas_method.engine.checkpoint import list_checkpoints, load_checkpoint_file, save_checkpoint
from kneas_method.errors import KneasError
from conftest import run, run_dir_of

ARGS = ["--preset", "tiny", "--seed", "1", "--trainer.epochs", "3", "--trainer.checkpoint-every", "1",
        "--trainer.eval-every", "0"]


def test_full_output_folder_reported_before_training(tiny_scene, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(run_dir_mod.shutil, "disk_usage", lambda p: type("U", (), {"free": 5 << 20})())
    code, out, err = run(["k-neas", "--scene", str(tiny_scene), *ARGS, "--output-dir", str(tmp_path / "o")], capsys)
    assert code == 2 and "MiB free" in err and "--output-dir" in err and "Traceback" not in err
    assert "prior: training" not in out and not list(tmp_path.rglob("*.ckpt"))


def test_unwritable_output_folder_reported_before_training(tiny_scene, tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    code, out, err = run(["k-neas", "--scene", str(tiny_scene), *ARGS, "--output-dir", str(blocker / "o")], capsys)
    assert code == 2 and f"{blocker} is a file, not a folder" in " ".join(err.split()) and "--output-dir" in err
    assert "prior: training" not in out


def test_disk_full_mid_run_keeps_last_good_checkpoint_and_says_where(tiny_scene, tmp_path, capsys, monkeypatch):
    real = torch.save
    calls = {"n": 0}

    def full_disk(obj, f, *a, **k):
        calls["n"] += 1
        if calls["n"] >= 3:  # the 3rd (last) checkpoint write runs out of space half way
            f.write(b"partial")
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(obj, f, *a, **k)

    monkeypatch.setattr(ckpt_mod.torch, "save", full_disk)
    out_dir = tmp_path / "o"
    code, out, err = run(["k-neas", "--scene", str(tiny_scene), *ARGS, "--output-dir", str(out_dir),
                          "--bounds-source", "wide"], capsys)
    monkeypatch.setattr(ckpt_mod.torch, "save", real)
    assert code == 2 and "Traceback" not in err, err
    assert "No space left on device" in err and "last good checkpoint is" in err and "--resume" in err
    run_dir = run_dir_of(out)
    good = list_checkpoints(run_dir / "checkpoints")
    assert [p.name for p in good] == ["step-00000004.ckpt", "step-00000008.ckpt"]
    assert str(good[-1]) in err.replace("\n", "")
    assert not [p for p in (run_dir / "checkpoints").iterdir() if p.name.endswith(".tmp")]
    assert load_checkpoint_file(good[-1], method="k-neas")["step"] == 8
    # space freed: the run resumes from the last good checkpoint and finishes
    code, out, err = run(["--resume", str(run_dir)], capsys)
    assert code == 0, err
    assert f"resuming from {good[-1]}" in out.replace("\n", "")
    assert json.loads((run_dir / "metrics.json").read_text())["steps"] == 12


def _finished_run_without_metrics(tiny_scene, tmp_path, capsys):
    """A one-epoch k-neas run whose metrics.json is removed (so --resume has work to do)."""
    code, out, err = run(["k-neas", "--scene", str(tiny_scene), *ARGS, "--trainer.epochs", "1",
                          "--bounds-source", "wide", "--output-dir", str(tmp_path / "o")], capsys)
    assert code == 0, err
    run_dir = run_dir_of(out)
    (run_dir / "metrics.json").unlink()
    return run_dir


def test_resume_into_full_folder_reported_before_training(tiny_scene, tmp_path, capsys, monkeypatch):
    run_dir = _finished_run_without_metrics(tiny_scene, tmp_path, capsys)
    monkeypatch.setattr(run_dir_mod.shutil, "disk_usage", lambda p: type("U", (), {"free": 1 << 20})())
    code, out, err = run(["--resume", str(run_dir)], capsys)
    assert code == 2 and "MiB free" in err and "resuming run" not in out


def test_foreign_checkpoints_in_a_run_folder_refused(tiny_scene, tmp_path, capsys, monkeypatch):
    run_dir = _finished_run_without_metrics(tiny_scene, tmp_path, capsys)
    ck = run_dir / "checkpoints"
    state = torch.load(list_checkpoints(ck)[-1], weights_only=True)
    # another method's checkpoint, newer than ours: refused, naming both methods, never skipped silently
    save_checkpoint(ck, {**state, "step": 99, "method": "naf"}, keep=10)
    code, out, err = run(["--resume", str(run_dir)], capsys)
    assert code == 2 and "'naf'" in err and "'k-neas'" in err
    # an incompatible format version: names both versions
    blob = {**state, "step": 99, "format": 7, "kneas_version": "9.9"}
    torch.save(blob, ck / "step-00000099.ckpt")
    code, out, err = run(["--resume", str(run_dir)], capsys)
    assert code == 2 and "format 7" in err and "9.9" in err and "reads format 1" in err


def _trainer(tiny_scene, tmp_path):
    from kneas_method import presets, registry
    from kneas_method.data.naf import load_naf
    from kneas_method.engine.trainer import Trainer

    cfg = presets.resolve(dataclasses.replace(registry.load("methods", "neas-1m").config, method="neas-1m", preset="tiny"))
    cfg = dataclasses.replace(cfg, trainer=dataclasses.replace(cfg.trainer, epochs=3, eval_every=0, checkpoint_every=1))
    (tmp_path / "checkpoints").mkdir()
    return Trainer(cfg, load_naf(tiny_scene), tmp_path, epochs=3, device="cpu", label="model")


def _all_finite(folder):
    for path in list_checkpoints(folder):
        state = load_checkpoint_file(path)
        for v in state["model"].values():
            assert torch.isfinite(v).all(), path


def test_nan_injected_into_the_model_mid_training(tiny_scene, tmp_path):
    trainer = _trainer(tiny_scene, tmp_path)

    def poison(trainer):
        if trainer.step == 6:
            with torch.no_grad():
                next(trainer.model.parameters()).fill_(float("nan"))

    with pytest.raises(KneasError, match="non-finite losses in a row.*last good checkpoint is .*step-00000004.ckpt"):
        trainer.train(step_hooks=[poison])
    assert [p.name for p in list_checkpoints(tmp_path / "checkpoints")] == ["step-00000004.ckpt"]
    _all_finite(tmp_path / "checkpoints")


def test_nan_injected_at_the_last_step_is_not_a_finished_run(tiny_scene, tmp_path):
    trainer = _trainer(tiny_scene, tmp_path)

    def poison(trainer):
        if trainer.step == trainer.total_steps:
            with torch.no_grad():
                next(trainer.model.parameters()).fill_(float("inf"))

    with pytest.raises(KneasError, match="non-finite parameters.*last good checkpoint is .*step-00000008.ckpt"):
        trainer.train(step_hooks=[poison])
    assert not trainer.complete
    _all_finite(tmp_path / "checkpoints")
    # nothing on disk claims the stage is complete, so a resume redoes the last epoch from good weights
    state = load_checkpoint_file(list_checkpoints(tmp_path / "checkpoints")[-1])
    assert state["step"] == 8 and state["extra"]["complete"] is False


def test_nan_injected_into_the_projections_during_training(tiny_scene, tmp_path):
    trainer = _trainer(tiny_scene, tmp_path)
    trainer.datamanager.train_projections[1:] = float("nan")  # views 1..3 poisoned after loading
    with pytest.raises(KneasError, match="non-finite losses in a row"):
        trainer.train()
    assert trainer.bad_steps and all(torch.isfinite(p).all() for p in trainer.model.parameters())
    _all_finite(tmp_path / "checkpoints")
