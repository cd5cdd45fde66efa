import json
import math

import numpy as np
import pytest
import torch

from kneas_method.errors import KneasError
from kneas_method.evaluation import metrics as M
from kneas_method.geometry import Geometry


@pytest.fixture
def rng():
    return np.random.default_rng(0)


# ---------------------------------------------------------------------- 2D
def test_psnr2d_identical_is_inf_and_per_view(rng):
    p = rng.uniform(0, 2, size=(3, 16, 20)).astype(np.float32)
    out = M.psnr2d(p, p)
    assert out.shape == (3,) and np.all(np.isinf(out))
    res = M.projection_metrics(p, p)
    assert math.isinf(res["psnr2d"]) and res["ssim2d"] == pytest.approx(1.0)
    assert res["n_views"] == 3 and len(res["psnr2d_per_view"]) == 3
    json.dumps(res)  # JSON-able (inf is written as Infinity)


def test_psnr2d_known_mse_after_own_minmax(rng):
    # gt intensity image whose own min-max normalisation is a known image n
    n = rng.uniform(0.1, 0.8, size=(24, 24))
    n[0, 0], n[-1, -1] = 0.0, 1.0
    gt_int = 0.2 + 0.5 * n  # range [0.2, 0.7]
    noise = np.zeros_like(n)
    noise[5:10, 5:10] = 0.1  # keeps min 0 / max 1 of n untouched
    pred_norm = n + noise
    pred_norm[0, 0], pred_norm[-1, -1] = 0.0, 1.0
    pred_int = 0.05 + 0.9 * pred_norm  # a different affine map: normalisation undoes it
    mse = np.mean((pred_norm - n) ** 2)
    expected = 10 * np.log10(1 / mse)
    got = M.psnr2d(-np.log(pred_int)[None], -np.log(gt_int)[None])
    assert got[0] == pytest.approx(expected, rel=1e-9)
    # same thing given intensities directly
    assert M.psnr2d(pred_int, gt_int, domain="intensity")[0] == pytest.approx(expected, rel=1e-9)
    # and the affine map alone does not change the PSNR (each image normalised by its own range)
    assert M.psnr2d(0.05 + 0.9 * n, gt_int, domain="intensity")[0] > 250  # equal up to rounding


def test_ssim2d_uses_pair_data_range_and_torch_inputs(rng):
    gt = torch.tensor(rng.uniform(0, 1, size=(2, 32, 32)), dtype=torch.float32)
    pred = gt + 0.05 * torch.tensor(rng.standard_normal((2, 32, 32)), dtype=torch.float32)
    s = M.ssim2d(pred, gt)
    assert s.shape == (2,) and np.all(s < 1) and np.all(s > 0.3)
    # worse noise -> lower SSIM
    worse = gt + 0.3 * torch.tensor(rng.standard_normal((2, 32, 32)), dtype=torch.float32)
    assert np.all(M.ssim2d(worse, gt) < s)
    # torch and numpy give the same answer
    assert np.allclose(M.ssim2d(pred.numpy(), gt.numpy()), s)


def test_shape_mismatch_is_one_line_error():
    with pytest.raises(KneasError, match="same shape"):
        M.psnr2d(np.zeros((2, 8, 8)), np.zeros((3, 8, 8)))


# ---------------------------------------------------------------------- 3D
def test_psnr3d_known_value_and_ls_recovers_scale(rng):
    gt = rng.uniform(0, 1, size=(16, 16, 16))
    pred = gt + 0.1  # MSE = 0.01 -> 20 dB at peak 1
    assert M.psnr3d(pred, gt) == pytest.approx(20.0, abs=1e-9)
    assert math.isinf(M.psnr3d(gt, gt))
    scaled = 0.37 * gt
    assert M.psnr3d(scaled, gt) < 15
    assert M.ls_scale(scaled, gt) == pytest.approx(1 / 0.37, rel=1e-12)
    assert M.psnr3d_ls(scaled, gt) > 200  # exact recovery (up to rounding)
    assert M.ssim3d_ls(scaled, gt) == pytest.approx(1.0, abs=1e-9)
    assert M.ssim3d(scaled, gt) < 0.99
    res = M.volume_metrics(scaled, gt)
    assert set(res) >= {"psnr3d", "ssim3d", "psnr3d_ls", "ssim3d_ls", "ls_scale"}
    assert res["psnr3d"] == pytest.approx(M.psnr3d(scaled, gt))


def test_a_scan_in_a_scanners_units_is_also_scored_against_the_truths_peak(rng):
    gt = rng.uniform(0, 1, size=(16, 16, 16))
    gt[0, 0, 0] = 1.0
    pred = gt + 0.01 * rng.standard_normal(gt.shape)
    normalised = M.volume_metrics(pred, gt)
    assert "psnr3d_truth_peak" not in normalised and "ssim3d_truth_range" not in normalised  # NAF's [0, 1]: peak 1 is the truth's
    physical = M.volume_metrics(75 * pred, 75 * gt)  # the same volumes in /m as a scanner gives them
    assert physical["psnr3d"] == pytest.approx(normalised["psnr3d"] - 20 * math.log10(75), abs=1e-6)  # peak 1 is blind to the scale
    assert physical["psnr3d_truth_peak"] == pytest.approx(normalised["psnr3d"], abs=1e-6)
    assert physical["ssim3d_truth_range"] == pytest.approx(M.ssim3d(pred, gt, data_range=1.0 - gt.min()), abs=1e-6)
    assert "psnr3d_truth_peak" not in M.volume_metrics(75 * pred, 75 * gt, data_range=100.0)


def test_nan_volume_rejected():
    v = np.zeros((8, 8, 8))
    v[1, 1, 1] = np.nan
    with pytest.raises(KneasError, match="NaN"):
        M.psnr3d(v, np.zeros((8, 8, 8)))


# ----------------------------------------------------------------- surfaces
def test_chamfer_and_fscore_known_answers(rng):
    a = rng.uniform(-10, 10, size=(500, 3))
    sym, ab, ba = M.chamfer_distance(a, a)
    assert sym == ab == ba == 0.0
    assert M.fscore(a, a, 0.1) == 1.0
    # a flat grid shifted normal to itself by delta: every nearest neighbour is at delta
    g = np.stack(np.meshgrid(np.arange(20.0), np.arange(20.0), [0.0], indexing="ij"), -1).reshape(-1, 3)
    delta = 0.3
    sym, ab, ba = M.chamfer_distance(g, g + [0, 0, delta])
    assert sym == pytest.approx(delta) and ab == pytest.approx(delta) and ba == pytest.approx(delta)
    assert M.fscore(g, g + [0, 0, delta], 0.2) == 0.0
    assert M.fscore(g, g + [0, 0, delta], 0.4) == 1.0
    f, p, r = M.fscore(g[:200], g, 0.01, return_pr=True)
    assert p == 1.0 and r == pytest.approx(0.5) and f == pytest.approx(2 * 0.5 / 1.5)
    with pytest.raises(KneasError, match="empty"):
        M.chamfer_distance(np.zeros((0, 3)), a)


def test_dice():
    a = np.zeros((6, 6, 6), int)
    a[:3] = 1
    a[3:] = 2
    assert M.dice(a, a, 1) == 1.0
    b = np.where(a == 1, 2, 1)  # swapped labels: disjoint
    assert M.dice(b, a, 1) == 0.0
    c = a.copy()
    c[2] = 2  # 1: |A|=72, |B|=108, overlap 72 -> 0.8
    assert M.dice(c, a, 1) == pytest.approx(2 * 72 / 180)
    assert M.dice_per_label(c, a) == {1: pytest.approx(0.8), 2: M.dice(c, a, 2)}


def test_surface_points_are_in_physical_mm_frame():
    g = Geometry.from_mm(mode="cone", DSD=1500.0, DSO=1000.0, nDetector=(8, 8), dDetector=(1.0, 1.0),
                         nVoxel=(24, 20, 16), dVoxel=(2.0, 2.0, 2.0), offOrigin=(3.0, -4.0, 5.0))
    centres_mm = g.voxel_centres(dtype=torch.float64).numpy() * g.mm_per_unit
    c = np.array([10.0, -6.0, 8.0])  # mm, off-centre, inside the 48x40x32 mm box around the offset
    r = 7.0
    mask = np.linalg.norm(centres_mm - c, axis=-1) <= r
    pts = M.surface_points_from_labels(mask.astype(int), g, label=1)
    assert pts.shape[1] == 3 and len(pts) > 100
    assert np.allclose(pts.mean(0), c, atol=0.6)  # centre in the right place on every axis
    radii = np.linalg.norm(pts - c, axis=1)
    assert abs(radii.mean() - r) < 1.0  # staircase surface of a voxelised ball, 2 mm voxels
    assert M.surface_points_from_labels(np.zeros(g.n_voxel, bool), g).shape == (0, 3)
    with pytest.raises(KneasError, match="does not match"):
        M.surface_points_from_labels(np.zeros((3, 3, 3), bool), g)
