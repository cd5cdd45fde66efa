"""Every command line, every kind of mistake: one line ``error: ...`` naming the closest valid
choice, exit code 2, no traceback."""

import importlib

import pytest

CASES = [
    # (module, argv, words the one line must hold)
    ("train", ["k-nesa"], ["unknown method 'k-nesa'", "did you mean k-neas"]),
    ("train", ["k-neas", "--trainer.epoch", "3"], ["unknown option --trainer.epoch", "did you mean --trainer.epochs"]),
    ("train", ["k-neas", "--preset", "fast", "--dry-run"], ["--preset 'fast' is not one of auto, paper, cpu, tiny"]),
    ("train", ["k-neas", "--seed", "abc", "--dry-run"], ["--seed", "'abc'"]),
    ("train", ["k-neas", "--scene", "fooot", "--preset", "tiny", "--output-dir", "{tmp}"], ["'fooot'", "did you mean foot"]),
    ("train", ["--resume", "{tmp}/nowhere"], ["no config.json"]),
    ("train", ["k-neas", "--trainer.epochs", "0", "--dry-run"], ["--trainer.epochs must be a whole number >= 1, got 0"]),
    ("train", ["k-neas", "--preset", "paper", "--trainer.prior-epochs", "0", "--dry-run"], ["--trainer.prior-epochs", "got 0"]),
    ("train", ["k-neas", "--model.num-samples", "0", "--dry-run"], ["--model.num-samples must be a whole number >= 1, got 0"]),
    ("train", ["k-neas", "--trainer.lr", "-1", "--dry-run"], ["--trainer.lr must be a number > 0, got -1.0"]),
    ("train", ["naf", "--trainer.eval-chunk", "0", "--dry-run"], ["--trainer.eval-chunk must be a whole number >= 1"]),
    ("train", ["k-neas", "--datamanager.num-object-rays", "0", "--datamanager.num-air-rays", "0", "--dry-run"],
     ["both 0", "at least one ray"]),
    ("train", ["sart", "--method", "k-neas", "--dry-run"], ["the method is the subcommand", "drop --method"]),
    ("eval", ["{tmp}/nowhere"], ["does not exist"]),
    ("eval", ["{tmp}"], ["has no config.json", "not a kneas run folder"]),
    ("eval", ["--scnee", "foot"], ["unrecognized arguments: --scnee", "did you mean --scene"]),
    ("eval", ["{tmp}", "--figure-views", "-2"], ["--figure-views must be 0 (none) or more, got -2"]),
    ("eval", ["--checkpoint", "{tmp}/nope.ckpt"], ["--checkpoint", "nope.ckpt does not exist"]),
    ("eval", ["{tmp}/cli.log"], ["cli.log is a file, not a run folder or a checkpoint"]),
    ("export", ["figures", "{tmp}/cli.log"], ["cli.log is a file, not a run folder or a checkpoint"]),
    ("export", ["mesk", "run"], ["invalid choice: 'mesk'", "did you mean mesh"]),
    ("export", ["mesh", "run", "--resolutoin", "3"], ["--resolutoin", "did you mean --resolution"]),
    ("export", ["mesh", "run", "--chunk", "0"], ["--chunk must be at least 1", "got 0"]),
    ("export", ["figures", "run", "--views", "-1"], ["--views must be 0 (all) or more, got -1"]),
    ("train", ["sart", "--reconstruction.iterations", "0", "--output-dir", "{tmp}/out"],
     ["--reconstruction.iterations must be a whole number >= 1, got 0"]),
    ("train", ["os-sart", "--reconstruction.subsets", "0", "--output-dir", "{tmp}/out"], ["--reconstruction.subsets", "got 0"]),
    ("train", ["os-sart", "--reconstruction.relaxation", "0", "--output-dir", "{tmp}/out"], ["--reconstruction.relaxation must be a number > 0"]),
    ("train", ["k-neas", "--reconstruction.iterations", "0", "--dry-run"], ["--reconstruction.iterations", "got 0"]),
    ("train", ["k-neas", "--model.selector", "hard", "--output-dir", "{tmp}/out"], ["hard selector works only with 2 materials", "--num-materials 2"]),
    ("data", ["simulte"], ["invalid choice: 'simulte'", "did you mean simulate"]),
    ("data", ["simulate", "--phantom", "fot", "-o", "{tmp}/x.pickle"], ["unknown built-in phantom 'fot'", "did you mean foot"]),
    ("data", ["inspect", "{tmp}/missing.pickle"], ["missing.pickle"]),
    ("data", ["export", "nosuch", "--rtk", "{tmp}/rtk"], ["SCENE 'nosuch' is neither an existing file nor a built-in scene"]),
    ("data", ["simulate", "--phantom", "foot", "-o", "{tmp}/x.txt"], ["-o", "x.txt", "ending in .pickle", "x.pickle"]),
    ("bench", ["tabel1"], ["unknown table 'tabel1'", "did you mean table1"]),
    ("bench", ["table1", "--sedes", "3"], ["unknown option --sedes", "did you mean --seeds"]),
    ("bench", ["grid", "--methods", "k-nes", "--dry-run"], ["k-nes"]),
]


@pytest.mark.parametrize("module,argv,words", CASES, ids=[" ".join([c[0], *c[1]]) for c in CASES])
def test_mistakes_are_one_line(module, argv, words, tmp_path, capsys):
    cli = importlib.import_module(f"kneas_method.cli.{module}")
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    (tmp_path / "cli.log").write_text("a log, not a run\n")
    with pytest.raises(SystemExit) as exc:
        cli.main(argv)
    err = capsys.readouterr().err.strip()
    assert exc.value.code == 2, err
    assert err.startswith("error:") and len(err.splitlines()) == 1 and "Traceback" not in err, err
    for word in words:
        assert word in err, (word, err)
    assert not (tmp_path / "out").exists()  # refused before any run folder is made


def test_a_wrong_scene_is_refused_before_any_work_or_output(tmp_path, capsys):
    """The error is the whole answer: no preset notes before it, no run folder made."""
    cli = importlib.import_module("kneas_method.cli.train")
    with pytest.raises(SystemExit) as exc:
        cli.main(["k-neas", "--scene", str(tmp_path / "missing.pickle"), "--output-dir", str(tmp_path / "out")])
    out, err = capsys.readouterr()
    assert exc.value.code == 2
    assert out == "" and err.startswith("error: --scene") and "missing.pickle" in err, (out, err)
    assert not (tmp_path / "out").exists()


def test_a_settings_error_found_in_the_run_leaves_no_run_folder(tmp_path, capsys):
    """A bounds file with the wrong K is found once the run has started (its folder made): the
    one-line error, and no folder left behind that --resume or kneas-eval would point into."""
    cli = importlib.import_module("kneas_method.cli.train")
    bounds = tmp_path / "b3.json"
    bounds.write_text('{"alphas": [1, 2, 3], "betas": [0, 0.1, 0.2]}')
    out = tmp_path / "out"
    out.mkdir()
    with pytest.raises(SystemExit) as exc:
        cli.main(["neas-2m", "--preset", "tiny", "--bounds", str(bounds), "--output-dir", str(out)])
    err = capsys.readouterr().err.strip()
    assert exc.value.code == 2 and err.startswith("error: --bounds") and "3 materials" in err and "K = 2" in err, err
    assert list(out.iterdir()) == []
