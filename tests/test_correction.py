"""The band correction (kneas_method.stages.band_correction): its pure functions against naive oracles, the
correction of a known-answer surface model, the noise stop, the fit that writes it into the model,
and the stage in a tiny run (metrics, checkpoint, reloading, resuming)."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import exact_sphere_model, run, run_dir_of, sphere_scene, sphere_scene_file
from kneas_method.classical.projector import Projector
from kneas_method.stages.band_correction import (band_cgls, band_correction, band_fields, box_mean, discretisation_error, edge_band, gradient_magnitude, requery_band,
                                     gradient_weights, interpolate_fields, noise_variance)
from kneas_method.data.simulate import SimulationConfig
from kneas_method.engine.evaluate import sample_volume
from kneas_method.errors import KneasError
from kneas_method.evaluation.metrics import psnr3d

SIM = SimulationConfig(n_voxel=24, voxel_mm=6.0, n_detector=32, n_train=16, n_val=2)


def test_box_mean_matches_a_loop():
    g = torch.Generator().manual_seed(0)
    fine = torch.rand(6, 9, 3, generator=g)
    out = box_mean(fine, 3)
    assert out.shape == (2, 3, 1)
    for a in range(2):
        for b in range(3):
            assert float(out[a, b, 0]) == pytest.approx(float(fine[3 * a:3 * a + 3, 3 * b:3 * b + 3, 0:3].mean()), abs=1e-6)


def test_edge_band_marks_the_step_and_its_neighbours_only():
    v = torch.zeros(12, 12, 12)
    v[6:] = 0.5  # a step between x = 5 and x = 6
    band = edge_band(v, gradient=0.02, dilate=1)
    rows = band.any(-1).any(-1)
    assert rows.tolist() == [False] * 4 + [True] * 4 + [False] * 4  # gradient at 5, 6; dilated to 4..7
    assert torch.equal(edge_band(1000 * v), band)  # relative to the volume's level: any units
    assert not edge_band(torch.full((8, 8, 8), 0.3)).any()


def test_noise_variance_finds_white_noise_and_ignores_smooth_projections():
    g = torch.Generator().manual_seed(1)
    u = torch.linspace(-1, 1, 64)
    smooth = (1 - u[None, :, None] ** 2) * (1 - u[None, None, :] ** 2) * torch.ones(4, 1, 1)
    assert noise_variance(smooth) < 1e-5 * float((smooth * smooth).mean())
    sigma = 0.01
    noisy = smooth + sigma * torch.randn(smooth.shape, generator=g)
    assert noise_variance(noisy) == pytest.approx(sigma ** 2, rel=0.15)
    assert noise_variance(torch.zeros(2, 8, 8)) == 0.0


def _sphere_problem():
    scene = sphere_scene(SIM)
    geometry, angles = scene.geometry, scene.train.angles
    model = exact_sphere_model(scene, shift_mm=(4.0, 0.0, 0.0), sharpness=200.0)  # the spheres 2/3 voxel off
    v = torch.as_tensor(sample_volume(model, geometry))
    b = torch.as_tensor(np.asarray(scene.train.projections, dtype=np.float32))
    return scene, model, v, b


def test_band_cgls_keeps_x_in_the_band_lowers_the_residual_and_honours_the_stop():
    scene, model, v, b = _sphere_problem()
    A = Projector(scene.geometry, scene.train.angles)
    band = edge_band(v)
    r = b - A.forward(v)
    x, history = band_cgls(A, r, band, 4)
    assert len(history) == 5 and all(h1 < h0 for h0, h1 in zip(history, history[1:]))
    assert float(x[~band].abs().max()) == 0.0 and float(x[band].abs().max()) > 0
    assert history[-1] == pytest.approx(float(((r - A.forward(x)) ** 2).mean()), rel=1e-3)  # the tracked residual is the true one
    x0, h0 = band_cgls(A, r, band, 4, stop=lambda res: True)
    assert h0 == history[:1] and float(x0.abs().max()) == 0.0


class _Counting:
    """A projector that counts its forward and back projections."""

    def __init__(self, A):
        self.A, self.forwards, self.backs = A, 0, 0

    def forward(self, volume):
        self.forwards += 1
        return self.A.forward(volume)

    def back(self, projections):
        self.backs += 1
        return self.A.back(projections)


def test_band_cgls_projects_once_each_way_per_iteration():
    scene, model, v, b = _sphere_problem()
    A = _Counting(Projector(scene.geometry, scene.train.angles))
    band = edge_band(v)
    x, history = band_cgls(A, b - A.A.forward(v), band, 3)
    assert len(history) == 4 and (A.forwards, A.backs) == (3, 3)  # no back-projection for a 4th direction


def naive_discretisation_error(model, geometry, volume, band, A, A_fine, *, fine, sharpen):
    """Test oracle: the model queried at every fine centre of the band (twice as sharp edges)."""
    w = torch.nn.functional.interpolate(volume[None, None], scale_factor=fine, mode="trilinear", align_corners=False)[0, 0]
    fine_band = band.repeat_interleave(fine, 0).repeat_interleave(fine, 1).repeat_interleave(fine, 2)
    points = geometry.refined(fine).voxel_centres().reshape(-1, 3)[fine_band.reshape(-1)]
    saved = model.boundary.log_s.data.clone()
    model.boundary.log_s.data += math.log(sharpen) / model.boundary.LOG_SCALE
    with torch.no_grad():
        w[fine_band] = model.query(points)["mu"].float()
    model.boundary.log_s.data = saved
    return A_fine.forward(w) - A.forward(box_mean(w, fine))


def _interpolate_fields_naive(index, table, coords):
    """The oracle: each point's 8 corners indexed by their clamped ``ijk`` one at a time."""
    n = torch.tensor(index.shape)
    out = torch.zeros(len(coords), table.shape[1], dtype=torch.float64)
    for p, c in enumerate(coords.double()):
        low = c.floor()
        t = c - low
        for corner in range(8):
            offset = torch.tensor([(corner >> 2) & 1, (corner >> 1) & 1, corner & 1])
            i, j, k = torch.minimum((low.long() + offset).clamp_min(0), n - 1).tolist()
            weight = torch.where(offset.bool(), t, 1 - t).prod()
            out[p] += weight * table[int(index[i, j, k])].double()
    return out


def test_interpolate_fields_matches_the_naive_corner_by_corner_interpolation_at_the_edges_too():
    g = torch.Generator().manual_seed(1)
    index = torch.randperm(4 * 5 * 6, generator=g).reshape(4, 5, 6).to(torch.int32)  # rows in any order, as band_fields
    table = torch.randn(4 * 5 * 6, 3, generator=g)
    coords = torch.rand(300, 3, generator=g) * torch.tensor([4.0, 5.0, 6.0]) - 0.5  # half a cell beyond each edge
    expected = _interpolate_fields_naive(index, table, coords)
    assert torch.allclose(interpolate_fields(index, table, coords).double(), expected, atol=1e-5)


def test_interpolate_fields_is_exact_on_a_linear_field_and_refuses_corners_not_queried():
    g = torch.Generator().manual_seed(0)
    index = torch.arange(5 * 6 * 7).reshape(5, 6, 7)
    ijk = torch.stack(torch.meshgrid(*(torch.arange(n).float() for n in (5, 6, 7)), indexing="ij"), -1).reshape(-1, 3)
    slope = torch.tensor([[0.3, -1.2], [2.0, 0.5], [-0.7, 1.1]])
    table = ijk @ slope + torch.tensor([0.1, -0.2])
    coords = torch.rand(200, 3, generator=g) * torch.tensor([4.0, 5.0, 6.0])  # inside the grid's centres
    assert torch.allclose(interpolate_fields(index, table, coords), coords @ slope + torch.tensor([0.1, -0.2]), atol=1e-5)
    assert torch.allclose(interpolate_fields(index, table, ijk[:10]), table[:10])  # at the centres: the values
    index[2, 3, 4] = -1
    with pytest.raises(RuntimeError, match="outside the queried band"):
        interpolate_fields(index, table, torch.tensor([[2.5, 3.5, 3.5]]))


def test_discretisation_error_from_interpolated_fields_matches_querying_every_fine_point():
    scene, model, v, b = _sphere_problem()
    geometry, angles = scene.geometry, scene.train.angles
    band = edge_band(v)
    A, A_fine = Projector(geometry, angles), Projector(geometry.refined(3), angles)
    naive = naive_discretisation_error(model, geometry, v, band, A, A_fine, fine=3, sharpen=2.0)
    assert float(naive.abs().max()) > 0
    same_grid = discretisation_error(model, geometry, v, band, A, A_fine, fine=3, sharpen=2.0, coarse=3)
    assert torch.allclose(same_grid, naive, atol=1e-6 * float(naive.abs().max()))  # interpolation at the centres: exact
    coarse = discretisation_error(model, geometry, v, band, A, A_fine, fine=3, sharpen=2.0)  # the default, 2x grid
    deviation = float(((coarse - naive) ** 2).mean())
    assert deviation < 3e-3 * float((naive ** 2).mean())  # 1.1e-3 measured
    truth = b - A.forward(torch.as_tensor(np.asarray(scene.image, dtype=np.float32)))  # the exact data's d
    assert deviation < 0.01 * float(((naive - truth) ** 2).mean())  # far below the estimate's own error
    index, table = band_fields(model, geometry, band, 2)
    assert index.shape == (48, 48, 48) and index.dtype == torch.int32 and table.shape == (int((index >= 0).sum()), 4)  # K = 2: distances, attenuations
    assert bool((index[band.repeat_interleave(2, 0).repeat_interleave(2, 1).repeat_interleave(2, 2)] >= 0).all())
    assert float(model.boundary.log_s.detach()) == pytest.approx(math.log(200.0) / model.boundary.LOG_SCALE)  # sharpness restored


def test_band_correction_moves_a_misplaced_surface_model_towards_the_truth():
    scene, model, v, b = _sphere_problem()
    gt = np.asarray(scene.image, dtype=np.float32)
    result = band_correction(model, v, b, scene.geometry, scene.train.angles, iterations=3, noise_factor=2.0)
    assert result.iterations == 3 and result.residuals[-1] < 0.5 * result.residuals[0]
    before, after = psnr3d(v.numpy(), gt), psnr3d((v + result.grid).clamp_min(0).numpy(), gt)
    assert after > before + 1.0, (before, after)
    assert 0 < result.band_fraction < 0.6
    assert not result.reused and result.to_json()["discretisation"] == "computed"
    again = band_correction(model, v, b, scene.geometry, scene.train.angles, iterations=3, noise_factor=2.0,
                            discretisation=result.discretisation)  # a later pass reusing this pass's d
    assert again.reused and again.to_json()["discretisation"] == "reused" and torch.equal(again.grid, result.grid)
    ignored = band_correction(model, v, b, scene.geometry, scene.train.angles, iterations=3, noise_factor=2.0,
                              discretisation=torch.zeros_like(result.discretisation))
    assert not torch.allclose(ignored.grid, result.grid)  # the d given is the one used
    projectors: dict = {}
    kept = band_correction(model, v, b, scene.geometry, scene.train.angles, iterations=3, noise_factor=2.0, projectors=projectors)
    assert sorted(projectors) == [1, 3] and torch.allclose(kept.grid, result.grid, atol=1e-7)  # the scene's and the 3x grid's
    held = dict(projectors)
    band_correction(model, v, b, scene.geometry, scene.train.angles, iterations=3, noise_factor=2.0, projectors=projectors)
    assert all(projectors[f] is held[f] for f in held)  # a later pass builds no projector (nor its ray tables) again


def test_requery_band_queries_the_band_and_keeps_the_rest():
    scene, model, v, b = _sphere_problem()
    geometry = scene.geometry
    stale = torch.full_like(v, -1.0)  # a volume no model gives: what requery leaves is what it kept
    whole = requery_band(model, geometry, stale, torch.ones_like(v, dtype=torch.bool))
    assert torch.allclose(whole, v, atol=1e-6)  # every voxel in the band: the model's volume
    band = edge_band(v)
    part = requery_band(model, geometry, stale, band)
    assert torch.allclose(part[band], v[band], atol=1e-6) and bool((part[~band] == -1.0).all())
    assert torch.equal(requery_band(model, geometry, stale, torch.zeros_like(band)), stale)


def test_band_cgls_with_weights_is_cgls_on_the_scaled_columns():
    """Column scaling: x = M z with z from CGLS on (A M) z = r; the first iteration checked against
    the steepest-descent step written out (the oracle), and a 0/1 weight is the plain band mask."""
    scene, model, v, b = _sphere_problem()
    from kneas_method.classical.projector import Projector

    A = Projector(scene.geometry, scene.train.angles)
    r = b - A.forward(v)
    band = edge_band(v)
    steep = edge_band(v, dilate=0)
    weights = steep.float() + 0.5 * (band & ~steep).float()
    x, history = band_cgls(A, r, weights, 1)
    # one CGLS step from 0 is the steepest-descent step along s = M A^T r, x = a M s
    s = A.back(r) * weights
    q = A.forward(weights * s)
    expected = float((s * s).sum()) / float((q * q).sum()) * weights * s
    assert torch.allclose(x, expected, rtol=1e-4, atol=1e-7)
    assert float(x[~band].abs().max()) == 0.0 and history[1] < history[0]
    ring = band & ~steep
    plain, _ = band_cgls(A, r, band, 3)
    damped, _ = band_cgls(A, r, weights, 3)
    assert float(damped[ring].abs().mean()) < float(plain[ring].abs().mean())  # the ring's share is damped
    assert torch.equal(band_cgls(A, r, band.float(), 3)[0], plain)  # weights 0/1 are the mask


def test_band_correction_ring_weight_sets_where_it_solves_and_keeps_the_band_for_the_fit():
    scene, model, v, b = _sphere_problem()
    gt = torch.as_tensor(np.asarray(scene.image, dtype=np.float32))
    kw = dict(iterations=3, noise_factor=0.0)
    whole = band_correction(model, v, b, scene.geometry, scene.train.angles, ring=1.0, **kw)
    steep = edge_band(v, dilate=0)
    ring = whole.band & ~steep
    runs = {w: band_correction(model, v, b, scene.geometry, scene.train.angles, ring=w, discretisation=whole.discretisation, **kw)
            for w in (0.0, 0.5)}
    assert all(torch.equal(c.band, whole.band) for c in runs.values()) and int(steep.sum()) < int(whole.band.sum())
    assert float(runs[0.0].grid[~steep].abs().max()) == 0.0 and float(runs[0.0].grid[steep].abs().max()) > 0  # steep only
    assert 0 < float(runs[0.5].grid[ring].abs().mean()) < float(whole.grid[ring].abs().mean())  # the ring damped, not dropped
    for c in (whole, *runs.values()):
        assert c.residuals[-1] < c.residuals[0]
        assert float(((v + c.grid - gt) ** 2).mean()) < float(((v - gt) ** 2).mean())  # towards the truth
    for bad in (-0.1, 1.5):
        with pytest.raises(KneasError, match="correction.ring"):
            band_correction(model, v, b, scene.geometry, scene.train.angles, ring=bad, **kw)


def test_gradient_weights_follow_the_square_root_of_the_gradient_over_the_steep_voxels_median():
    g = torch.Generator().manual_seed(4)
    v = torch.zeros(14, 12, 10)
    v[7:] = 0.4  # a step between x = 6 and 7
    v[2:5, 2:5, 2:5] += 2.0  # a small cube with 5x steeper faces
    v += 0.001 * torch.rand(v.shape, generator=g)
    steep = edge_band(v, dilate=0)
    w = gradient_weights(v, steep)
    gx, gy, gz = np.gradient(v.double().numpy())  # the oracle, in numpy
    magnitude = np.sqrt(gx ** 2 + gy ** 2 + gz ** 2)
    expected = np.sqrt(np.minimum(magnitude / np.median(magnitude[steep.numpy()]), 4.0))
    assert np.allclose(w.numpy(), expected, rtol=1e-4, atol=1e-6)
    assert float(w[6, 9, 8]) == pytest.approx(1.0, abs=0.02)  # the step's voxels hold the median
    assert float(w.max()) == pytest.approx(2.0) and float(w[1, 3, 3]) == pytest.approx(2.0)  # the cube's face: capped
    assert float(w[11, 9, 8]) < 0.1  # flat parts barely move
    assert torch.allclose(gradient_weights(1000 * v, steep), w, atol=1e-5)  # the same whatever the data's units
    assert float(gradient_weights(v, torch.zeros_like(steep)).abs().max()) == 0.0  # nothing steep: nothing moves


def test_band_correction_weighs_the_band_by_its_gradient_when_asked():
    scene, model, v, b = _sphere_problem()
    gt = torch.as_tensor(np.asarray(scene.image, dtype=np.float32))
    kw = dict(iterations=3, noise_factor=0.0)
    by_gradient = band_correction(model, v, b, scene.geometry, scene.train.angles, weighting="gradient", **kw)
    ring = band_correction(model, v, b, scene.geometry, scene.train.angles, discretisation=by_gradient.discretisation, **kw)
    assert torch.equal(by_gradient.band, ring.band) and float(by_gradient.grid[~by_gradient.band].abs().max()) == 0.0
    assert not torch.allclose(by_gradient.grid, ring.grid)  # another solve
    steep = edge_band(v, dilate=0)
    w = gradient_weights(v, steep)
    oracle, _ = band_cgls(Projector(scene.geometry, scene.train.angles), b - Projector(scene.geometry, scene.train.angles).forward(v)
                          - by_gradient.discretisation, by_gradient.band.float() * w, 3)
    assert torch.allclose(by_gradient.grid, oracle, atol=1e-6)  # CGLS with the gradient weights as columns' scale
    assert float(((v + by_gradient.grid - gt) ** 2).mean()) < float(((v - gt) ** 2).mean())  # towards the truth
    with pytest.raises(KneasError, match="correction.weights"):
        band_correction(model, v, b, scene.geometry, scene.train.angles, weighting="steepest", **kw)


def test_band_correction_stops_at_the_noise_of_a_noisy_scan():
    scene, model, v, b = _sphere_problem()
    g = torch.Generator().manual_seed(2)
    noisy = b + 0.05 * float(b.max()) * torch.randn(b.shape, generator=g)  # noise far above the model's misfit
    result = band_correction(model, v, noisy, scene.geometry, scene.train.angles, iterations=3, noise_factor=2.0)
    assert result.iterations == 0 and float(result.grid.abs().max()) == 0.0
    assert result.noise_variance == pytest.approx((0.05 * float(b.max())) ** 2, rel=0.3)


def test_fit_to_volume_moves_the_model_towards_the_target_in_the_mask(tmp_path):
    from kneas_method import presets, registry
    from kneas_method.engine.trainer import Trainer
    from kneas_method.stages.volume_fit import fit_in_region

    scene = sphere_scene(SIM)
    cfg = dataclasses.replace(registry.load("methods", "k-neas").config, method="k-neas", preset="tiny", num_materials=2)
    trainer = Trainer(presets.resolve(cfg), scene, tmp_path, epochs=1, device="cpu", bounds=([0.1, 0.1], [0.25, 0.75]))
    gt = np.asarray(scene.image, dtype=np.float32)
    mask = edge_band(torch.as_tensor(gt)).numpy()
    before = sample_volume(trainer.model, scene.geometry)
    state = {k: v.clone() for k, v in trainer.optimizer.state_dict()["state"].get(0, {}).items()}
    fit_in_region(trainer, gt, mask, steps=60, points_per_step=512, lr=1e-2)
    after = sample_volume(trainer.model, scene.geometry)
    assert np.mean((after - gt)[mask] ** 2) < 0.5 * np.mean((before - gt)[mask] ** 2)
    assert {k: v for k, v in trainer.optimizer.state_dict()["state"].get(0, {}).items()}.keys() == state.keys()  # training optimiser untouched


def test_fit_with_the_curvature_term_smooths_the_surfaces(tmp_path):
    from kneas_method import presets, registry
    from kneas_method.engine.trainer import Trainer
    from kneas_method.losses.curvature import surface_smoothness
    from kneas_method.stages.volume_fit import fit_in_region

    scene = sphere_scene(SIM)
    cfg = dataclasses.replace(registry.load("methods", "k-neas").config, method="k-neas", preset="tiny", num_materials=2)
    gt = np.asarray(scene.image, dtype=np.float32)
    mask = edge_band(torch.as_tensor(gt)).numpy()
    pts = scene.geometry.voxel_centres().reshape(-1, 3)[torch.as_tensor(mask).reshape(-1)]
    h = float(min(scene.geometry.d_voxel))
    u = torch.randn(len(pts), 3, generator=torch.Generator().manual_seed(1))
    steps = h * u / u.norm(dim=-1, keepdim=True)
    smoothness, losses = [], []
    for weight in (0.0, 1.0):
        torch.manual_seed(0)
        trainer = Trainer(presets.resolve(cfg), scene, tmp_path / str(weight), epochs=1, device="cpu", bounds=([0.1, 0.1], [0.25, 0.75]))
        fit_in_region(trainer, gt, mask, steps=60, points_per_step=512, lr=1e-2, curvature=weight)
        model = trainer.model
        d = model.field.distances(pts).detach()
        smoothness.append(float(surface_smoothness(model.distance_gradients(pts), model.distance_gradients(pts + steps), d, h).detach()))
        losses.append(model.volume_loss_dict(pts[:64], torch.as_tensor(gt.reshape(-1))[torch.as_tensor(mask).reshape(-1)][:64],
                                             curvature_weight=weight, steps=steps[:64]))
    assert smoothness[1] < 0.5 * smoothness[0], smoothness
    assert "curvature" not in losses[0] and float(losses[1]["curvature"]) > 0
    losses[1]["curvature"].backward()  # the term reaches the field's parameters
    assert any(p.grad is not None and float(p.grad.abs().sum()) > 0 for p in model.field.parameters())


# the paper's procedure with the band correction added (the paper's fitting settings, so a few steps train a sphere)
CORRECTION = ["--procedure", "paper", "--add-stages", "correction"]


def test_a_run_writes_its_correction_passes_into_the_model(tmp_path, capsys):
    from kneas_method.engine.checkpoint import load_latest_checkpoint
    from kneas_method.engine.loading import load_run

    scene_path = sphere_scene_file(tmp_path)
    argv = ["k-neas", "--scene", str(scene_path), "--preset", "tiny", "--device", "cpu", "--num-materials", "2",
            "--output-dir", str(tmp_path / "out"), *CORRECTION, "time-budget", "--stages.correction.passes", "2", "--trainer.epochs", "20",
            "--stages.correction.noise-factor", "0",  # no noise stop: every pass iterates
            "--stages.correction.steps", "30", "--stages.correction.points", "1024",
            "--stages.time-budget.seconds", "3600"]  # a budget that leaves room for every pass changes nothing
    code, out, err = run(argv, capsys)
    assert code == 0, err
    run_dir = run_dir_of(out)
    metrics = json.loads((run_dir / "metrics.json").read_text())
    record = metrics["stages"]["correction"]
    passes = record["passes"]
    assert record["budget"] is None and "left out" not in out and metrics["stages"]["time-budget"]["training"] is None
    cap = json.loads((run_dir / "config.json").read_text())["stages"]["correction"]["iterations"]
    assert len(passes) == 2 and all(p["iterations"] == cap for p in passes), passes  # no noise stop: the cap
    assert [p["discretisation"] for p in passes] == ["computed", "reused"]  # --stages.correction.refresh 3
    assert all(p["residual_mean_square"][-1] < p["residual_mean_square"][0] for p in passes)
    assert record["seconds"] > 0 and "correction" in out.split("time per stage:")[1]
    # each stage's volume scored against the truth; the last is the evaluation's volume but for what the fits moved
    # outside where the volume is queried again (RunState.model_volume)
    scores = metrics["stage_scores"]
    assert [r["after"] for r in scores] == ["training", "correction"] and "score after correction: psnr3d" in out
    assert math.isclose(scores[-1]["psnr3d"], metrics["psnr3d"], abs_tol=0.1), (scores, metrics["psnr3d"])
    assert scores[-1]["psnr3d"] != scores[0]["psnr3d"]  # the passes moved the volume
    state, _, _ = load_latest_checkpoint(run_dir / "checkpoints", method="k-neas")
    assert state["extra"]["stages"]["correction"]["passes"] == passes and state["step"] == metrics["steps"]
    loaded = load_run(run_dir)  # the corrected model is the run's model: what kneas-eval scores
    assert math.isclose(psnr3d(sample_volume(loaded.model, loaded.scene.geometry), np.asarray(loaded.scene.image, np.float32)),
                        metrics["psnr3d"], abs_tol=1e-4)
    code, out, err = run(["--resume", str(run_dir)], capsys)
    assert code == 0, err


def test_a_time_budget_that_has_run_out_shortens_training_leaves_the_passes_out_and_says_so(tmp_path, capsys):
    from kneas_method.engine.checkpoint import load_latest_checkpoint

    scene_path = sphere_scene_file(tmp_path)
    argv = ["k-neas", "--scene", str(scene_path), "--preset", "tiny", "--device", "cpu", "--num-materials", "2",
            "--output-dir", str(tmp_path / "out"), *CORRECTION, "smoothing", "time-budget", "--stages.correction.passes", "3",
            "--trainer.epochs", "60", "--stages.correction.noise-factor", "0", "--stages.correction.steps", "5",
            "--stages.correction.points", "256", "--stages.time-budget.seconds", "1"]  # spent before training ends (30 s are kept for the end)
    code, out, err = run(argv, capsys)
    assert code == 0, err
    assert "no time for pass 1, so 3 of 3 passes are left out" in out and "--skip-stages time-budget" in out
    assert "100 of the 240 steps (25 of 60 epochs)" in out  # 4 steps an epoch: cut at the 100th step, where it was timed
    run_dir = run_dir_of(out)
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics["steps"] == 100 and metrics["epochs"] == 25
    budget = metrics["stages"]["time-budget"]
    assert budget["training"]["epochs_planned"] == 60 and budget["training"]["epochs"] == 25 and budget["time_budget_s"] == 1.0
    assert json.loads((run_dir / "config.json").read_text())["trainer"]["epochs"] == 25  # what a resumed run trains
    correction = metrics["stages"]["correction"]
    assert correction["passes"] == [] and correction["budget"]["passes_left_out"] == 3 and correction["budget"]["seconds_left"] <= 1.0
    assert metrics["stages"]["smoothing"]["filter"] in ("none", "gaussian", "bilateral")  # still smoothed where needed
    state, _, _ = load_latest_checkpoint(run_dir / "checkpoints", method="k-neas")
    assert state["extra"]["stages"]["correction"]["budget"] == correction["budget"]
    code, out, err = run(["--resume", str(run_dir)], capsys)  # complete: nothing redone
    assert code == 0, err
    assert "already complete" in out


def test_the_budget_counts_from_the_runs_start_not_from_the_passes(tmp_path):
    import time

    from kneas_method import presets, registry
    from kneas_method.engine.trainer import Trainer
    from kneas_method.stages import RunState
    from kneas_method.stages.correction import CorrectionConfig
    from kneas_method.stages.time_budget import TIME_RESERVE_S

    scene = sphere_scene(SIM)
    cfg = dataclasses.replace(registry.load("methods", "k-neas").config, method="k-neas", preset="tiny", num_materials=2)
    cfg = presets.resolve(cfg)
    stage = CorrectionConfig(passes=2, steps=3, points=128, noise_factor=0.0).setup()
    for ago in (1000.0 - TIME_RESERVE_S, 0.0):  # a run that began long ago has spent its budget by the passes
        trainer = Trainer(cfg, scene, tmp_path / str(ago), epochs=1, device="cpu", bounds=([0.1, 0.1], [0.25, 0.75]))
        state = RunState(config=cfg, scene=scene, run_dir=tmp_path / str(ago), device="cpu", started=time.perf_counter() - ago,
                         loss_scale=1.0, say=print, records=trainer.records, trainer=trainer)
        state.deadline = state.started + 1000.0
        stage.run(state)
        done = trainer.records["correction"]
        if ago:
            assert done["passes"] == [] and done["budget"]["passes_left_out"] == 2, done
        else:  # a pass is started (this untrained model's first finds no edge to correct, and ends them)
            assert len(done["passes"]) >= 1 and done["budget"] is None, done
    stage.run(state)  # done: not redone
    assert trainer.records["correction"] is done


def test_a_run_solves_at_the_edges_when_asked(tmp_path, capsys):
    scene_path = sphere_scene_file(tmp_path)
    argv = ["k-neas", "--scene", str(scene_path), "--preset", "tiny", "--device", "cpu", "--num-materials", "2",
            "--output-dir", str(tmp_path / "out"), *CORRECTION, "--stages.correction.passes", "1", "--trainer.epochs", "4",
            "--stages.correction.noise-factor", "0", "--stages.correction.steps", "5", "--stages.correction.points", "256",
            "--stages.correction.ring", "0"]
    code, out, err = run(argv, capsys)
    assert code == 0, err
    assert "CGLS in the band's steep voxels" in out
    saved = json.loads((run_dir_of(out) / "config.json").read_text())
    assert saved["stages"]["correction"]["ring"] == 0.0 and saved["stages"]["correction"]["weights"] == "ring"


def test_older_band_settings_read_as_ring_weights():
    from kneas_method.engine.legacy_config import upgrade

    for solve, weight in (("edges", 0.0), ("band", 1.0)):  # config.json written before 2026-11-27: correction_solve band / edges
        old = {"method": "k-neas", "bounds_volume": "asd-pocs", "trainer": {"warm_start": "asd-pocs", "warm_start_steps": 300,
                                                                             "correction_passes": 12, "correction_solve": solve}}
        stages = upgrade(old, lambda m, x: False)["stages"]
        assert stages["correction"]["ring"] == weight and stages["correction"]["weights"] == "ring"


def test_correction_settings_that_cannot_apply_are_refused(tmp_path, capsys):
    code, out, err = run(["naf", "--scene", "foot", "--preset", "cpu", "--dry-run"], capsys)
    assert code == 0 and "stages: classical-start, time-budget, warm-start, anchor" in out  # no surfaces: no correction
    code, out, err = run(["k-neas", "--scene", "foot", "--preset", "cpu", "--stages.correction.refresh", "0", "--dry-run"], capsys)
    assert code != 0 and "--stages.correction.refresh must be a whole number >= 1, got 0" in err and "Traceback" not in err
    for flag, value, rule in (("--stages.correction.passes", "-1", "a whole number >= 1"), ("--stages.correction.lr", "-1e-4", "a number >= 0"),
                              ("--stages.materials-refit.steps", "-5", "a whole number >= 1"), ("--stages.anchor.points", "0", "a whole number >= 1"),
                              ("--stages.time-budget.seconds", "-1", "a number > 0")):
        code, out, err = run(["k-neas", "--scene", "foot", "--preset", "cpu", flag, value, "--dry-run"], capsys)
        assert code == 2 and f"{flag} must be {rule}, got" in err and "Traceback" not in err
    code, out, err = run(["k-neas", "--scene", "foot", "--preset", "cpu", "--stages.correction.ring", "2", "--dry-run"], capsys)
    assert code != 0 and "--stages.correction.ring must be a number >= 0 and <= 1" in err and "Traceback" not in err
    code, out, err = run(["k-neas", "--scene", "foot", "--preset", "cpu", "--stages.correction.weights", "gradient",
                          "--stages.correction.ring", "0.3", "--dry-run"], capsys)
    assert code != 0 and "--stages.correction.weights ring" in err and "Traceback" not in err  # the ring with the gradient rule


def test_gradient_magnitude_is_the_central_difference_slope_per_voxel():
    x, y, z = np.meshgrid(*(np.arange(12.0),) * 3, indexing="ij")
    ramp = torch.as_tensor(0.03 * x - 0.04 * z + 0.5)  # slope 0.05 per voxel
    assert torch.allclose(gradient_magnitude(ramp), torch.full_like(ramp, 0.05), atol=1e-9)
    smooth = np.sin(0.3 * x) * np.cos(0.2 * y) + 0.1 * z
    naive = np.sqrt(sum(g ** 2 for g in np.gradient(smooth)))  # numpy's central differences, one-sided at the faces
    assert np.allclose(gradient_magnitude(torch.as_tensor(smooth)).numpy(), naive, atol=1e-9)


def test_a_stage_volume_is_scored_only_against_a_truth_on_its_grid():
    from types import SimpleNamespace

    from kneas_method.stages.base import RunState

    truth = np.random.default_rng(0).random((6, 5, 4)).astype(np.float32)
    said = []
    state = RunState(config=None, scene=SimpleNamespace(image=truth), run_dir=Path("."), device="cpu", started=0.0,
                     loss_scale=1.0, say=said.append)
    noisy = truth + 0.01
    row = state.score("warm-start", noisy)
    assert math.isclose(row["psnr3d"], psnr3d(noisy, truth), rel_tol=1e-9) and row["ssim3d"] < 1
    state.score("warm-start", torch.as_tensor(truth))  # a resumed run scores a stage again: one row per stage
    assert [r["after"] for r in state.records["scores"]] == ["warm-start"] and state.records["scores"][0]["ssim3d"] == 1.0
    assert state.score("training", np.zeros((3, 3, 3))) is None  # another grid (a fitting box): not scored
    assert RunState(config=None, scene=SimpleNamespace(image=None), run_dir=Path("."), device="cpu", started=0.0,
                    loss_scale=1.0, say=said.append).score("training", truth) is None  # a scan without truth
    assert len(said) == 2 and "psnr3d" in said[0]
