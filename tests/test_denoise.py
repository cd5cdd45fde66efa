"""SURE-chosen smoothing (kneas_method.stages.denoise): its pure functions against naive oracles (scipy's
Gaussian, a direct covariance, a loop-by-loop bilateral filter), SURE (exact and by Monte Carlo)
against the true error on volumes with known noise, the choice on clean, noisy and textured volumes,
and the stage in a run (metrics, checkpoint, settings)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from scipy import ndimage

from conftest import run, run_dir_of, sphere_scene
from kneas_method.stages.denoise import (BAND_EDGES, BAND_FLOOR, BILATERAL_TRUNCATE, GIVE_UP, NOISE_SCALES, SIGMAS, band_power_ratios,
                                  bilateral, correlated_noise, discrepancy_smoothing, gaussian_blur, gaussian_taps, monte_carlo_sure, noise_autocovariance, robust_variance,
                                  shifted_pairs, sure, sure_smoothing)


def _balls(n: int = 64) -> np.ndarray:
    """A piecewise-constant volume: a ball of 0.5 holding a smaller one of 1.0, in air. Its edges are few
    (differences across them would bias the noise estimate, as many edges in a small box do)."""
    x, y, z = np.meshgrid(*(np.arange(n),) * 3, indexing="ij")
    c = (n - 1) / 2
    v = np.zeros((n, n, n), np.float32)
    v[(x - c) ** 2 + (y - c) ** 2 + (z - c) ** 2 < (0.375 * n) ** 2] = 0.5
    v[(x - c - 4) ** 2 + (y - c + 2) ** 2 + (z - c - 1) ** 2 < (n / 8) ** 2] = 1.0
    return v


def _correlated_noise(shape, std: float, width: float, seed: int = 0) -> np.ndarray:
    """Normal noise of standard deviation ``std`` made spatially correlated by a Gaussian of ``width`` voxels."""
    n = ndimage.gaussian_filter(np.random.default_rng(seed).standard_normal(shape), width, mode="wrap")
    return (std * n / n.std()).astype(np.float32)


def _direct_autocovariance(noise: np.ndarray) -> np.ndarray:
    """The noise's own autocovariance at the offsets {-1, 0, 1}^3 (periodic), measured directly: [3, 3, 3]."""
    noise = noise.astype(np.float64)
    direct = np.zeros((3, 3, 3))
    for k in np.ndindex(3, 3, 3):
        direct[k] = np.mean(noise * np.roll(noise, tuple(-(o - 1) for o in k), axis=(0, 1, 2)))
    return direct


def test_gaussian_blur_matches_scipy():
    v = np.random.default_rng(1).random((12, 9, 14)).astype(np.float32)
    for sigma in (0.4, 0.8, 1.5):
        ours = gaussian_blur(torch.as_tensor(v), sigma).numpy()
        np.testing.assert_allclose(ours, ndimage.gaussian_filter(v, sigma, mode="nearest", truncate=4.0), atol=1e-6)
    assert gaussian_blur(torch.as_tensor(v), 0.0) is not None and np.array_equal(gaussian_blur(torch.as_tensor(v), 0.0).numpy(), v)
    assert float(gaussian_taps(0.7).sum()) == pytest.approx(1.0) and len(gaussian_taps(0.7)) == 2 * int(4 * 0.7 + 0.5) + 1


def test_shifted_pairs_are_the_differences_inside_the_mask():
    v = torch.arange(4 * 5 * 6, dtype=torch.float32).reshape(4, 5, 6)
    mask = torch.ones_like(v, dtype=torch.bool)
    mask[0] = False
    d = shifted_pairs(v, mask, (1, 0, -1))
    naive = [float(v[i, j, k] - v[i + 1, j, k - 1]) for i in range(4) for j in range(5) for k in range(6)
             if i + 1 < 4 and k - 1 >= 0 and mask[i, j, k] and mask[i + 1, j, k - 1]]
    assert sorted(d.tolist()) == sorted(naive)


def test_robust_variance_of_normal_values_ignores_a_few_large_ones():
    x = torch.randn(200_000, generator=torch.Generator().manual_seed(0)) * 0.3
    x[:2000] = 50.0  # 1 % outliers: edges
    assert robust_variance(x) == pytest.approx(0.09, rel=0.05)
    assert robust_variance(torch.zeros(0)) == 0.0


def test_noise_autocovariance_matches_the_noise_it_was_given():
    shape = (48, 48, 48)
    noise = _correlated_noise(shape, 0.05, 0.7)
    v = noise.copy()
    v[24:] += 0.5  # one edge: the differences across it are few (in a small box of many edges they would bias c)
    c = noise_autocovariance(torch.as_tensor(v), torch.ones(shape, dtype=torch.bool)).numpy()
    direct = _direct_autocovariance(noise)
    np.testing.assert_allclose(c, direct, atol=0.1 * direct[1, 1, 1])
    assert c[1, 1, 1] == pytest.approx(0.05 ** 2, rel=0.1) and c[2, 1, 1] > 0.4 * c[1, 1, 1]


def test_sure_tracks_the_true_error_of_each_smoothing():
    clean = _balls()
    v = torch.as_tensor(clean + _correlated_noise(clean.shape, 0.05, 0.7, seed=3))
    mask = torch.ones(clean.shape, dtype=torch.bool)
    c = noise_autocovariance(v, mask)
    for sigma in (0.0, 0.6, 1.0):
        smoothed = gaussian_blur(v, sigma)
        true = float(((smoothed - torch.as_tensor(clean)) ** 2).sum())
        assert sure(v, smoothed, sigma, int(mask.sum()), c) == pytest.approx(true, rel=0.15), sigma
    assert sure(v, v, 0.0, 10, c) == pytest.approx(10 * float(c[1, 1, 1]))


def _naive_bilateral(v: np.ndarray, sigma: float, range_std: float, guide: np.ndarray) -> np.ndarray:
    """The separable cross-bilateral filter of ``kneas_method.stages.denoise.bilateral``, voxel by voxel."""
    r = max(1, int(BILATERAL_TRUNCATE * sigma + 0.5))
    out = v.astype(np.float64)
    for axis in range(3):
        new = np.zeros_like(out)
        for x in np.ndindex(*v.shape):
            total = weights = 0.0
            for j in range(-r, r + 1):
                y = list(x)
                y[axis] = min(max(x[axis] + j, 0), v.shape[axis] - 1)  # the border repeated
                y = tuple(y)
                w = np.exp(-0.5 * (j / sigma) ** 2) * np.exp(-0.5 * ((guide[y] - guide[x]) / range_std) ** 2)
                total += w * out[y]
                weights += w
            new[x] = total / weights
        out = new
    return out


def test_bilateral_matches_the_naive_filter_and_keeps_an_edge_a_gaussian_blurs():
    rng = np.random.default_rng(2)
    v = rng.random((7, 5, 6)).astype(np.float32)
    guide = gaussian_blur(torch.as_tensor(v), 0.8)
    ours = bilateral(torch.as_tensor(v), 1.2, 0.2, guide).numpy()
    np.testing.assert_allclose(ours, _naive_bilateral(v, 1.2, 0.2, guide.numpy()), atol=1e-5)
    assert torch.equal(bilateral(torch.as_tensor(v), 0.0, 0.2), torch.as_tensor(v))
    # a step of 0.5 under noise of 0.05: the bilateral takes the noise out and keeps the step's contrast
    step = np.zeros((32, 32, 32), np.float32)
    step[16:] = 0.5
    noisy = torch.as_tensor(step + _correlated_noise(step.shape, 0.05, 0.5, seed=4))
    b = bilateral(noisy, 3.0, 0.05).numpy()
    g = gaussian_blur(noisy, 3.0).numpy()
    assert np.abs(b - step).mean() < 0.5 * np.abs(noisy.numpy() - step).mean()
    assert b[17:20].mean() - b[12:15].mean() > 0.45 > g[17:20].mean() - g[12:15].mean()


def test_correlated_noise_has_the_covariance_it_was_asked_for():
    shape = (40, 40, 40)
    c = noise_autocovariance(torch.as_tensor(_correlated_noise(shape, 0.05, 0.6)), torch.ones(shape, dtype=torch.bool))
    p = correlated_noise(c, shape, torch.Generator().manual_seed(1)).numpy().astype(np.float64)
    for k in np.ndindex(3, 3, 3):
        measured = np.mean(p * np.roll(p, tuple(-(o - 1) for o in k), axis=(0, 1, 2)))
        assert measured == pytest.approx(float(c[k]), abs=0.08 * float(c[1, 1, 1])), k


def test_monte_carlo_sure_equals_the_exact_one_for_a_gaussian_and_tracks_a_bilateral_error():
    # noise correlated with its neighbours and barely beyond (a Gaussian of 0.5 voxel: 0.02 two voxels apart), as
    # the covariance model assumes, and that covariance measured on the noise itself: this checks the Monte Carlo
    # estimate, not the covariance's (SURE's terms cancel: c(0) 13 % high here would shift it by 80 of the 60)
    clean = _balls()
    noise = _correlated_noise(clean.shape, 0.05, 0.5, seed=3)
    v = torch.as_tensor(clean + noise)
    mask = torch.ones(clean.shape, dtype=torch.bool)
    c = torch.as_tensor(_direct_autocovariance(noise))
    region = int(mask.sum())
    probe = correlated_noise(c, v.shape, torch.Generator().manual_seed(0))
    smoothed = gaussian_blur(v, 0.8)
    exact = sure(v, smoothed, 0.8, region, c)
    assert monte_carlo_sure(v, lambda x: gaussian_blur(x, 0.8), smoothed, probe, region, float(c[1, 1, 1])) == pytest.approx(exact, rel=0.05)
    std = float(c[1, 1, 1]) ** 0.5
    for s, k in ((1.5, 1.0), (3.0, 1.0)):
        smoother = lambda x, s=s, k=k: bilateral(x, s, k * std)
        smoothed = smoother(v)
        true = float(((smoothed - torch.as_tensor(clean)) ** 2).sum())
        assert monte_carlo_sure(v, smoother, smoothed, probe, region, float(c[1, 1, 1])) == pytest.approx(true, rel=0.1), (s, k)


def test_sure_smoothing_takes_correlated_noise_out_better_than_any_gaussian():
    clean = _balls()
    noisy = clean + _correlated_noise(clean.shape, 0.05, 0.7, seed=5)
    smoothed, choice = sure_smoothing(torch.as_tensor(noisy))
    best_gaussian = min(float(((ndimage.gaussian_filter(noisy, s, mode="nearest") - clean) ** 2).sum()) for s in SIGMAS)
    assert choice.filter == "bilateral", choice.sure
    assert float(((smoothed.numpy() - clean) ** 2).sum()) < 0.7 * best_gaussian
    assert choice.neighbour_correlation > 0.4 and choice.region == int((noisy != 0).sum())
    assert set(choice.to_json()) >= {"filter", "sigma_voxels", "range_noise_stds", "noise_std", "neighbour_correlation", "sure"}
    # with only Gaussians to choose from, SURE picks one near the truth's best
    _, gaussian = sure_smoothing(torch.as_tensor(noisy), bilaterals=())
    errors = {s: float(((ndimage.gaussian_filter(noisy, s, mode="nearest") - clean) ** 2).sum()) for s in SIGMAS}
    assert gaussian.filter == "gaussian" and abs(gaussian.sigma - min(errors, key=errors.get)) <= 0.2, (gaussian.sigma, errors)


def test_sure_smoothing_leaves_a_clean_or_a_textured_volume_as_it_is():
    clean = torch.as_tensor(_balls())
    smoothed, choice = sure_smoothing(clean)
    assert choice.filter == "none" and torch.equal(smoothed, clean)
    # fine texture (real, in every voxel) with a little white noise: smoothing would take the texture out
    textured = _balls() * (1 + 0.3 * _correlated_noise((64,) * 3, 1.0, 0.6, seed=7)) + _correlated_noise((64,) * 3, 0.002, 0.01, seed=8)
    _, choice = sure_smoothing(torch.as_tensor(textured))
    assert choice.filter == "none", choice.sure


def test_discrepancy_raises_the_noise_estimate_while_the_choice_fits_the_data_closer_than_their_noise():
    clean = _balls()
    noise = _correlated_noise(clean.shape, 0.03, 0.7, seed=5)
    noise[:, :32] *= 4  # half the volume four times noisier: the robust spread sees the quieter half
    noisy = torch.as_tensor(clean + noise)
    noise_variance = float((noise.astype(np.float64) ** 2).mean())
    calls = []

    def misfit(v):  # the data are the noisy volume itself (an identity projector), as a model that fitted their noise
        calls.append(1)
        return float(((v - noisy) ** 2).mean())

    first, sure_choice = sure_smoothing(noisy)
    smoothed, choice = discrepancy_smoothing(noisy, misfit, noise_variance)
    error = lambda v: float(((v.numpy() - clean) ** 2).sum())
    assert sure_choice.filter != "none" and choice.noise_scale > 1.0
    assert error(smoothed) < 0.6 * error(first), (choice.misfit, error(smoothed), error(first))
    ratios = [r for _, _, r in choice.misfit]
    assert ratios[0] == pytest.approx(misfit(first) / noise_variance) and all(r < 1 for r in ratios[:-1])
    assert [m for m, _, _ in choice.misfit] == list(NOISE_SCALES[: len(ratios)]) and choice.misfit[-1][1] == choice.label
    assert choice.to_json()["misfit"][0]["noise_scale"] == 1.0
    # where SURE's choice already reaches the data's noise, it stands: a volume that misfits the data by a
    # floor of its own (half of what the filter gives up), the filter within the noise
    floor = 0.5 * misfit(first)
    smoothed, choice = discrepancy_smoothing(noisy, lambda v: misfit(v) + floor, 1.2 * misfit(first))
    assert torch.equal(smoothed, first) and choice.noise_scale == 1.0 and len(choice.misfit) == 1 and not choice.refused
    # a clean volume: SURE chooses none and the projections are not compared
    calls.clear()
    smoothed, choice = discrepancy_smoothing(torch.as_tensor(clean), misfit, noise_variance)
    assert choice.filter == "none" and not calls and choice.misfit == []


def test_band_power_ratios_read_white_noise_as_one_and_a_fitted_share_as_less():
    g = torch.Generator().manual_seed(0)
    white = 0.1 * torch.randn(24, 64, 80, generator=g)
    ratios = band_power_ratios(white, 0.01, footprint=1.5)
    assert len(ratios) == len(BAND_EDGES) - 1 and all(abs(r - 1) < 0.06 for r in ratios), ratios
    # a volume that fitted the noise's finer half leaves only its smooth part: the upper bands fall
    smooth = torch.nn.functional.avg_pool2d(white[:, None], 5, stride=1, padding=2)[:, 0]
    low = band_power_ratios(smooth, 0.01, footprint=1.5)
    assert low[-1] < 0.2 and low[0] > low[-1]
    # the naive DFT sum at one band (the oracle)
    r = torch.randn(2, 8, 10, generator=g, dtype=torch.float64)
    total, count = 0.0, 0
    for v in range(8):
        for u in range(10):
            fv, fu = (v if v < 4 else v - 8) / 8, (u if u < 5 else u - 10) / 10
            if 0.25 <= (fu * fu + fv * fv) ** 0.5 * 1.0 < 0.4:
                for n in range(2):
                    z = sum(complex(r[n, j, i]) * np.exp(-2j * np.pi * (fv * j + fu * i)) for j in range(8) for i in range(10))
                    total += abs(z) ** 2 / 80
                    count += 1
    assert band_power_ratios(r, 2.0, footprint=1.0, edges=(0.25, 0.4))[0] == pytest.approx(total / count / 2.0)
    assert np.isnan(band_power_ratios(r, 2.0, footprint=1.0, edges=(0.9, 1.0))[0])  # no frequency that high


def test_a_choice_within_the_whole_misfit_is_raised_while_a_detector_band_still_fits_closer_than_the_noise():
    """The whole misfit carries a floor of the volume's own (a model that misses the data's smoothest
    part); the band's power does not, and shows the noise the volume fitted."""
    clean = _balls()
    noise = _correlated_noise(clean.shape, 0.03, 0.7, seed=5)
    noise[:, :32] *= 4
    noisy = torch.as_tensor(clean + noise)
    noise_variance = float((noise.astype(np.float64) ** 2).mean())

    def fitted(v):  # the data are the noisy volume itself (an identity projector)
        return float(((v - noisy) ** 2).mean()) / noise_variance

    first, _ = sure_smoothing(noisy)
    floor = 1.0 - fitted(first) + 0.01  # enough to lift the first choice's whole misfit over the noise
    whole = lambda v: (fitted(v) + floor) * noise_variance
    smoothed, choice = discrepancy_smoothing(noisy, whole, noise_variance)
    assert torch.equal(smoothed, first) and choice.noise_scale == 1.0 and choice.band_fit == [None]
    smoothed, choice = discrepancy_smoothing(noisy, whole, noise_variance, band_fit=fitted)
    assert choice.noise_scale > 1.0 and choice.band_fit[0] == pytest.approx(fitted(first)) and choice.band_fit[0] < BAND_FLOOR
    assert choice.band_fit[-1] >= BAND_FLOOR or choice.noise_scale == NOISE_SCALES[-1]
    error = lambda v: float(((v.numpy() - clean) ** 2).sum())
    assert error(smoothed) < 0.6 * error(first)
    assert choice.to_json()["band_fit_over_noise"][0] == round(fitted(first), 4)


def test_a_filter_that_gives_up_more_fit_than_the_noise_is_refused():
    """Texture that varies from voxel to voxel looks like noise to SURE; the projections (here the volume
    itself, an identity projector) show it is not: taking it out costs far more fit than the data's noise."""
    textured = torch.as_tensor(_balls() * (1 + 0.2 * _correlated_noise((64,) * 3, 1.0, 0.7, seed=3)))
    _, sure_choice = sure_smoothing(textured)
    assert sure_choice.filter != "none"  # SURE alone takes the texture for noise

    def misfit(v):  # the data are the textured volume: it fits them exactly
        return float(((v - textured) ** 2).mean())

    removed = misfit(bilateral(textured, 1.5, 1.0 * sure_choice.noise_std))
    smoothed, choice = discrepancy_smoothing(textured, misfit, data_noise=removed / 50)
    assert torch.equal(smoothed, textured) and choice.filter == "none"
    assert choice.refused == sure_choice.label and choice.own_misfit == 0.0 and len(choice.misfit) == 1
    record = choice.to_json()
    assert record["refused"] == sure_choice.label and record["own_misfit_over_noise"] == 0.0
    # with the data's noise as large as what the filter takes out, the filter is kept (and the stronger one
    # the raised noise estimate then asks for is refused)
    smoothed, choice = discrepancy_smoothing(textured, misfit, data_noise=misfit(sure_smoothing(textured)[0]) / GIVE_UP * 1.001)
    assert choice.label == sure_choice.label and choice.noise_scale == 1.0 and not torch.equal(smoothed, textured)
    assert [m for m, _, _ in choice.misfit] == list(NOISE_SCALES[:2]) and choice.refused == choice.misfit[1][1]


def test_a_stronger_choice_refused_keeps_the_last_one_within_the_noise():
    clean = _balls()
    noisy = torch.as_tensor(clean + _correlated_noise(clean.shape, 0.03, 0.7, seed=5))
    first, first_choice = sure_smoothing(noisy)
    values = iter([0.0, 0.5, 5.0])  # the volume's own misfit, then each choice's, in the order they are asked for
    smoothed, choice = discrepancy_smoothing(noisy, lambda v: next(values), data_noise=1.0)
    assert torch.equal(smoothed, first) and choice.label == first_choice.label and choice.noise_scale == 1.0
    assert [m for m, _, _ in choice.misfit] == list(NOISE_SCALES[:2]) and choice.refused == choice.misfit[1][1]


def test_a_run_smooths_a_noisy_scan_and_records_it(tmp_path, capsys):
    from kneas_method.data.naf import save_naf
    from kneas_method.data.simulate import SimulationConfig
    from kneas_method.engine.checkpoint import load_latest_checkpoint

    scene_path = save_naf(sphere_scene(SimulationConfig(n_voxel=24, voxel_mm=6.0, n_detector=32, n_train=16, n_val=2,
                                                        noise=True, photons=300.0)), tmp_path / "noisy.pickle")
    argv = ["k-neas", "--scene", str(scene_path), "--preset", "tiny", "--device", "cpu", "--num-materials", "2",
            "--output-dir", str(tmp_path / "out"), "--procedure", "paper", "--add-stages", "correction", "smoothing",
            "--stages.correction.passes", "1", "--trainer.epochs", "4", "--stages.correction.steps", "10",
            "--stages.correction.points", "512", "--stages.smoothing.steps", "10", "--stages.smoothing.points", "512"]
    code, out, err = run(argv, capsys)
    assert code == 0, err
    run_dir = run_dir_of(out)
    metrics = json.loads((run_dir / "metrics.json").read_text())
    record = metrics["stages"]["smoothing"]
    assert record["filter"] in ("none", "gaussian", "bilateral") and record["noise_std"] > 0 and "none" in record["sure"]
    assert record["noise_scale"] >= 1.0 and all(r["misfit_over_noise"] > 0 for r in record["misfit"])
    assert (record["filter"] == "none") == (record["misfit"] == [])
    assert "smoothing: " in out
    state, _, _ = load_latest_checkpoint(run_dir / "checkpoints", method="k-neas")
    assert state["extra"]["stages"]["smoothing"] == record


@pytest.mark.parametrize("fit", ["as-built", "away"])
def test_a_smoothing_fit_that_ends_further_from_its_target_is_undone(tmp_path, capsys, monkeypatch, fit):
    """The smoothing's fit is kept where it brings the model closer to the smoothed volume (the stage's own
    fit on a noisy scan), and undone where it ends further from it (a fit replaced here by one that pushes
    the model's weights away): the run then ends with the model it had after training, the smoothing's
    score equal to training's."""
    import torch

    import kneas_method.stages.smoothing as smoothing
    from kneas_method.data.naf import save_naf
    from kneas_method.data.simulate import SimulationConfig

    if fit == "away":
        def push_away(trainer, *args, **kwargs):
            with torch.no_grad():
                for p in trainer.model.parameters():
                    p.add_(0.5 * torch.randn_like(p))
        monkeypatch.setattr(smoothing, "fit_in_region", push_away)
    scene_path = save_naf(sphere_scene(SimulationConfig(n_voxel=24, voxel_mm=6.0, n_detector=32, n_train=16, n_val=2,
                                                        noise=True, photons=300.0)), tmp_path / "noisy.pickle")
    argv = ["k-neas", "--scene", str(scene_path), "--preset", "tiny", "--device", "cpu", "--num-materials", "2",
            "--output-dir", str(tmp_path / "out"), "--procedure", "paper", "--add-stages", "smoothing",
            "--trainer.epochs", "4", "--stages.smoothing.points", "512"]  # the fit at its default 300 steps and rate
    code, out, err = run(argv, capsys)
    assert code == 0, err
    metrics = json.loads((run_dir_of(out) / "metrics.json").read_text())
    record = metrics["stages"]["smoothing"]
    assert record["filter"] != "none"  # this scene's noise is smoothed
    kept = fit == "as-built"
    assert record["fit_kept"] is kept, (record["fit_distance_before"], record["fit_distance_after"])
    assert (record["fit_distance_after"] < record["fit_distance_before"]) is kept
    scores = {s["after"]: (s["psnr3d"], s["ssim3d"]) for s in metrics["stage_scores"]}
    assert (scores["smoothing"] == scores["training"]) is (not kept)
    assert ("put back as it was" in out) is (not kept)
    assert metrics["psnr3d"] == pytest.approx(scores["smoothing"][0], abs=0.05)  # the run ends with the model the stage left


def test_smoothing_settings_and_older_runs(capsys):
    import dataclasses

    from kneas_method import presets, registry
    from kneas_method.engine.legacy_config import upgrade

    naf = presets.resolve(dataclasses.replace(registry.load("methods", "naf").config, method="naf", preset="cpu"))
    assert naf.stages.smoothing is None  # the procedure's, where there are no surfaces (and no correction)
    kneas = presets.resolve(dataclasses.replace(registry.load("methods", "k-neas").config, method="k-neas", preset="cpu"))
    assert kneas.stages.smoothing.rule == "sure"
    base = {"method": "k-neas", "bounds_volume": "asd-pocs", "trainer": {"warm_start": "asd-pocs", "warm_start_steps": 300,
                                                                          "correction_passes": 12, "correction_steps": 75}}
    assert upgrade(base, lambda m, x: False)["stages"]["smoothing"] is None  # written before the smoothing existed: none
    # the first smoothing's runs: Gaussians alone, fitted with a pass's steps and rate
    gaussian = upgrade({**base, "trainer": {**base["trainer"], "denoise": "sure"}}, lambda m, x: False)["stages"]["smoothing"]
    assert (gaussian["rule"], gaussian["steps"], gaussian["lr"]) == ("sure-gaussian", 75, 1e-4)
    code, out, err = run(["k-neas", "--scene", "foot", "--preset", "cpu", "--stages.smoothing.steps", "-3", "--dry-run"], capsys)
    assert code == 2 and "--stages.smoothing.steps must be a whole number >= 0, got -3" in err and "Traceback" not in err


def test_the_smoothing_estimates_the_noise_of_the_material_not_of_the_quiet_air_the_hull_keeps():
    """A model holds the air its visual hull keeps at its lowest level, nearly still: over the whole
    hull the robust noise estimate reads that air; over the material it reads the material's noise."""
    from types import SimpleNamespace

    from kneas_method.stages.smoothing import material_voxels

    clean = _balls()
    inside = clean > 0
    air = 1e-3 + 1e-4 * np.abs(_correlated_noise(clean.shape, 1.0, 0.7, seed=2))  # the hull's air: not 0, quiet
    noisy = torch.as_tensor(np.where(inside, clean + _correlated_noise(clean.shape, 0.03, 0.7, seed=5), air).astype(np.float32))
    noisy[:6] = 0.0  # outside the hull
    bounds = SimpleNamespace(alphas=[0.25, 0.5, 0.5], betas=[0.0, 0.25, 0.75])  # the lowest interval's middle: 0.125
    mask = material_voxels(noisy, bounds)
    assert torch.equal(mask, torch.as_tensor(inside) & (noisy >= 0.125)) and bool(mask[torch.as_tensor(inside)].float().mean() > 0.99)
    assert torch.equal(material_voxels(noisy), noisy != 0)  # no bounds: the hull
    hull_std = float(noise_autocovariance(noisy, noisy != 0)[1, 1, 1]) ** 0.5
    material_std = float(noise_autocovariance(noisy, mask)[1, 1, 1]) ** 0.5
    true_std = float(_correlated_noise(clean.shape, 0.03, 0.7, seed=5)[inside].std())
    assert material_std == pytest.approx(true_std, rel=0.25) and hull_std < 0.5 * material_std
