import os

import pytest
import torch

from kneas_method.engine.checkpoint import (
    list_checkpoints,
    load_checkpoint_file,
    load_latest_checkpoint,
    save_checkpoint,
)
from kneas_method.errors import CheckpointError


def state(step, method="k-neas"):
    return {"step": step, "method": method, "model": {"w": torch.full((3,), float(step))}}


def test_save_prunes_and_loads_newest(tmp_path):
    for s in (1, 2, 3):
        save_checkpoint(tmp_path, state(s), keep=2)
    assert [p.name for p in list_checkpoints(tmp_path)] == ["step-00000002.ckpt", "step-00000003.ckpt"]
    loaded, path, skipped = load_latest_checkpoint(tmp_path, method="k-neas")
    assert loaded["step"] == 3 and torch.equal(loaded["model"]["w"], torch.full((3,), 3.0)) and not skipped
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]


def test_damaged_newest_falls_back(tmp_path):
    save_checkpoint(tmp_path, state(1))
    newest = save_checkpoint(tmp_path, state(2))
    data = newest.read_bytes()
    newest.write_bytes(data[: len(data) // 2])  # a torn write
    loaded, path, skipped = load_latest_checkpoint(tmp_path)
    assert loaded["step"] == 1 and len(skipped) == 1


def test_foreign_method_refused(tmp_path):
    save_checkpoint(tmp_path, state(1, method="naf"))
    with pytest.raises(CheckpointError, match="'naf'.*'k-neas'"):
        load_latest_checkpoint(tmp_path, method="k-neas")


def test_format_version_refused(tmp_path):
    path = save_checkpoint(tmp_path, state(1))
    blob = torch.load(path, weights_only=True)
    blob["format"] = 999
    torch.save(blob, path)
    with pytest.raises(CheckpointError, match="format 999"):
        load_checkpoint_file(path)


class Payload:
    def __reduce__(self):
        return (os.system, ("touch PWNED_CHECKPOINT",))


def test_pickle_payload_is_refused_and_runs_nothing(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    path = tmp_path / "step-00000001.ckpt"
    torch.save({"format": 1, "model": {}, "evil": Payload()}, path)
    with pytest.raises(CheckpointError, match="cannot be loaded safely") as info:
        load_checkpoint_file(path)
    assert not (tmp_path / "PWNED_CHECKPOINT").exists()
    reason = str(info.value).split("(", 1)[1].rsplit(");", 1)[0]
    assert len(reason) <= 160 and "\n" not in str(info.value)  # torch's long explanation cut to its first sentence, whole


def test_nothing_to_resume(tmp_path):
    with pytest.raises(CheckpointError, match="no complete checkpoint"):
        load_latest_checkpoint(tmp_path / "missing")
