"""`kneas-data` command line: simulate, inspect, scenes; exit codes and one-line errors."""

import os
import pickle

import numpy as np
import pytest

from kneas_method.cli import data as cli
from kneas_method.data.naf import load_naf
from kneas_method.data.phantoms import PHANTOM_NAMES

TINY = ["--n-voxel", "12", "--voxel-mm", "20", "--n-detector", "12", "--views", "3", "--n-val", "2"]


def run(argv, capsys):
    with pytest.raises(SystemExit) as info:
        cli.main(argv)
    out = capsys.readouterr()
    return info.value.code, out.out, out.err


def test_simulate_phantom_tiny_and_inspect(tmp_path, capsys):
    out = tmp_path / "foot_3.pickle"
    code, stdout, _ = run(["simulate", "--phantom", "foot", "-o", str(out), *TINY, "--seed", "5"], capsys)
    assert code == 0 and out.is_file()
    assert "wrote" in stdout and str(out) in stdout.replace("\n", "")
    scene = load_naf(out)
    assert scene.train.projections.shape == (3, 12, 12) and scene.val.projections.shape == (2, 12, 12)
    assert scene.image.shape == (12, 12, 12) and scene.meta["phantom"] == "foot"
    assert scene.materials and scene.labels is not None and scene.membership is not None
    assert scene.train.projections.max() > 0

    png = tmp_path / "fig" / "foot.png"
    code, stdout, _ = run(["inspect", str(out), "--png", str(png)], capsys)
    assert code == 0
    assert "DSD 1500 mm" in stdout and "(12, 12, 12)" in stdout and "train: 3 views" in stdout
    assert png.is_file() and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    (tmp_path / "afile").write_text("x")  # a --png that cannot be written: refused before the report, in one line
    code, stdout, err = run(["inspect", str(out), "--png", str(tmp_path / "afile" / "foot.png")], capsys)
    assert code == 2 and "DSD" not in stdout and len(err.strip().splitlines()) == 1 and "choose another with --png" in " ".join(err.split())


def test_simulate_options_reach_the_scene(tmp_path, capsys):
    out = tmp_path / "p.pickle"
    code, _, _ = run(["simulate", "--phantom", "jaw", "-o", str(out), *TINY, "--mode", "parallel", "--total-angle", "360",
                      "--start-angle", "10", "--even-val-angles", "--noise", "--photons", "1000", "--detector-mm", "25"], capsys)
    assert code == 0
    s = load_naf(out)
    g = s.geometry.to_mm()
    assert s.geometry.mode == "parallel" and g["dDetector"][0] == pytest.approx(25.0)
    assert s.meta["totalAngle"] == 360 and s.meta["startAngle"] == 10 and s.meta["noise"] == 1 and s.meta["randomAngle"] is False
    np.testing.assert_allclose(np.degrees(s.train.angles), [10, 130, 250])
    np.testing.assert_allclose(np.degrees(s.val.angles), [100, 280])


def test_simulate_from_volume_with_conversion(tmp_path, capsys):
    hu = np.full((10, 8, 6), -1000.0, np.float32)
    hu[3:7, 2:6, 1:5] = 1000.0
    np.save(tmp_path / "ct.npy", (hu + 1024) / 2.0)  # raw = (HU + 1024) / 2
    out = tmp_path / "ct_3.pickle"
    code, stdout, _ = run(["simulate", "--volume", str(tmp_path / "ct.npy"), "-o", str(out), "--convert", "--rescale-slope", "2",
                           "--rescale-intercept", "-1024", "--voxel-mm", "10", "--n-detector", "16", "--views", "3", "--n-val", "1"], capsys)
    assert code == 0, stdout
    s = load_naf(out)
    assert s.image.shape == (10, 8, 6) and s.image.max() == pytest.approx(1.0) and s.image.min() == 0.0
    assert s.meta["convert"] is True and s.meta["rescale_slope"] == 2.0 and s.meta["rescale_intercept"] == -1024.0 and s.meta["normalize"] is True
    assert s.geometry.to_mm()["dVoxel"] == pytest.approx([10, 10, 10])
    assert s.train.projections.max() > 0
    # without --convert the negative HU volume is refused with a hint
    code, _, err = run(["simulate", "--volume", str(tmp_path / "ct.npy"), "-o", str(out), "--no-normalize",
                        "--n-detector", "8", "--views", "1", "--n-val", "1"], capsys)
    assert code == 0  # raw values are positive here: accepted as attenuation, unnormalised
    assert load_naf(out).image.max() == pytest.approx(1012.0) and load_naf(out).meta["normalize"] is False
    np.save(tmp_path / "hu.npy", hu)
    code, _, err = run(["simulate", "--volume", str(tmp_path / "hu.npy"), "-o", str(out)], capsys)
    assert code == 2 and err.startswith("error:") and "--convert" in err and "Traceback" not in err


def test_inspect_malicious_pickle_runs_nothing(tmp_path, capsys):
    marker = tmp_path / "pwned"

    class Evil:
        def __reduce__(self):
            return (os.system, (f"touch {marker}",))

    evil = tmp_path / "evil.pickle"
    evil.write_bytes(pickle.dumps({"DSD": Evil()}, protocol=2))
    code, stdout, err = run(["inspect", str(evil)], capsys)
    assert code == 2 and not marker.exists()
    assert "not a plain-data scene pickle" in err and "Traceback" not in err
    assert len(err.strip().splitlines()) <= 2  # one message (rich may soft-wrap nothing)


def test_user_errors_exit_2_with_one_line(tmp_path, capsys):
    cases = [
        ["simulate", "--phantom", "knee", "-o", str(tmp_path / "k.pickle")],
        ["inspect", str(tmp_path / "missing.pickle")],
        ["simulate", "--phantom", "foot", "-o", str(tmp_path / "x.pickle"), "--dsd-mm", "500"],
        ["simulate", "--phantom", "foot", "-o", str(tmp_path), *TINY],
        ["simulate", "--volume", str(tmp_path / "nothing.npy"), "-o", str(tmp_path / "x.pickle")],
    ]
    for argv in cases:
        code, _, err = run(argv, capsys)
        assert code == 2, argv
        assert err.startswith("error:") and "Traceback" not in err, err
    assert not (tmp_path / "k.pickle").exists() and not (tmp_path / "x.pickle").exists()


def test_argparse_usage_errors_exit_2(tmp_path, capsys):
    for argv, words in (([], "required"), (["simulate", "-o", "x.pickle"], "--phantom"),
                        (["simulate", "--phantom", "foot", "--volume", "v.npy", "-o", "x"], "not allowed with"),
                        (["simulate", "--phantom", "foot"], "-o"), (["frobnicate"], "invalid choice")):
        code, _, err = run(argv, capsys)
        assert code == 2 and err.startswith("error: kneas-data") and words in err and len(err.strip().splitlines()) == 1, err


def test_scenes_lists_every_builtin(capsys):
    code, stdout, _ = run(["scenes"], capsys)
    assert code == 0
    for name in PHANTOM_NAMES:
        assert name in stdout
    assert "soft tissue" in stdout


def test_console_script_is_wired():
    from importlib.metadata import entry_points

    eps = {e.name: e.value for e in entry_points(group="console_scripts")}
    assert eps.get("kneas-data") == "kneas_method.cli.data:main"


def test_value_ranges_print_without_negative_zero():
    assert cli._range(np.array([-0.0, 1.2693])) == "[0, 1.269]"
    assert cli._range(np.array([-0.25, 2.0])) == "[-0.25, 2]"
