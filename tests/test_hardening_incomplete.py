"""kneas-eval and kneas-export on incomplete or damaged run folders say what is missing."""

import shutil

import pytest

from kneas_method.cli import eval as eval_cli
from kneas_method.cli import export as export_cli
from conftest import foot_scene_file, write_run


def _exit(main, argv):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    return exc.value.code


@pytest.fixture()
def run_dir(tmp_path):
    return write_run(tmp_path, "k-neas", foot_scene_file(tmp_path), num_materials=2)


COMMANDS = [
    (eval_cli.main, []),
    (export_cli.main, ["volume"]),
    (export_cli.main, ["mesh"]),
    (export_cli.main, ["figures"]),
]


@pytest.mark.parametrize("main,prefix", COMMANDS)
def test_no_checkpoint_is_named(run_dir, capsys, main, prefix):
    shutil.rmtree(run_dir / "checkpoints")
    (run_dir / "checkpoints").mkdir()
    assert _exit(main, prefix + [str(run_dir)]) == 2
    err = capsys.readouterr().err  # a finished run (metrics.json) is trained again from its config, not resumed
    assert "no checkpoint" in err and f"kneas-train --config {run_dir}/config.json" in err and "Traceback" not in err
    (run_dir / "metrics.json").unlink()  # an unfinished run is resumed
    assert _exit(main, prefix + [str(run_dir)]) == 2
    err = capsys.readouterr().err
    assert "no checkpoint" in err and "--resume" in err and "Traceback" not in err


@pytest.mark.parametrize("main,prefix", COMMANDS[:2])
def test_only_damaged_checkpoints_are_named(run_dir, capsys, main, prefix):
    for ckpt in (run_dir / "checkpoints").glob("*.ckpt"):
        data = ckpt.read_bytes()
        ckpt.write_bytes(data[: len(data) // 3])
    assert _exit(main, prefix + [str(run_dir)]) == 2
    err = capsys.readouterr().err
    assert "damaged" in err and f"kneas-train --config {run_dir}/config.json" in err and "Traceback" not in err
    (run_dir / "metrics.json").unlink()
    assert _exit(main, prefix + [str(run_dir)]) == 2
    err = capsys.readouterr().err
    assert "damaged" in err and "--resume" in err and "Traceback" not in err


@pytest.mark.parametrize("main,prefix", COMMANDS[:2])
def test_missing_config_is_named(run_dir, capsys, main, prefix):
    (run_dir / "config.json").unlink()
    assert _exit(main, prefix + [str(run_dir)]) == 2
    err = capsys.readouterr().err
    assert "config.json" in err and "Traceback" not in err
