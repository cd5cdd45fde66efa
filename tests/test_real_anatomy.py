"""Real-anatomy scenes (benchmarks/real_anatomy.py): tissues as thresholds of the true volume in HU,
carried by the pickle, scored by kneas-eval (Dice and Chamfer) on a small crop of a real CT."""

import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

from conftest import run, run_dir_of  # noqa: E402
from kneas_method.data.naf import LABEL_THRESHOLDS_KEY, MATERIALS_KEY, load_naf, save_naf, threshold_labels, threshold_membership  # noqa: E402
from kneas_method.errors import SceneError  # noqa: E402

CROP = Path(__file__).resolve().parent / "data" / "ts_abdomen_crop_hu.npy"


def crop_scene():
    """The shipped crop of a real abdomen CT as a scene, as benchmarks/real_anatomy.py makes them."""
    import real_anatomy as ra
    from kneas_method.data.simulate import SimulationConfig, simulate_from_volume
    from kneas_method.data.volume_io import hu_to_mu

    hu = np.load(CROP).astype(np.float32)
    mu = hu_to_mu(hu)
    image = (mu / mu.max()).astype(np.float32)
    thresholds = [float(v) for v in hu_to_mu(np.array(ra.HU_THRESHOLDS)) / mu.max()]
    cfg = SimulationConfig(n_detector=32, n_train=8, n_val=4)
    scene = simulate_from_volume(image, cfg, voxel_mm=3.0, name="crop",
                                 meta={LABEL_THRESHOLDS_KEY: thresholds, MATERIALS_KEY: list(ra.MATERIALS)})
    scene.labels = threshold_labels(image, thresholds)
    return scene, hu, thresholds


def test_the_crop_holds_every_tissue():
    import real_anatomy as ra

    hu = np.load(CROP)
    shares = np.bincount(np.digitize(hu, ra.HU_THRESHOLDS).ravel(), minlength=5) / hu.size
    assert hu.shape == (24, 24, 24) and hu.dtype == np.int16
    assert np.all(shares > 0.03), shares  # air, lung/gas, fat, soft tissue and bone


def test_threshold_membership_is_the_labels_at_the_voxel_centres_and_interpolates_between():
    scene, hu, thresholds = crop_scene()
    member = threshold_membership(scene.image, thresholds, scene.geometry)
    centres = scene.geometry.voxel_centres().reshape(-1, 3).numpy()
    assert np.array_equal(member(centres), scene.labels.reshape(-1))
    # the naive version: a point half way between two voxel centres along x holds their mean
    x, y, z = scene.geometry.voxel_axes()
    for i, j, k in ((3, 4, 5), (10, 2, 20), (17, 17, 1)):
        mean = 0.5 * (scene.image[i, j, k] + scene.image[i + 1, j, k])
        point = np.array([[(float(x[i]) + float(x[i + 1])) / 2, float(y[j]), float(z[k])]])
        assert member(point)[0] == np.digitize(mean, thresholds)


def test_a_scene_with_threshold_labels_reads_back_with_its_materials_and_surfaces(tmp_path):
    scene, _, thresholds = crop_scene()
    path = save_naf(scene, tmp_path / "crop.pickle")
    loaded = load_naf(path)
    assert loaded.materials == ("lung", "fat", "soft tissue", "bone") and np.array_equal(loaded.labels, scene.labels)
    assert loaded.membership is not None
    centres = loaded.geometry.voxel_centres().reshape(-1, 3).numpy()
    assert np.array_equal(loaded.membership(centres), loaded.labels.reshape(-1))


@pytest.mark.parametrize("bad,words", [([0.3, 0.1], "ascending"), (["a"], "list of numbers"), ([0.1], "labels go up to 4")])
def test_wrong_thresholds_are_one_line(tmp_path, bad, words):
    scene, _, _ = crop_scene()
    scene.meta[LABEL_THRESHOLDS_KEY] = bad
    scene.meta[MATERIALS_KEY] = ["x"] * len(bad)
    path = save_naf(scene, tmp_path / "bad.pickle")
    with pytest.raises(SceneError, match=words):
        load_naf(path)


def test_kneas_eval_scores_dice_and_chamfer_against_the_hu_tissues(tmp_path, capsys):
    from kneas_method.cli import eval as eval_cli

    scene, _, _ = crop_scene()
    path = save_naf(scene, tmp_path / "crop.pickle")
    code, out, err = run(["asd-pocs", "--scene", str(path), "--reconstruction.iterations", "3", "--output-dir", str(tmp_path / "o")],
                         capsys)
    assert code == 0, err
    run_dir = run_dir_of(out)
    with pytest.raises(SystemExit) as exc:
        eval_cli.main([str(run_dir), "--no-figures", "-o", str(tmp_path / "e")])
    assert exc.value.code == 0, capsys.readouterr().err
    metrics = json.loads((tmp_path / "e" / "metrics.json").read_text())
    materials = metrics["materials"]["materials"]
    assert set(materials) >= {"soft tissue", "bone"}
    for m in materials.values():
        assert 0.0 <= m["dice"] <= 1.0
    # the classical volume's brightest class is matched to bone, and its surface lies near the threshold's
    assert materials["bone"]["predicted_materials"] and 0.0 < materials["bone"]["dice"]
    assert materials["bone"]["chamfer_mm"] is not None and 0.0 < materials["bone"]["chamfer_mm"] < 10.0


def test_the_classical_bar_smooths_the_run_and_its_best_count_as_kneas_smooths_its_volume(tmp_path):
    """benchmarks/classical.py --trace --smooth: the run's volume and its best count's volume after the
    smoothing stage's own filter (stages.smoothing.smooth_against_views), scored as the run is."""
    import dataclasses

    import classical
    import torch

    from kneas_method.classical.iterative import sart
    from kneas_method.classical.projector import Projector
    from kneas_method.data.simulate import SimulationConfig, simulate_from_volume
    from kneas_method.evaluation.metrics import psnr3d
    from kneas_method.stages.smoothing import smooth_against_views
    from kneas_method.evaluation.surfaces import volume_material_metrics
    from kneas_method.stages.band_correction import volume_at_noise

    scene, _, _ = crop_scene()
    noisy = simulate_from_volume(scene.image, dataclasses.replace(SimulationConfig(n_detector=32, n_train=8, n_val=4), noise=True),
                                 voxel_mm=3.0, name="crop-noisy", meta=dict(scene.meta))
    noisy.labels = scene.labels
    path = save_naf(noisy, tmp_path / "crop-noisy.pickle")
    out = tmp_path / "bar.json"
    assert classical.main(["--scenes", str(path), "--runs", "sart:iterations=12,relaxation=1.0", "--trace", "--smooth", "--dice",
                           "--out", str(out)]) == 0
    row = json.loads(out.read_text())["rows"][0]
    best = row["best"]["iteration"]
    assert best < 12 and row["smoothed_best"]["iteration"] == best  # the noise makes an earlier count best
    # the oracle: SART run by hand to the last and to the best count, smoothed by hand
    loaded = load_naf(path)
    projections = torch.as_tensor(loaded.train.projections)
    projector = Projector(loaded.geometry, loaded.train.angles)
    for key, count in (("smoothed", 12), ("smoothed_best", best)):
        volume = torch.as_tensor(sart(loaded.train.projections, loaded.geometry, loaded.train.angles, iterations=count, relaxation=1.0))
        smoothed, choice = smooth_against_views(volume, projections, projector, mask=torch.ones(volume.shape, dtype=torch.bool))
        assert row[key]["filter"] == choice.label
        assert row[key]["psnr3d"] == pytest.approx(psnr3d(smoothed.clamp_min(0).numpy(), loaded.image), abs=1e-3)
        # --dice with --smooth: the smoothed volume thresholded as the run's own is (the paper's K rule)
        tissues = volume_material_metrics(smoothed.clamp_min(0).numpy(), loaded, surfaces=False)
        assert row["dice_" + key] == {k: round(v["dice"], 3) for k, v in tissues["materials"].items()}
    assert row["dice_smoothed_best"] != row["dice"] and "chamfer_mm_cpu_rule_smoothed_best" in row
    # the best count's volume fits the views to their noise and keeps its filter; the last count's may be refused
    # (a filter may not give up more fit than the noise), so it is never worse than the run's own volume
    assert row["smoothed_best"]["filter"] != "none" and row["smoothed_best"]["psnr3d"] > row["best"]["psnr3d"]
    assert row["smoothed"]["psnr3d"] >= row["psnr3d"] - 1e-3  # both rounded as the table prints them
    # --dice: the cpu preset's K rule as k-neas's start gets it, the at-noise rule where the volume fits the views to their noise
    seen = []
    for count in (1, 12):
        out = tmp_path / f"dice-{count}.json"
        assert classical.main(["--scenes", str(path), "--runs", f"sart:iterations={count},relaxation=1.0", "--dice", "--out", str(out)]) == 0
        rule = json.loads(out.read_text())["rows"][0]["cpu_rule"]
        volume = sart(loaded.train.projections, loaded.geometry, loaded.train.angles, iterations=count, relaxation=1.0)
        at_noise = volume_at_noise(volume, projections, projector)[0]
        assert rule["at_noise"] is at_noise and rule["k_rule"] == ("bic" if at_noise else "peaks")
        seen.append(at_noise)
    # both branches: on 8 views of a 32-pixel detector twelve sweeps fit part of the noise itself, whose
    # estimate from the residual's high frequencies then falls below the residual's mean square
    assert seen == [True, False]


def test_the_classical_bar_refuses_to_smooth_a_scene_without_truth(tmp_path):
    import classical

    scene, _, _ = crop_scene()
    scene.image = None
    scene.labels = None
    path = save_naf(scene, tmp_path / "no-truth.pickle")
    with pytest.raises(SystemExit, match="ground truth"):
        classical.main(["--scenes", str(path), "--runs", "sart:iterations=2", "--smooth"])


def test_the_classical_bar_starts_from_a_given_volume_or_the_truths_classes(tmp_path):
    import classical

    from kneas_method.classical.iterative import sart
    from kneas_method.evaluation.metrics import psnr3d

    scene, _, _ = crop_scene()
    path = save_naf(scene, tmp_path / "crop.pickle")
    loaded = load_naf(path)
    classes = np.zeros_like(loaded.image)
    for k in np.unique(loaded.labels):  # the naive version: every labelled class at its mean
        classes[loaded.labels == k] = loaded.image[loaded.labels == k].mean()
    np.save(tmp_path / "start.npy", classes)
    rows = {}
    for spec in ("truth-classes", str(tmp_path / "start.npy")):
        out = tmp_path / "bar.json"
        assert classical.main(["--scenes", str(path), "--runs", "sart:iterations=3", "--trace", "--init", spec, "--out", str(out)]) == 0
        rows[spec] = json.loads(out.read_text())["rows"][0]
    by_hand = sart(loaded.train.projections, loaded.geometry, loaded.train.angles, iterations=3, init=classes)
    for row in rows.values():
        assert row["init"]["psnr3d"] == pytest.approx(psnr3d(classes, loaded.image), abs=1e-3)
        assert row["psnr3d"] == pytest.approx(psnr3d(by_hand, loaded.image), abs=1e-3)
    np.save(tmp_path / "wrong.npy", classes[:-1])
    np.savez(tmp_path / "two.npz", a=classes, b=classes)
    for argv, words in ((["--runs", "sart:iterations=1", "--init", str(tmp_path / "wrong.npy")], "has shape"),
                        (["--runs", "sart:iterations=1", "--init", str(tmp_path / "two.npz")], "several arrays"),
                        (["--runs", "fdk", "--init", "truth-classes"], "FDK is not iterative")):
        with pytest.raises(SystemExit, match=words):
            classical.main(["--scenes", str(path), *argv])


def test_a_scene_projected_from_a_finer_grid_keeps_its_truth_and_takes_the_finer_views():
    """The ``-fine`` scenes: the truth on the reconstruction grid, the views from the CT's finer grid
    over the same box (no exact voxel solution for a classical method to approach)."""
    import real_anatomy as ra
    from kneas_method.classical.projector import forward
    from kneas_method.data.simulate import SimulationConfig, simulate_from_volume

    scene, _, _ = crop_scene()  # 24^3 voxels of 3 mm: the finer grid
    fine = scene.image
    coarse = fine.reshape(12, 2, 12, 2, 12, 2).mean(axis=(1, 3, 5))  # 12^3 voxels of 6 mm over the same box
    cfg = SimulationConfig(n_detector=32, n_train=8, n_val=4)
    target = simulate_from_volume(coarse, cfg, voxel_mm=6.0, name="crop-coarse")
    own = target.train.projections.copy()
    ra.project_finer(target, fine, (3.0, 3.0, 3.0), cfg)
    assert np.array_equal(target.image, coarse) and target.geometry.n_voxel == (12, 12, 12)
    np.testing.assert_allclose(target.train.projections, forward(fine, scene.geometry, target.train.angles), rtol=1e-5, atol=1e-7)
    assert np.allclose(target.geometry.on_grid((24, 24, 24)).d_voxel, scene.geometry.d_voxel)
    gap = np.abs(target.train.projections - own).mean() / own.mean()
    assert 1e-3 < gap < 0.1, gap  # the finer detail the coarse grid cannot hold
    assert target.meta["projected_from"] == {"n_voxel": [24, 24, 24], "voxel_mm": [3.0, 3.0, 3.0]}
    with pytest.raises(ValueError, match="does not fill the scene's box"):
        ra.project_finer(target, fine[:20], (3.0, 3.0, 3.0), cfg)
