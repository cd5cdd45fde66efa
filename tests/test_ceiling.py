"""benchmarks/ceiling.py: a run's model fitted to the true volume, and another representation's
ceiling measured from the same run folder (``--set``, ``--bounds truth``)."""

import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

from conftest import sphere_scene_file, write_run  # noqa: E402


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    folder = tmp_path_factory.mktemp("ceiling")
    return write_run(folder, "k-neas", sphere_scene_file(folder))


def test_the_ceiling_of_the_run_and_of_a_changed_representation(run_dir):
    import ceiling as c

    own = c.ceiling(run_dir, steps=30)
    assert own["K"] == len(json.loads((run_dir / "bounds.json").read_text())["alphas"]) and own["settings"] == [] and np.isfinite(own["ceiling_psnr3d"])
    assert own["top_bound"] == pytest.approx(0.1 + 0.75)  # the run's bounds.json: alpha_K + beta_K
    wider = c.ceiling(run_dir, steps=30, settings=["model.attenuation_options.hidden_dim=16", "model.num_materials=1"],
                      bounds_from="truth")
    assert wider["K"] == 1 and wider["bounds"] == "truth" and np.isfinite(wider["ceiling_psnr3d"])
    from kneas_method.data.naf import load_naf

    top = float(np.max(load_naf(sphere_scene_file(run_dir.parents[3])).image))
    assert wider["top_bound"] == pytest.approx(1.02 * top, rel=1e-3)  # the whole range of the truth is covered


@pytest.mark.parametrize("setting,words", [("model.num_materials", "KEY=VALUE"), ("nothing.here=1", "not a section"),
                                           ("model.num_materials=7", "add --bounds truth")])
def test_a_wrong_setting_is_one_line(run_dir, setting, words):
    import ceiling as c

    with pytest.raises(SystemExit, match=words):
        c.ceiling(run_dir, steps=1, settings=[setting])
