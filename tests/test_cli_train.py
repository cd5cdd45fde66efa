import dataclasses
import json
import re
import subprocess

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


def test_dry_run_says_what_each_further_material_costs(capsys):
    # K comes from the data: the count is at the default K = 3, plus the exact cost of one more material
    code, out, _ = run_main(["k-neas", "--dry-run", "--preset", "paper"], capsys)
    assert code == 0
    assert "parameters: 12,185,441" not in out
    k3 = int(re.search(r"^parameters: ([\d,]+)$", out, re.M).group(1).replace(",", ""))
    extra = re.search(r"^parameters per further material: \+([\d,]+) \(the count above is at K = 3", out, re.M)
    assert extra and k3 + int(extra.group(1).replace(",", "")) == 12_185_441  # the K = 4 count above


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
    code, _, _ = run_main(["--config", str(path), "neas-2m", "--seed", "13"], capsys)  # its own method, named
    assert code == 0 and got[3] == dataclasses.replace(got[0], seed=13)
    # another method: the file's settings would be dropped without a word; refused in one line instead
    code, _, err = run_main(["--config", str(path), "naf"], capsys)
    assert code == 2 and len(got) == 4 and len(err.strip().splitlines()) == 1
    assert "holds neas-2m settings" in err and "drop the method name 'naf'" in err, err


def _saved_run(tmp_path, capsys, monkeypatch, method="k-neas"):
    """A run folder holding only the config.json ``kneas-train`` would write (resolved, tiny)."""
    got = []
    monkeypatch.setattr(cli, "train", lambda config: got.append(config) or 0)
    run_main([method, "--preset", "tiny", "--trainer.epochs", "2"], capsys)
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text(json.dumps(to_dict(got[0])))
    return run, got


def test_resume_applies_safe_flags_and_refuses_the_others(tmp_path, capsys, monkeypatch):
    run, got = _saved_run(tmp_path, capsys, monkeypatch)
    code, _, err = run_main(["--resume", str(run)], capsys)
    assert code == 0 and got[-1] == dataclasses.replace(got[0], resume=str(run))
    # settings that do not change what is trained are applied
    code, _, err = run_main(["--resume", str(run), "--device", "cpu", "--trainer.eval-chunk", "512"], capsys)
    assert code == 0, err
    assert got[-1].device == "cpu" and got[-1].trainer.eval_chunk == 512 and got[-1].resume == str(run)
    # the others are refused in one line that names them and the way to start a new run with them
    calls = len(got)
    code, _, err = run_main(["--resume", str(run), "--trainer.epochs", "3", "--seed", "4"], capsys)
    assert code == 2 and len(got) == calls and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert "trainer.epochs (2 -> 3)" in err and "seed (0 -> 4)" in err
    assert f"kneas-train --config {run / 'config.json'}" in err and "--trainer.epochs 3" in err
    # a method name other than the run's is a mistake too
    code, _, err = run_main(["--resume", str(run), "naf"], capsys)
    assert code == 2 and "k-neas run" in err


def test_choices_are_listed_by_help_and_checked(tmp_path, capsys):
    code, out, _ = run_main(["k-neas", "--help"], capsys)
    assert code == 0
    for flag, choices in (("--stages.classical-start.algorithm", "{fdk,sart,os-sart,cgls,asd-pocs}"),
                          ("--stages.smoothing.rule", "{sure,sure-gaussian}"),
                          ("--preset", "{auto,paper,cpu,tiny}"), ("--bounds-method", "{gmm,quantile,bayes}"),
                          ("--bounds-k-rule", "{None,bic,bic-valleys,peaks}"), ("--model.quadrature", "{None,bins,voxel-planes}")):
        assert re.search(rf"{re.escape(flag)} {re.escape(choices)}", out), flag
    bad = tmp_path / "bad.json"
    data = to_dict(registry.load("methods", "k-neas").config)
    data["stages"]["classical_start"]["algorithm"] = "ground-truth"
    bad.write_text(json.dumps(data))
    code, _, err = run_main(["--config", str(bad), "--dry-run"], capsys)
    assert code == 2 and "stages.classical_start.algorithm" in err and "'ground-truth'" in err and "asd-pocs" in err


def test_older_fdk_config_still_loads(tmp_path):
    """FDK runs of kneas 0.1 wrote the neural settings too (and ``reconstructor``); they still load."""
    from kneas_method.engine.loading import read_run_config
    from kneas_method.methods import ClassicalConfig

    old = to_dict(registry.load("methods", "neas-1m").config)
    old.update(method="fdk", reconstructor="fdk", fdk_filter="hann")
    old["model"]["reference"] = False
    (tmp_path / "config.json").write_text(json.dumps(old))
    config = read_run_config(tmp_path)
    assert isinstance(config, ClassicalConfig) and config.algorithm == "fdk" and config.reconstruction.filter == "hann"
