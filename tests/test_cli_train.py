import dataclasses
import json
import re
import subprocess
import sys

import pytest

from kneas_method import registry
from kneas_method.cli import train as cli
from kneas_method.config import to_dict


def run_main(argv, capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main(argv)
    out = capsys.readouterr()
    return exc.value.code, out.out, out.err


def test_console_script_paper_parameter_count():
    # the installed console script, end to end
    proc = subprocess.run(["kneas-train", "neas-1m", "--dry-run", "--preset", "paper"], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "parameters: 12,168,411" in proc.stdout.splitlines()
    assert "preset 'paper' as requested" in proc.stdout


def test_k4_shared_adds_exactly_17030(capsys):
    code, out, _ = run_main(["k-neas", "--num-materials", "4", "--dry-run", "--preset", "paper"], capsys)
    assert code == 0
    lines = [l for l in out.splitlines() if l.startswith("parameters: ")]
    assert lines == ["parameters: 12,185,441"]
    assert int(lines[0].split()[1].replace(",", "")) - 12_168_411 == 17_030


def test_dry_run_tiny_and_auto_reason(capsys, monkeypatch):
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    code, out, _ = run_main(["naf", "--dry-run", "--preset", "tiny"], capsys)
    assert code == 0 and re.search(r"^parameters: [\d,]+$", out, re.M)
    monkeypatch.setattr(cli.presets, "TABLE", {**cli.presets.TABLE, "cpu": cli.presets.TABLE["tiny"]})  # keep it small
    code, out, _ = run_main(["k-neas", "--dry-run"], capsys)
    assert code == 0 and "preset 'cpu' chosen automatically: no CUDA GPU" in out


def test_user_errors_are_one_line(capsys):
    code, out, err = run_main(["neas-2m", "--num-materials", "3", "--dry-run", "--preset", "tiny"], capsys)
    assert code == 2 and err.strip().startswith("error:") and "only with 2 materials" in err and "Traceback" not in err
    code, _, err = run_main(["k-neas", "--dry-run", "--preset", "tiny", "--model.selector", "nope"], capsys)
    assert code == 2 and "no selector named 'nope'" in err
    code, _, err = run_main(["--config", "/nonexistent/config.json"], capsys)
    assert code == 2 and "does not exist" in err


def test_help_lists_registered_methods(capsys):
    code, out, _ = run_main(["--help"], capsys)
    assert code == 0
    for name in ("neas-1m", "neas-2m", "kselector", "kselector-floater", "kselector-shared", "k-neas", "naf"):
        assert name in out
    assert registry.load("methods", "k-neas").description.split(":")[0] in out


def test_training_branch_gets_resolved_config(capsys, monkeypatch):
    got = []
    monkeypatch.setattr(cli, "train", lambda config: got.append(config) or 0)
    code, _, _ = run_main(["kselector", "--preset", "tiny", "--scene", "jaw", "--views", "10", "--seed", "3", "--model.num-samples", "40"], capsys)
    assert code == 0 and len(got) == 1
    c = got[0]
    assert (c.method, c.scene, c.views, c.seed, c.preset) == ("kselector", "jaw", 10, 3, "tiny")
    assert c.model.num_samples == 40 and c.model.num_eval_samples == 16  # user wins, preset fills the rest


def test_config_file_reruns_saved_config(tmp_path, capsys, monkeypatch):
    got = []
    monkeypatch.setattr(cli, "train", lambda config: got.append(config) or 0)
    run_main(["neas-2m", "--preset", "tiny", "--seed", "11", "--model.s-init", "5"], capsys)
    path = tmp_path / "config.json"
    path.write_text(json.dumps(to_dict(got[0])))
    code, _, _ = run_main(["--config", str(path)], capsys)
    assert code == 0 and got[1] == got[0]
    code, _, _ = run_main(["--config", str(path), "--seed", "12"], capsys)
    assert code == 0 and got[2] == dataclasses.replace(got[0], seed=12)
