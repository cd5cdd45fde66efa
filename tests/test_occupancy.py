"""The empty-space grid (visual hull): conservative, carving, exact ray stretches, used by the model."""

import dataclasses

import numpy as np
import pytest
import torch

from kneas_method import methods, presets
from kneas_method.data.simulate import SimulationConfig, simulate_phantom
from kneas_method.datamanagers.ct import noise_air_threshold
from kneas_method.engine.visual_hull import air_test_views
from kneas_method.errors import ConfigError
from kneas_method.occupancy import box_of, occupancy_at, ray_intervals, visual_hull

SIM = SimulationConfig(n_voxel=24, voxel_mm=10.0, n_detector=24, n_train=12, n_val=2)


def naive_stretch(occupied, lo, hi, origin, direction, near, far, min_run: float, n=20000):
    """Oracle: first and last occupied points of one ray on a very fine probe, among the occupied
    runs at least ``min_run`` long (shorter ones are slivers of a cell corner a probe can step over)."""
    t = np.linspace(near, far, n)
    pts = torch.as_tensor(np.asarray(origin)[None] + t[:, None] * np.asarray(direction)[None], dtype=torch.float64)
    hit = occupancy_at(occupied, torch.as_tensor(lo, dtype=torch.float64), torch.as_tensor(hi, dtype=torch.float64), pts).numpy() > 0
    edges = np.flatnonzero(np.diff(np.concatenate([[0], hit.astype(int), [0]])))
    runs = [(t[a], t[b - 1]) for a, b in zip(edges[::2], edges[1::2]) if t[b - 1] - t[a] >= min_run]
    return (None, None) if not runs else (runs[0][0], runs[-1][1])


@pytest.fixture(scope="module", params=["foot", "chest"])
def scene(request):
    return simulate_phantom(request.param, SIM)


@pytest.mark.parametrize("noise", [False, True])
def test_hull_never_drops_material_and_carves_air(scene, noise):
    if noise:
        # a detector of 64 pixels: the noisy views' 7-pixel squares (air_test_views) widen the hull
        # by 3 pixels, a small share of it
        scene = simulate_phantom(scene.name, dataclasses.replace(SIM, noise=True, photons=3e4, n_detector=64))
    views, threshold, _ = air_test_views(scene.train.projections)  # what the model's hull reads
    occ = visual_hull(scene.geometry, scene.train.angles, views, resolution=16, air_threshold=threshold)
    lo, hi = (torch.tensor(v) for v in box_of(scene.geometry))
    # every point that holds material, on a grid 3x finer than the voxels, is in an occupied cell
    g = scene.geometry
    axes = [torch.linspace(l_ + 1e-6, h_ - 1e-6, 3 * n) for l_, h_, n in zip(lo.tolist(), hi.tolist(), g.n_voxel)]
    pts = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    material = torch.as_tensor(scene.membership(pts.numpy())) > 0
    assert material.sum() > 100
    assert bool(occupancy_at(occ, lo, hi, pts)[material].all())
    assert float(occ.float().mean()) < (0.7 if scene.name == "foot" else 1.0)  # it carves (the chest nearly fills its box)


def test_noisy_views_are_smoothed_before_the_air_test_so_faint_real_tissue_is_kept():
    """A real abdomen crop at 3e4 photons: a pixel's noise hides the body's outer voxels from the
    raw 3-sigma air test, which carves hundreds of tissue voxels; the smoothed views keep them all.
    Noise-free views are read as they are."""
    from test_real_anatomy import crop_scene  # the tests' folder is on the path, as for conftest

    from kneas_method.data.simulate import simulate_from_volume

    clean, _, _ = crop_scene()
    views, threshold, smoothing = air_test_views(clean.train.projections)
    assert smoothing == 0 and threshold == 0 and np.array_equal(views, np.asarray(clean.train.projections, dtype=np.float32))
    noisy = simulate_from_volume(clean.image, SimulationConfig(n_detector=32, n_train=8, n_val=4, noise=True, photons=3e4),
                                 voxel_mm=3.0, name="crop-3e4")
    g = noisy.geometry
    lo, hi = (torch.tensor(v, dtype=torch.float64) for v in box_of(g))
    shape = np.array(clean.image.shape)
    idx = torch.as_tensor(np.indices(shape).reshape(3, -1).T, dtype=torch.float64)
    centres = lo + (idx + 0.5) / torch.as_tensor(shape) * (hi - lo)
    tissue = clean.image.reshape(-1) > 0.05

    def dropped(views, threshold):
        occ = visual_hull(g, noisy.train.angles, views, resolution=16, air_threshold=threshold)
        return int((tissue & (occupancy_at(occ, lo, hi, centres).numpy() == 0)).sum())

    assert dropped(noisy.train.projections, noise_air_threshold(noisy.train.projections)[0]) > 100
    views, threshold, smoothing = air_test_views(noisy.train.projections)
    assert smoothing > 0 and threshold < noise_air_threshold(noisy.train.projections)[0] / 3
    assert dropped(views, threshold) == 0


def test_ray_stretches_hold_every_occupied_cell(scene):
    occ = visual_hull(scene.geometry, scene.train.angles, scene.train.projections, resolution=16)
    lo, hi = (torch.tensor(v, dtype=torch.float64) for v in box_of(scene.geometry))
    near, far = scene.geometry.near_far
    origins, directions = scene.geometry.rays([0.3, 1.9], dtype=torch.float64)
    origins, directions = origins.reshape(-1, 3)[::7], directions.reshape(-1, 3)[::7]
    t0, t1 = ray_intervals(occ, lo, hi, origins, directions, near, far, n_probe=256)
    step = (far - near) / 256
    empty = 0
    for r in range(len(origins)):
        a, b = naive_stretch(occ, lo, hi, origins[r].numpy(), directions[r].numpy(), near, far, min_run=step)
        if a is None:
            empty += 1
            continue  # a ray that misses every occupied cell may keep a sliver (probes are coarse); it is 0 there anyway
        assert t0[r] <= a + 1e-9 and t1[r] >= b - 1e-9  # the stretch holds every occupied point
        assert t0[r] >= a - 2 * step and t1[r] <= b + 2 * step  # and little more
    assert empty < len(origins)


def _carved_model(scene):
    """``(config, model)``: a tiny 2-material k-neas model with "material everywhere" before its
    16^3 occupancy grid, the scene's visual hull, carves it."""
    cfg = presets.resolve(dataclasses.replace(methods.k_neas.config, preset="tiny", num_materials=2))
    mc = dataclasses.replace(cfg.model, occupancy_grid=True, occupancy_resolution=16)
    torch.manual_seed(0)
    model = mc.setup(scale=scene.geometry.scale)
    model.set_bounds([0.3, 0.5], [0.0, 0.3])
    with torch.no_grad():
        model.field.mlp[-1].bias[:2] -= 1.0
    occ = visual_hull(scene.geometry, scene.train.angles, scene.train.projections, resolution=16)
    model.set_occupancy(occ, *box_of(scene.geometry))
    return dataclasses.replace(cfg, model=mc), model


def test_model_with_occupancy_grid_is_empty_outside_and_trains(scene):
    cfg, model = _carved_model(scene)
    mc = cfg.model
    pts = scene.geometry.voxel_centres().reshape(-1, 3)
    q = model.query(pts)
    inside = model.occupied(pts) > 0
    assert inside.any() and (~inside).any()
    assert torch.all(q["mu"][~inside] == 0) and torch.all(q["weights"][~inside] == 0) and torch.all(q["distances"][~inside] >= 0)
    assert torch.all(q["mu"][inside] > 0)
    # the grid travels with the weights
    other = mc.setup(scale=scene.geometry.scale)
    other.load_state_dict(model.state_dict())
    assert torch.equal(other.occupancy, model.occupancy) and torch.equal(other.occupancy_box, model.occupancy_box)
    # a training step on the scene's rays
    dm = cfg.datamanager.setup(scene=scene, seed=0)
    batch = dm.next_train()
    losses = model.loss_dict(batch, 0.0)
    losses["total"].backward()
    assert torch.isfinite(losses["total"]) and model.field.encoding.table.grad.abs().sum() > 0


def test_render_views_renders_only_the_rays_through_the_grid_and_the_same_views(scene):
    from kneas_method.engine.evaluate import render_views

    _, model = _carved_model(scene)
    angles = [0.4, 2.2]
    origins, directions = scene.geometry.rays(angles)
    origins, directions = origins.reshape(-1, 3), directions.reshape(-1, 3)
    near, far = scene.geometry.near_far
    hit = model.rays_through_occupied(origins, directions, near, far)
    assert hit.any() and (~hit).any()
    with torch.no_grad():
        every = model.render(origins, directions, near, far, 16, stratified=False).line_integral.reshape(2, *scene.val.projections.shape[1:])
    queried = []
    real_query = model.query
    model.query = lambda points: queried.append(len(points)) or real_query(points)
    rendered = render_views(model, scene, angles, chunk=97, n_samples=16)
    assert sum(queried) == int(hit.sum()) * 16  # only the rays through the grid are rendered
    assert np.allclose(rendered, every.numpy(), atol=1e-6) and float(np.abs(rendered).max()) > 0
    assert np.all(rendered.reshape(-1)[~hit.numpy()] == 0)
    with pytest.raises(ConfigError, match="pass scalars"):  # per-ray limits: one line, not a shape error
        model.render(origins, directions, torch.full((len(origins),), float(near)), far, 16)
    # the volume at the voxel centres: the field queried only inside the grid, the same volume
    from kneas_method.engine.evaluate import sample_volume

    pts = scene.geometry.voxel_centres().reshape(-1, 3)
    with torch.no_grad():
        every = real_query(pts)["mu"].reshape(tuple(scene.geometry.n_voxel)).numpy()
    queried.clear()
    volume = sample_volume(model, scene.geometry, chunk=1000)
    inside = int((model.occupied(pts) > 0).sum())
    assert sum(queried) == inside < len(pts) and np.array_equal(volume, every) and float(volume.max()) > 0
