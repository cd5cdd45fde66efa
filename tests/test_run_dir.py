import json

import numpy as np
import pytest

from kneas_method.engine import figures, run_dir
from kneas_method.errors import KneasError


def test_run_dir_layout_and_unique(tmp_path):
    a = run_dir.create_run_dir(tmp_path, "foot", "k-neas")
    b = run_dir.create_run_dir(tmp_path, "foot", "k-neas")
    assert a != b and a.parent == tmp_path / "foot" / "k-neas"
    assert (a / "figures").is_dir() and not (a / "checkpoints").exists()  # made by the first checkpoint


def test_first_checkpoint_makes_its_folder(tmp_path):
    from kneas_method.engine.checkpoint import list_checkpoints, save_checkpoint

    run = run_dir.create_run_dir(tmp_path, "foot", "k-neas")
    path = save_checkpoint(run / "checkpoints", {"step": 7, "method": "k-neas"})
    assert path.parent == run / "checkpoints" and list_checkpoints(run / "checkpoints") == [path]


def test_unwritable_output_reported_before_training(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    with pytest.raises(KneasError, match=r"/file is a file, not a folder; choose another with --output-dir"):
        run_dir.create_run_dir(blocker / "out", "foot", "k-neas")
    with pytest.raises(KneasError, match=r"/file is a file, not a folder; choose another with -o"):
        run_dir.check_writable(blocker, flag="-o")


def test_full_disk_reported(tmp_path):
    with pytest.raises(KneasError, match="MiB free"):
        run_dir.check_writable(tmp_path, needed_bytes=1 << 62)


def test_write_json_is_strict_and_atomic(tmp_path):
    path = run_dir.write_json(tmp_path / "m.json", {"psnr": float("inf"), "v": np.float32(1.5), "a": np.arange(2)})
    data = json.loads(path.read_text())
    assert data == {"psnr": "inf", "v": 1.5, "a": [0, 1]}
    assert [p.name for p in tmp_path.iterdir()] == ["m.json"]


def test_run_files_get_the_permissions_of_a_plain_write(tmp_path):
    """Atomic writes go through an owner-only temp file; the result must not stay owner-only
    (metrics and configs hidden from the other users of a shared machine)."""
    import os

    old = os.umask(0o022)
    try:
        path = run_dir.write_json(tmp_path / "metrics.json", {"psnr3d": 1.0})
        plain = tmp_path / "plain.json"
        plain.write_text("{}")
    finally:
        os.umask(old)
    assert path.stat().st_mode & 0o777 == plain.stat().st_mode & 0o777 == 0o644


def test_read_json_errors(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text("{nope")
    with pytest.raises(KneasError, match="not valid JSON"):
        run_dir.read_json(bad, "config")
    with pytest.raises(KneasError, match="does not exist"):
        run_dir.read_json(tmp_path / "none.json", "config")


def test_figures_write_pngs(tmp_path):
    rng = np.random.default_rng(0)
    outs = [
        figures.plot_loss_curves({"int": [(1, 1.0), (2, 0.5)], "reg": [(1, 0.1), (2, float("nan"))]}, tmp_path / "l.png"),
        figures.plot_projection_comparison(rng.random((8, 9)), rng.random((8, 9)), tmp_path / "p.png"),
        figures.plot_slice_comparison(rng.random((6, 7, 8)), rng.random((6, 7, 8)), tmp_path / "s.png"),
        figures.plot_slice_comparison(rng.random((6, 7, 8)), None, tmp_path / "s2.png"),
    ]
    for p in outs:
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_cli_error_keeps_brackets(capsys):
    from kneas_method.cli.common import run_cli
    from kneas_method.errors import missing_optional

    def body():
        raise missing_optional("open3d", "mesh", "mesh export")

    with pytest.raises(SystemExit) as exit_info:
        run_cli(body)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert "pip install 'kneas[mesh]'" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
