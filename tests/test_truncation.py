"""A scan whose object goes on beyond the box along the rotation axis is named in a warning (data.truncation)."""

import dataclasses

import numpy as np
import pytest

from kneas_method.data.naf import load_naf, save_naf
from kneas_method.data.scene import Views
from kneas_method.data.truncation import ROW_OBJECT_SHARE, axial_truncation, truncation_warning

from conftest import run, simulated_foot


def test_axial_truncation_counts_the_views_whose_end_rows_see_the_object():
    p = np.zeros((4, 6, 20), dtype=np.float32)
    p[:, 2:4, 5:15] = 0.3  # the object in the middle rows only
    assert axial_truncation(p, 0.0) == 0.0
    p[:2, 0, 3:17] = 0.05  # two views' first row crosses it
    assert axial_truncation(p, 0.0) == 0.5
    assert axial_truncation(p, 0.1) == 0.0  # below the air threshold: noise in air
    p[2, -1, : int(ROW_OBJECT_SHARE * 20) - 1] = 0.05  # a few pixels of the last row: not the object going on
    assert axial_truncation(p, 0.0) == 0.5


def test_a_truncated_scan_is_named_in_a_warning_and_still_reconstructed(tmp_path, capsys):
    path = simulated_foot(tmp_path, "foot", 16, 15.0, n_train=4)
    scene = load_naf(path)
    assert truncation_warning(scene) is None
    cut = scene.train.projections.copy()
    cut[:, 0, :] = cut[:, 0, :] + 0.02  # tissue crosses the first row in every view
    truncated = dataclasses.replace(scene, train=Views(scene.train.angles, cut))
    assert "4 of 4 training views" in truncation_warning(truncated)
    save_naf(truncated, tmp_path / "long.pickle")
    code, out, _ = run(["fdk", "--scene", str(tmp_path / "long.pickle"), "--preset", "tiny", "--output-dir", str(tmp_path / "o")], capsys)
    assert code == 0 and "warning: the object reaches the detector's first or last row in 4 of 4 training views" in out
    code, out, _ = run(["fdk", "--scene", str(path), "--preset", "tiny", "--output-dir", str(tmp_path / "o")], capsys)
    assert code == 0 and "warning: the object reaches" not in out
    from kneas_method.cli import data as data_cli

    for scene_path, warned in ((tmp_path / "long.pickle", True), (path, False)):  # kneas-data inspect says it too
        with pytest.raises(SystemExit) as exc:
            data_cli.main(["inspect", str(scene_path)])
        out = capsys.readouterr().out
        assert exc.value.code == 0 and ("warning: the object reaches" in out) == warned
