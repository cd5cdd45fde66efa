"""SURE-chosen smoothing (kneas_method.denoise): its pure functions against naive oracles (scipy's
Gaussian, a direct covariance), SURE against the true error on volumes with known noise, the choice
on clean, noisy and textured volumes, and the stage in a run (metrics, checkpoint, settings)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from scipy import ndimage

from conftest import run, run_dir_of, sphere_scene
from kneas_method.denoise import (SIGMAS, gaussian_blur, gaussian_taps, noise_autocovariance, robust_variance, shifted_pairs, sure,
                                  sure_gaussian)


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
    direct = np.zeros((3, 3, 3))  # the noise's own autocovariance, measured directly
    for k in np.ndindex(3, 3, 3):
        direct[k] = np.mean(noise * np.roll(noise, tuple(-(o - 1) for o in k), axis=(0, 1, 2)))
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


def test_sure_gaussian_smooths_correlated_noise_near_the_best_sigma():
    clean = _balls()
    noisy = clean + _correlated_noise(clean.shape, 0.05, 0.7, seed=5)
    smoothed, choice = sure_gaussian(torch.as_tensor(noisy))
    errors = {s: float(((ndimage.gaussian_filter(noisy, s, mode="nearest") - clean) ** 2).sum()) for s in SIGMAS}
    best = min(errors, key=errors.get)
    assert choice.sigma > 0 and abs(choice.sigma - best) <= 0.2, (choice.sigma, best)
    assert float(((smoothed.numpy() - clean) ** 2).sum()) < 0.8 * float(((noisy - clean) ** 2).sum())
    assert choice.neighbour_correlation > 0.4 and choice.region == int((noisy != 0).sum())
    assert set(choice.to_json()) >= {"sigma_voxels", "noise_std", "neighbour_correlation", "sure"}


def test_sure_gaussian_leaves_a_clean_or_a_textured_volume_as_it_is():
    clean = torch.as_tensor(_balls())
    smoothed, choice = sure_gaussian(clean)
    assert choice.sigma == 0.0 and torch.equal(smoothed, clean)
    # fine texture (real, in every voxel) with a little white noise: smoothing would take the texture out
    textured = _balls() * (1 + 0.3 * _correlated_noise((64,) * 3, 1.0, 0.6, seed=7)) + _correlated_noise((64,) * 3, 0.002, 0.01, seed=8)
    _, choice = sure_gaussian(torch.as_tensor(textured))
    assert choice.sigma == 0.0, choice.sure


def test_a_run_smooths_a_noisy_scan_and_records_it(tmp_path, capsys):
    from kneas_method.data.naf import save_naf
    from kneas_method.data.simulate import SimulationConfig
    from kneas_method.engine.checkpoint import load_latest_checkpoint

    scene_path = save_naf(sphere_scene(SimulationConfig(n_voxel=24, voxel_mm=6.0, n_detector=32, n_train=16, n_val=2,
                                                        noise=True, photons=300.0)), tmp_path / "noisy.pickle")
    argv = ["k-neas", "--scene", str(scene_path), "--preset", "tiny", "--device", "cpu", "--num-materials", "2",
            "--output-dir", str(tmp_path / "out"), "--trainer.correction-passes", "1", "--trainer.epochs", "4",
            "--trainer.correction-steps", "10", "--trainer.correction-points", "512", "--trainer.denoise", "sure"]
    code, out, err = run(argv, capsys)
    assert code == 0, err
    run_dir = run_dir_of(out)
    metrics = json.loads((run_dir / "metrics.json").read_text())
    record = metrics["denoising"]
    assert record["sigma_voxels"] in (0.0, *SIGMAS) and record["noise_std"] > 0 and "0" in record["sure"]
    assert "denoise: " in out
    state, _, _ = load_latest_checkpoint(run_dir / "checkpoints", method="k-neas")
    assert state["extra"]["denoising"] == record


def test_denoise_settings_that_cannot_apply_are_refused_and_older_runs_keep_none(capsys):
    import dataclasses

    from kneas_method import presets, registry
    from kneas_method.config import to_dict
    from kneas_method.engine.loading import config_from_dict

    code, out, err = run(["k-neas", "--scene", "foot", "--preset", "tiny", "--trainer.denoise", "sure", "--dry-run"], capsys)
    assert code != 0 and "correction-passes" in err and "Traceback" not in err
    naf = presets.resolve(dataclasses.replace(registry.load("methods", "naf").config, method="naf", preset="cpu"))
    assert naf.trainer.denoise == "none"  # the cpu preset's sure, where there is no correction stage
    kneas = presets.resolve(dataclasses.replace(registry.load("methods", "k-neas").config, method="k-neas", preset="cpu"))
    assert kneas.trainer.denoise == "sure"
    saved = to_dict(kneas)
    older = {**saved, "trainer": {k: v for k, v in saved["trainer"].items() if k != "denoise"}}  # a run written before it existed
    assert config_from_dict(older, "config.json").trainer.denoise == "none"
