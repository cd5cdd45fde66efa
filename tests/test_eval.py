"""`kneas-eval` on hand-written tiny run folders (a tiny built-in foot scene with exact membership)."""

import json

import numpy as np
import pytest

from kneas_method.cli import eval as eval_cli
from kneas_method.errors import KneasError
from conftest import foot_scene_file, write_run


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("evalruns")
    return write_run(root, "k-neas", foot_scene_file(root), num_materials=2)


def _cli(argv):
    with pytest.raises(SystemExit) as exc:
        eval_cli.main(argv)
    return exc.value.code


def test_eval_writes_metrics_and_figures(run_dir, capsys):
    assert _cli([str(run_dir), "--figure-views", "1"]) == 0
    text = capsys.readouterr().out
    outs = sorted(run_dir.glob("eval-*"))
    assert len(outs) == 1
    m = json.loads((outs[0] / "metrics.json").read_text())
    assert m["method"] == "k-neas" and m["step"] == 7 and m["scene"] == "foot_tiny"
    # 2D over all held-out views, 3D exact and least-squares variants
    assert m["n_views"] == 3 and len(m["psnr2d_per_view"]) == 3 and len(m["ssim2d_per_view"]) == 3
    for key in ("psnr2d", "ssim2d", "psnr3d", "ssim3d", "psnr3d_ls", "ssim3d_ls", "ls_scale"):
        assert isinstance(m[key], float)
    assert m["psnr2d"] == pytest.approx(np.mean(m["psnr2d_per_view"]))
    # per-material surface and label metrics; K = 2 model, M = 3 ground-truth materials
    mat = m["materials"]
    assert len(mat["matching"]) == 2 and set(mat["materials"]) == {"soft tissue", "marrow", "cortical bone"}
    assert np.array(mat["dice_matrix"]).shape == (2, 3)
    for entry in mat["materials"].values():
        assert 0.0 <= entry["dice"] <= 1.0
        if entry["predicted_materials"] and entry["pred_surface_points"]:
            assert entry["chamfer_mm"] >= 0 and 0 <= entry["fscore"] <= 1
    assert "material matching" in text and "2D PSNR" in text
    assert mat["shells_relabelled"] is True and "partial-volume shells" in mat["definition"]
    figs = sorted(p.name for p in (outs[0] / "figures").glob("*.png"))
    assert "slices.png" in figs and "weights.png" in figs and any(f.startswith("projection-") for f in figs)


def test_eval_reads_materials_from_the_values_at_the_models_bounds(run_dir, tmp_path):
    """``--materials values``: the model's volume thresholded at its own bounds, scored as a classical volume is
    (the same Dice as thresholding the exported volume by hand; no shells relabelled, as for a classical volume)."""
    from kneas_method.engine.loading import load_run
    from kneas_method.evaluation.metrics import dice
    from kneas_method.evaluation.surfaces import gt_levels, match_materials, threshold_labels

    out = tmp_path / "values"
    assert _cli([str(run_dir), "--materials", "values", "--no-figures", "--no-surfaces", "-o", str(out)]) == 0
    mat = json.loads((out / "metrics.json").read_text())["materials"]
    run = load_run(str(run_dir), device="cpu")
    alphas, betas = run.model.bounds
    assert mat["readout"] == "values" and mat["boundaries"] == pytest.approx([*betas, betas[-1] + alphas[-1]])
    assert "the model's own attenuation bounds" in mat["definition"] and "gmm" not in mat and mat["shells_relabelled"] is False
    _, _, vol = eval_cli.evaluate_run(run, device="cpu", surfaces=False, shells=False)
    labels = threshold_labels(vol, mat["boundaries"], mat["air_cut"])
    for k, entry in enumerate(mat["matching"]):  # each class's mean value where it holds voxels, matched to the nearest level
        if (labels == k + 1).any():
            assert entry["mean_mu"] == pytest.approx(float(vol[labels == k + 1].mean()), rel=1e-5)
    matching = match_materials([e["mean_mu"] for e in mat["matching"]], gt_levels(run.scene))
    assert matching == [e["gt_label"] for e in mat["matching"]]
    mapped = np.concatenate([[0], matching])[labels]
    for entry in mat["materials"].values():
        assert entry["dice"] == pytest.approx(dice(mapped, run.scene.labels, entry["label"]))
    with pytest.raises(KneasError, match="no material reading 'value'"):  # from Python too, not only through --materials' choices
        eval_cli.evaluate_run(run, device="cpu", materials="value")


def test_eval_checkpoint_and_output(run_dir, tmp_path):
    ckpt = next((run_dir / "checkpoints").glob("*.ckpt"))
    out = tmp_path / "e"
    assert _cli(["--checkpoint", str(ckpt), "-o", str(out), "--no-figures", "--no-surfaces"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["checkpoint"] == str(ckpt)
    assert all(e.get("chamfer_mm") is None for e in m["materials"]["materials"].values())
    assert not (out / "figures").exists()
    kept = tmp_path / "kept"
    assert _cli(["--checkpoint", str(ckpt), "-o", str(kept), "--no-figures", "--no-surfaces", "--keep-shells"]) == 0
    mat = json.loads((kept / "metrics.json").read_text())["materials"]
    assert mat["shells_relabelled"] is False and mat["shell_cells_moved"] == {}


def test_eval_user_errors(tmp_path, capsys):
    assert _cli([]) == 2
    assert "give a run folder" in capsys.readouterr().err
    (tmp_path / "run").mkdir()
    assert _cli([str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err
    # without config.json a folder cannot be resumed either (kneas-train --resume needs it): no --resume hint
    assert "config.json" in err and "not a kneas run folder" in err and "--resume" not in err


def test_eval_of_a_run_with_damaged_checkpoints_says_how_to_get_it_back(run_dir, tmp_path, capsys):
    """A finished run (metrics.json) cannot be resumed, so its damaged checkpoints send the user to
    train it again from its config; an unfinished one is resumed."""
    import shutil

    damaged = tmp_path / "damaged"
    shutil.copytree(run_dir, damaged)
    for ckpt in (damaged / "checkpoints").glob("*.ckpt"):
        ckpt.write_bytes(ckpt.read_bytes()[:100])
    assert _cli([str(damaged), "--no-figures"]) == 2
    err = capsys.readouterr().err.strip()
    assert "only damaged checkpoints" in err and f"kneas-train --config {damaged}/config.json" in err and "--resume" not in err
    assert len(err.splitlines()) == 1
    (damaged / "metrics.json").unlink()
    assert _cli([str(damaged), "--no-figures"]) == 2
    err = capsys.readouterr().err
    assert f"kneas-train --resume {damaged}" in err and "--config" not in err
