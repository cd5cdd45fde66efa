"""The classical start's stages (options beside the paper's procedure; the refine-classical procedure's):
bounds on the start's volume, the warm start and the anchor."""

import dataclasses
import json

import numpy as np
import pytest
import torch
from scipy import ndimage

from kneas_method import presets, registry
from kneas_method.data.naf import load_naf
from kneas_method.stages.anchor import build_anchor, edge_trust, label_interior
from kneas_method.stages.volume_fit import fit_in_region
from kneas_method.stages.warm_start import warm_start
from kneas_method.engine.evaluate import sample_volume
from kneas_method.engine.loading import load_run
from kneas_method.engine.trainer import Trainer
from kneas_method.errors import ConfigError, KneasError
from kneas_method.evaluation.metrics import psnr3d

from conftest import run, run_dir_of, simulated_foot


@pytest.fixture(scope="module")
def small_scene(tmp_path_factory):
    return simulated_foot(tmp_path_factory.mktemp("scene"), "smallfoot", 24, 10.0, n_train=8)


def _tiny_config(method="k-neas", **trainer):
    cfg = dataclasses.replace(registry.load("methods", method).config, method=method, preset="tiny")
    cfg = dataclasses.replace(cfg, trainer=dataclasses.replace(cfg.trainer, **trainer))
    return presets.resolve(cfg)


def anchor_loss(trainer, anchor):
    return anchor.loss(trainer.model, trainer.generator)


def test_warm_start_fits_the_volume_and_leaves_training_state_alone(small_scene, tmp_path):
    scene = load_naf(small_scene)
    cfg = _tiny_config()
    target = np.asarray(scene.image, dtype=np.float32)
    trainer = Trainer(cfg, scene, tmp_path, epochs=1, device="cpu", bounds=([0.4, 0.3, 0.4], [0.0, 0.4, 0.7]))
    before = psnr3d(sample_volume(trainer.model, scene.geometry), target)
    sampler = trainer.datamanager.state_dict()
    gen = trainer.generator.get_state().clone()
    opt_state = trainer.optimizer.state_dict()["state"]
    seconds = warm_start(trainer, target - 0.05, steps=150, points_per_step=4096, what="test")  # negatives are clipped
    after = psnr3d(sample_volume(trainer.model, scene.geometry), target)
    assert after > before + 5.0, (before, after)
    assert seconds > 0 and trainer.step == 0
    assert trainer.datamanager.state_dict()["position"] == sampler["position"]
    assert torch.equal(trainer.generator.get_state(), gen) and opt_state == {} == trainer.optimizer.state_dict()["state"]
    assert "warm_start_volume" in trainer.history
    with pytest.raises(KneasError, match="grid"):
        warm_start(trainer, target[:-1], steps=1, points_per_step=16)


def test_warm_start_is_deterministic(small_scene, tmp_path):
    scene = load_naf(small_scene)
    cfg = _tiny_config()
    vols = []
    for i in range(2):
        tr = Trainer(cfg, scene, tmp_path / str(i), epochs=1, device="cpu", bounds=([0.4, 0.3, 0.4], [0.0, 0.4, 0.7]))
        warm_start(tr, np.asarray(scene.image), steps=5, points_per_step=512)
        vols.append(sample_volume(tr.model, scene.geometry))
    assert np.array_equal(vols[0], vols[1])


def test_anchor_loss_is_the_weighted_mse_to_the_prior_volume(small_scene, tmp_path):
    scene = load_naf(small_scene)
    target = np.asarray(scene.image, dtype=np.float32)
    trainer = Trainer(_tiny_config(), scene, tmp_path, epochs=1, device="cpu", bounds=([0.4, 0.3, 0.4], [0.0, 0.4, 0.7]))
    anchor = build_anchor(trainer, target - 0.05, weight=0.5, points_per_step=300)  # negatives are clipped, as in the warm start
    draw = torch.Generator().manual_seed(0)
    draw.set_state(trainer.generator.get_state())
    idx = torch.randint(0, target.size, (300,), generator=draw)
    points = scene.geometry.voxel_centres().reshape(-1, 3)[idx]
    with torch.no_grad():
        expected = 0.5 * torch.mean((trainer.model.query(points)["mu"] - torch.as_tensor(np.clip(target - 0.05, 0, None)).reshape(-1)[idx]) ** 2)
        assert float(anchor_loss(trainer, anchor)) == pytest.approx(float(expected), rel=1e-6)
    assert torch.equal(trainer.generator.get_state(), draw.get_state())  # drawn from the run's generator: resumable
    with pytest.raises(KneasError, match="grid"):
        anchor = build_anchor(trainer, target[:-1], weight=0.5, points_per_step=10)
    anchor = build_anchor(trainer, target, weight=0.0, points_per_step=10)
    assert anchor is None


def test_anchor_edge_contrast_weighs_each_voxel_by_its_trust(small_scene, tmp_path):
    scene = load_naf(small_scene)
    target = np.asarray(scene.image, dtype=np.float32)
    trainer = Trainer(_tiny_config(), scene, tmp_path, epochs=1, device="cpu", bounds=([0.4, 0.3, 0.4], [0.0, 0.4, 0.7]))
    anchor = build_anchor(trainer, target, weight=0.5, points_per_step=300, edge_contrast=0.1)
    trust = edge_trust(target, 0.1).reshape(-1)
    assert np.array_equal(anchor.value_weights.numpy(), trust) and trust.min() < 0.5 and trust.max() == 1.0
    draw = torch.Generator().manual_seed(0)
    draw.set_state(trainer.generator.get_state())
    idx = torch.randint(0, target.size, (300,), generator=draw)
    points = scene.geometry.voxel_centres().reshape(-1, 3)[idx]
    with torch.no_grad():
        squared = (trainer.model.query(points)["mu"] - torch.as_tensor(target).reshape(-1)[idx]) ** 2
        expected = 0.5 * torch.mean(torch.as_tensor(trust)[idx] * squared)
        assert float(anchor_loss(trainer, anchor)) == pytest.approx(float(expected), rel=1e-6)
        assert float(expected) < float(0.5 * torch.mean(squared))  # the edges count less than in the plain MSE
    anchor = build_anchor(trainer, target, weight=0.5, points_per_step=300)
    assert anchor.value_weights is None


def _trainer_with_a_grid(scene_path, tmp_path):
    """``(scene, trainer)``: a tiny k-neas trainer whose 8^3 occupancy grid keeps a box of the volume."""
    from kneas_method.occupancy import box_of

    scene = load_naf(scene_path)
    cfg = _tiny_config()
    cfg = dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, occupancy_grid=True, occupancy_resolution=8))
    trainer = Trainer(cfg, scene, tmp_path, epochs=1, device="cpu", bounds=([0.4, 0.3, 0.4], [0.0, 0.4, 0.7]))
    occ = torch.zeros(8, 8, 8, dtype=torch.bool)
    occ[2:6, 1:7, 3:8] = True
    trainer.model.set_occupancy(occ, *box_of(scene.geometry))
    return scene, trainer


def test_anchor_in_the_hull_draws_only_there_with_the_box_loss_in_expectation(small_scene, tmp_path):
    scene, trainer = _trainer_with_a_grid(small_scene, tmp_path)
    centres = scene.geometry.voxel_centres().reshape(-1, 3)
    inside = trainer.model.occupied(centres) > 0
    target = np.asarray(scene.image, dtype=np.float32).reshape(-1) * inside.numpy()  # 0 where mu is 0 whatever the field
    target = target.reshape(scene.image.shape)
    anchor = build_anchor(trainer, target, weight=0.5, points_per_step=300, region="hull")
    hull = anchor
    share = float(inside.float().mean())
    assert 0.1 < share < 0.9 and len(hull.points) == int(inside.sum())
    assert bool((trainer.model.occupied(hull.points) > 0).all())  # every draw lands in the hull
    assert hull.weight == pytest.approx(0.5 * share)
    with torch.no_grad():  # the whole-set losses: the hull's (weight x share) equals the box's
        in_hull = hull.weight * torch.mean((trainer.model.query(hull.points)["mu"] - hull.targets) ** 2)
        anchor = build_anchor(trainer, target, weight=0.5, points_per_step=300)
        box = anchor
        in_box = box.weight * torch.mean((trainer.model.query(box.points)["mu"] - box.targets) ** 2)
    assert len(box.points) == target.size and float(in_hull) == pytest.approx(float(in_box), rel=1e-5)
    with pytest.raises(KneasError, match="box or hull"):
        anchor = build_anchor(trainer, target, weight=0.5, points_per_step=300, region="everywhere")



def test_anchor_outside_skip_queries_only_the_grid_with_the_same_gradient_there(small_scene, tmp_path):
    """The anchor (``skip_outside``, always in a run): the field is queried only at the draws inside the occupancy
    grid; the value term (loss and gradient) is the one a query of every draw gives, and the label
    term is that query's without the draws outside the grid (the same mean's denominator)."""
    scene, trainer = _trainer_with_a_grid(small_scene, tmp_path)
    target = np.asarray(scene.image, dtype=np.float32) + 0.01  # nonzero outside the grid too: a constant there
    centres = scene.geometry.voxel_centres().reshape(-1, 3)
    inside = trainer.model.occupied(centres) > 0
    params = [p for p in trainer.model.parameters() if p.requires_grad]

    def loss_and_grads(fn):
        trainer.model.zero_grad(set_to_none=True)
        loss = fn()
        grads = torch.autograd.grad(loss, params, allow_unused=True)
        return float(loss.detach()), [torch.zeros_like(p) if g is None else g for p, g in zip(params, grads)]

    for occupancy_weight in (0.0, 0.3):
        anchor = build_anchor(trainer, target, weight=0.5, points_per_step=400, occupancy_weight=occupancy_weight, skip_outside=True)
        a = anchor
        assert torch.equal(a.outside, ~inside) and 0.1 < float(inside.float().mean()) < 0.9
        state = trainer.generator.get_state()
        sizes = []
        query = trainer.model.query
        trainer.model.query = lambda points: sizes.append(len(points)) or query(points)
        try:
            skip_loss, skip_grads = loss_and_grads(lambda: anchor_loss(trainer, anchor))
        finally:
            trainer.model.query = query
        trainer.generator.set_state(state)
        idx = torch.randint(0, len(centres), (400,), generator=trainer.generator)
        assert sizes == [int(inside[idx].sum())] and 0 < sizes[0] < 400  # only the draws inside the grid

        def oracle():  # every draw queried; the labels outside the grid left out of the sum, not the count
            q = query(centres[idx])
            loss = torch.mean((q["mu"] - a.targets[idx]) ** 2)
            if a.label_mask is not None:
                bce = torch.nn.functional.binary_cross_entropy_with_logits(
                    -trainer.model.boundary.s * q["distances"],
                    (a.targets[idx][:, None] > trainer.model.label_thresholds()[None, :]).float(), reduction="none")
                kept = (a.label_mask[idx] & inside[idx]).float()
                loss = loss + occupancy_weight * (bce * kept[:, None]).sum() / (a.label_mask[idx].sum() * bce.shape[-1])
            return 0.5 * loss

        want_loss, want_grads = loss_and_grads(oracle)
        assert skip_loss == pytest.approx(want_loss, rel=1e-5)
        for got, want in zip(skip_grads, want_grads):
            assert torch.allclose(got, want, rtol=1e-4, atol=1e-10)
        assert any(float(g.abs().sum()) > 0 for g in skip_grads)
    anchor = build_anchor(trainer, target, weight=0.5, points_per_step=400, skip_outside=False)
    assert anchor.outside is None  # the naive version queries every draw

def test_volume_fit_queried_only_in_the_grid_keeps_every_draws_mean(small_scene, tmp_path):
    """``volume_loss_dict(queried=...)``: the field is queried only at the points inside the grid;
    the value term (loss and gradient) is a query of every point's, and the label, eikonal and
    curvature terms are its per-point terms summed over the queried points, over every point's count."""
    scene, trainer = _trainer_with_a_grid(small_scene, tmp_path)
    model = trainer.model
    gen = torch.Generator().manual_seed(3)
    centres = scene.geometry.voxel_centres().reshape(-1, 3)
    idx = torch.randint(0, len(centres), (500,), generator=gen)
    points = centres[idx]
    targets = torch.as_tensor(np.asarray(scene.image, dtype=np.float32).reshape(-1))[idx] + 0.01
    inside = model.occupied(points) > 0
    assert 50 < int(inside.sum()) < 450
    u = torch.randn(len(points), 3, generator=gen)
    steps = float(min(scene.geometry.d_voxel)) * u / u.norm(dim=-1, keepdim=True)
    params = [p for p in model.parameters() if p.requires_grad]

    def grads_of(loss):
        return [torch.zeros_like(p) if g is None else g for p, g in
                zip(params, torch.autograd.grad(loss, params, allow_unused=True, retain_graph=True))]

    seen = []
    field = model.field.get_outputs
    model.field.get_outputs = lambda x, *a, **k: seen.append(len(x)) or field(x, *a, **k)
    try:
        got = model.volume_loss_dict(points, targets, occupancy_weight=0.3, curvature_weight=0.2, steps=steps, queried=inside)
    finally:
        model.field.get_outputs = field
    assert set(seen) == {int(inside.sum())}  # the field (autograd eikonal) sees only the points inside the grid

    # the oracle: every point queried, each term's per-point values masked, every mean over all points
    q = model.query(points.detach().requires_grad_(True))
    keep = inside.float()[:, None]
    width = float(steps.norm(dim=-1).mean())
    bce = torch.nn.functional.binary_cross_entropy_with_logits(
        -model.boundary.s * q["distances"], (targets[:, None] > model.label_thresholds()[None, :]).float(), reduction="none")
    grads = model.distance_gradients(points)
    eik = (grads.norm(dim=-1) - 1) ** 2
    w = torch.exp(-(q["distances"].detach() / width) ** 2)  # no gradient through the weights
    curv = w * ((grads - model.distance_gradients(points + steps)) ** 2).sum(-1)
    count = len(points) * bce.shape[-1]
    want = {"volume": torch.mean((q["mu"] - targets) ** 2), "occupancy": 0.3 * (bce * keep).sum() / count,
            "eikonal": model.lambda_eikonal * (eik * keep).sum() / count, "curvature": 0.2 * (curv * keep).sum() / count}
    assert set(got) == set(want) | {"total"}
    for key in want:
        assert float(got[key].detach()) == pytest.approx(float(want[key].detach()), rel=1e-4), key
        pairs = list(zip(grads_of(got[key]), grads_of(want[key])))
        scale = max(float(h.abs().max()) for _, h in pairs)
        assert scale > 0 and all(float((g - h).abs().max()) <= 5e-3 * scale for g, h in pairs), key  # float32 double backward
    assert float(want["curvature"].detach()) > 0 and float(want["eikonal"].detach()) > 0


def test_fits_to_a_volume_query_only_the_grid_unless_told(small_scene, tmp_path, monkeypatch):
    """The warm start and the correction fits pass the occupancy grid's draws as ``queried``;
    ``skip_outside=False`` (the naive version) queries every draw."""
    scene, trainer = _trainer_with_a_grid(small_scene, tmp_path)
    target = np.asarray(scene.image, dtype=np.float32)
    calls = []
    loss = trainer.model.volume_loss_dict

    def record(points, targets, **kw):  # the fits' calls (the skip's own inner call passes no ``queried``)
        if "queried" in kw:
            calls.append((points, kw["queried"]))
        return loss(points, targets, **kw)

    monkeypatch.setattr(trainer.model, "volume_loss_dict", record)
    warm_start(trainer, target, steps=3, points_per_step=300, what="test")
    mask = np.zeros(target.shape, dtype=bool)
    mask[4:-4, 4:-4, 4:-4] = True
    fit_in_region(trainer, target, mask, steps=2, points_per_step=200, lr=1e-4, curvature=0.1)
    assert len(calls) == 5
    for points, queried in calls:
        assert torch.equal(queried, trainer.model.occupied(points) > 0) and 0 < int(queried.sum()) < len(points)
    calls.clear()
    fit_in_region(trainer, target, mask, steps=1, points_per_step=200, lr=1e-4, skip_outside=False)
    assert len(calls) == 1 and calls[0][1] is None


def test_edge_trust_is_one_where_flat_and_half_at_the_contrast_step():
    volume = np.zeros((16, 16, 16), dtype=np.float32)
    volume[:, :, 8:] = 1.0  # a step: the 99.5th percentile is 1
    volume[:, :, 4:8] = np.linspace(0.2, 0.8, 4)  # a ramp of 0.2 per voxel before it
    trust = edge_trust(volume, 0.2)
    assert np.allclose(trust[:, :, 5:7], 0.5, atol=1e-6)  # slope 0.2 = contrast x range: half
    assert np.all(trust[:, :, 12:] == 1.0) and np.all(trust[:, :, :2] == 1.0)  # flat: full weight
    assert np.all(edge_trust(volume, 0.05)[:, :, 5:7] < trust[:, :, 5:7])  # a smaller contrast trusts edges less
    assert np.all(edge_trust(np.zeros((4, 4, 4)), 0.2) == 1.0)  # an empty volume: nothing to weigh


def test_occupancy_loss_scores_the_labels_the_values_give(small_scene, tmp_path):
    scene = load_naf(small_scene)
    model = Trainer(_tiny_config(), scene, tmp_path, epochs=1, device="cpu", bounds=([0.4, 0.3, 0.4], [0.0, 0.4, 0.7])).model
    targets = torch.tensor([0.1, 0.3, 0.5, 0.9])  # thresholds 0.2 (alpha_1 / 2), 0.4, 0.7: reach 0, 1, 2, 3 materials
    reached = torch.tensor([[0, 0, 0], [1, 0, 0], [1, 1, 0], [1, 1, 1]], dtype=torch.bool)
    right = torch.where(reached, -0.2, 0.2)  # inside (d < 0) exactly where the value reaches the material
    with torch.no_grad():
        good, bad = float(model.occupancy_loss(right, targets)), float(model.occupancy_loss(-right, targets))
        one_wrong = right.clone()
        one_wrong[2, 1] = 0.2  # the 0.5 voxel left out of material 2
        assert good < float(model.occupancy_loss(one_wrong, targets)) < bad


def test_first_label_threshold_moves_where_material_one_starts(small_scene, tmp_path):
    """Bounds whose material 1 reaches far above its own level (the peaks rule: up to the valley
    before material 2): alpha_1 / 2 = 0.25 would call a 0.18 voxel air; the model's
    ``first_label_threshold`` (half that material's level) puts it in material 1."""
    scene = load_naf(small_scene)
    bounds = ([0.5, 0.2, 0.3], [0.0, 0.5, 0.7])
    default = Trainer(_tiny_config(), scene, tmp_path / "a", epochs=1, device="cpu", bounds=bounds).model
    cfg = _tiny_config()
    cfg = dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, first_label_threshold=0.09))
    told = Trainer(cfg, scene, tmp_path / "b", epochs=1, device="cpu", bounds=bounds).model
    np.testing.assert_allclose(default.label_thresholds().detach().numpy(), [0.25, 0.5, 0.7])
    np.testing.assert_allclose(told.label_thresholds().detach().numpy(), [0.09, 0.5, 0.7])
    targets = torch.tensor([0.05, 0.18, 0.6])
    inside_one = torch.tensor([[0.2, 0.2, 0.2], [-0.2, 0.2, 0.2], [-0.2, -0.2, 0.2]])  # the 0.18 voxel inside material 1
    with torch.no_grad():
        assert float(told.occupancy_loss(inside_one, targets)) < float(default.occupancy_loss(inside_one, targets))
    bad = dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, first_label_threshold=0.7))
    with pytest.raises(ConfigError, match="first_label_threshold"):
        Trainer(bad, scene, tmp_path / "c", epochs=1, device="cpu", bounds=bounds).model.label_thresholds()


def test_anchor_with_occupancy_adds_the_label_term_away_from_the_edges(small_scene, tmp_path):
    scene = load_naf(small_scene)
    target = np.asarray(scene.image, dtype=np.float32)
    trainer = Trainer(_tiny_config(), scene, tmp_path, epochs=1, device="cpu", bounds=([0.4, 0.3, 0.4], [0.0, 0.4, 0.7]))
    anchor = build_anchor(trainer, target, weight=0.5, points_per_step=300, occupancy_weight=0.3)
    interior = label_interior(target, [0.2, 0.4, 0.7]).reshape(-1)
    assert np.array_equal(anchor.label_mask.numpy(), interior) and 0 < interior.mean() < 1
    draw = torch.Generator().manual_seed(0)
    draw.set_state(trainer.generator.get_state())
    idx = torch.randint(0, target.size, (300,), generator=draw)
    points = scene.geometry.voxel_centres().reshape(-1, 3)[idx]
    values = torch.as_tensor(target).reshape(-1)[idx]
    with torch.no_grad():
        q = trainer.model.query(points)
        mse = torch.mean((q["mu"] - values) ** 2)
        labels = trainer.model.occupancy_loss(q["distances"], values, mask=torch.as_tensor(interior)[idx])
        assert float(labels) > 0
        assert float(anchor_loss(trainer, anchor)) == pytest.approx(float(0.5 * (mse + 0.3 * labels)), rel=1e-6)
    anchor = build_anchor(trainer, target, weight=0.5, points_per_step=300)
    assert anchor.label_mask is None  # no label term, no mask


def test_occupancy_loss_mask_averages_over_the_masked_points_only(small_scene, tmp_path):
    scene = load_naf(small_scene)
    model = Trainer(_tiny_config(), scene, tmp_path, epochs=1, device="cpu", bounds=([0.4, 0.3, 0.4], [0.0, 0.4, 0.7])).model
    gen = torch.Generator().manual_seed(3)
    distances, targets = torch.randn(50, 3, generator=gen) * 0.1, torch.rand(50, generator=gen)
    mask = torch.rand(50, generator=gen) > 0.5
    with torch.no_grad():
        whole = float(model.occupancy_loss(distances, targets))
        assert float(model.occupancy_loss(distances, targets, mask=torch.ones(50, dtype=torch.bool))) == pytest.approx(whole, rel=1e-6)
        assert float(model.occupancy_loss(distances, targets, mask=mask)) == pytest.approx(
            float(model.occupancy_loss(distances[mask], targets[mask])), rel=1e-6)
        assert float(model.occupancy_loss(distances, targets, mask=torch.zeros(50, dtype=torch.bool))) == 0.0


def _label_interior_naive(volume, thresholds, margin):
    labels = np.digitize(volume, thresholds)
    out = np.zeros(volume.shape, dtype=bool)
    X, Y, Z = volume.shape
    for x in range(X):
        for y in range(Y):
            for z in range(Z):
                cube = labels[max(0, x - margin):x + margin + 1, max(0, y - margin):y + margin + 1, max(0, z - margin):z + margin + 1]
                out[x, y, z] = bool(np.all(cube == labels[x, y, z]))
    return out


@pytest.mark.parametrize("margin", [0, 1, 2])
def test_label_interior_matches_the_naive_neighbourhood_check(margin):
    rng = np.random.default_rng(margin)
    volume = ndimage.zoom(rng.random((4, 5, 3)), 6, order=0)  # blocks of one label, edges between them
    thresholds = [0.3, 0.6]
    got = label_interior(volume, thresholds, margin)
    assert np.array_equal(got, _label_interior_naive(volume, thresholds, margin))
    assert got.all() == (margin == 0) and got.any()


def test_label_interior_keeps_a_sphere_two_voxels_in_from_its_surface():
    grid = np.indices((21, 21, 21)) - 10
    radius = np.sqrt((grid ** 2).sum(0))
    volume = np.where(radius <= 6, 0.5, 0.0)
    kept = label_interior(volume, [0.25])
    assert kept[radius <= 2.5].all() and not kept[(radius > 5) & (radius <= 6)].any()
    assert kept[radius >= 9.5].all()  # the air two voxels out is kept too


def test_anchor_occupancy_keeps_the_prior_volume_labels(small_scene, tmp_path):
    from kneas_method.evaluation.surfaces import labels_from_weights, query_grid

    scene = load_naf(small_scene)
    # a prior with materials thick enough to have voxels two away from their edges (the
    # 24^3 phantom's are not): two nested cubes (labels 1, 2) in air under the bounds below
    prior = np.full(np.shape(scene.image), 0.05, dtype=np.float32)
    for lo, hi, value in ((3, 21, 0.3), (8, 16, 0.55)):
        prior[lo:hi, lo:hi, lo:hi] = value
    bounds = ([0.4, 0.3, 0.4], [0.0, 0.4, 0.7])
    prior_labels = np.digitize(prior, [0.2, 0.4, 0.7])
    trusted = label_interior(prior, [0.2, 0.4, 0.7])
    assert all(np.any(trusted & (prior_labels == k)) for k in range(3))
    agree = {}
    for occupancy in (0.0, 1.0):
        trainer = Trainer(_tiny_config(epochs=20), scene, tmp_path / str(occupancy), epochs=20, device="cpu", bounds=bounds)
        anchor = build_anchor(trainer, prior, weight=100.0, points_per_step=2048, occupancy_weight=occupancy)
        trainer.train(loss_terms={"anchor": lambda: anchor_loss(trainer, anchor)})
        labels = labels_from_weights(query_grid(trainer.model, scene.geometry, keys=("weights",))["weights"])
        agree[occupancy] = float(np.mean(labels[trusted] == prior_labels[trusted]))
    assert agree[1.0] > agree[0.0] + 0.02, agree


def test_anchor_holds_the_field_near_the_prior_during_projection_training(small_scene, tmp_path):
    scene = load_naf(small_scene)
    target = np.asarray(scene.image, dtype=np.float32)
    scores = {}
    for weight in (0.0, 100.0):
        trainer = Trainer(_tiny_config(epochs=20), scene, tmp_path / str(weight), epochs=20, device="cpu",
                          bounds=([0.4, 0.3, 0.4], [0.0, 0.4, 0.7]))
        anchor = build_anchor(trainer, target, weight=weight, points_per_step=2048)
        trainer.train(loss_terms={} if anchor is None else {"anchor": lambda: anchor_loss(trainer, anchor)})
        scores[weight] = psnr3d(sample_volume(trainer.model, scene.geometry), target)
        assert ("anchor" in trainer.history) == (weight > 0)
    assert scores[100.0] > scores[0.0] + 1.0, scores


def test_the_stages_settings_check_themselves():
    base = registry.load("methods", "k-neas").config
    cpu = presets.resolve(dataclasses.replace(base, preset="cpu"))
    st = cpu.stages
    assert (st.classical_start.algorithm, st.warm_start.steps, st.anchor.weight, st.anchor.weight_at_noise, st.anchor.occupancy,
            st.anchor.edge_contrast) == ("asd-pocs", 300, 0.01, 0.05, 0.03, 0.0)
    assert presets.resolve(cpu) == cpu  # a saved run's config resolves to itself
    lines = " ".join(presets.describe(cpu))
    assert ("anchor: the classical start kept as a prior during training, weight 0.01 (0.05 where the start fits the views to "
            "their noise), its labels away from its edges at weight 0.03") in lines
    for part, setting, value, words in (("anchor", "edge_contrast", -0.1, "--stages.anchor.edge-contrast must be a number >= 0"),
                                        ("anchor", "weight_at_noise", -0.05, "--stages.anchor.weight-at-noise must be a number >= 0"),
                                        ("anchor", "occupancy", float("nan"), "--stages.anchor.occupancy"),
                                        ("warm_start", "steps", 1.5, "stages.warm_start.steps must be an integer"),
                                        ("warm_start", "points", 0, "--stages.warm-start.points must be a whole number >= 1")):
        stages = dataclasses.replace(base.stages, **{part: dataclasses.replace(getattr(base.stages, part), **{setting: value})})
        with pytest.raises(ConfigError, match=words):
            presets.resolve(dataclasses.replace(base, preset="cpu", stages=stages))
    with pytest.raises(ConfigError, match="asd-pocs"):
        stages = dataclasses.replace(base.stages, classical_start=dataclasses.replace(base.stages.classical_start, algorithm="gt"))
        presets.resolve(dataclasses.replace(base, preset="cpu", stages=stages))


START_ONLY = ["--procedure", "refine-classical", "--skip-stages", "correction", "smoothing", "materials-refit", "time-budget"]


def test_k_neas_with_fdk_bounds_and_warm_start(small_scene, tmp_path, capsys):
    outdir = tmp_path / "out"
    code, out, err = run(["k-neas", "--scene", str(small_scene), "--preset", "tiny", "--output-dir", str(outdir), *START_ONLY,
                          "--stages.classical-start.algorithm", "fdk", "--stages.warm-start.steps", "20",
                          "--bounds-k-rule", "bic-valleys", "--bounds-max-materials", "5", "--bounds-min-std", "0.03", "--bounds-gmm-restarts", "2",
                          "--stages.anchor.weight", "0.01", "--stages.anchor.occupancy", "0.03"], capsys)
    assert code == 0, err
    assert "classical start: an FDK reconstruction of the training views" in out and "warm start: fitting the model to the FDK" in out
    assert "model: anchor: the FDK volume kept as a prior, weight 0.01, 4,096 voxel centres per step (the field queried only" in out
    assert "and its labels away from its edges, weight 0.03 inside it" in out
    assert ("bounds: K by the lowest BIC with every boundary a density valley, K = 1..5, the best of 2 GMM starts, components at "
            "least 0.03 x the 99.5th percentile wide, on the voxel values of the FDK start") in out
    assert "prior: training" not in out and "model: warm start done" in out
    run_dir = run_dir_of(out)
    assert not (outdir / "smallfoot" / "neas-1m-prior").exists()  # no prior model was trained
    bounds = json.loads((run_dir / "bounds.json").read_text())
    assert bounds["volume"] == "fdk" and "FDK" in bounds["source"] and bounds["prior_run"] is None
    assert bounds["k_chosen_by"] == "bic-valleys" and sorted(bounds["gmm"]["bic"]) == ["1", "2", "3", "4", "5"]
    assert (bounds["gmm"]["settings"]["k_rule"], bounds["gmm"]["settings"]["min_std"], bounds["gmm"]["settings"]["n_init"]) == ("bic-valleys", 0.03, 2)
    assert bounds["gmm"]["placeable"][str(bounds["K"])] is True and not bounds["warnings"]
    fdk = np.load(run_dir / "fdk_volume.npy")
    assert fdk.shape == (24, 24, 24) and np.isfinite(fdk).all()
    metrics = json.loads((run_dir / "metrics.json").read_text())
    stages = metrics["stages"]
    assert list(stages) == ["classical-start", "warm-start", "anchor"] and stages["classical-start"]["algorithm"] == "fdk"
    assert stages["warm-start"]["seconds"] > 0 and stages["classical-start"]["seconds"] > 0
    assert metrics["bounds_time_s"] == pytest.approx(bounds["fit_time_s"]) and metrics["bounds_time_s"] > 0
    assert metrics["loss_scale"] == 1.0  # a NAF-normalised scan: its losses as they were (engine.loss_scale)
    parts = (metrics["train_time_s"] + stages["warm-start"]["seconds"] + stages["classical-start"]["seconds"] + metrics["bounds_time_s"]
             + metrics["eval_time_s"] + metrics["prior_time_s"])
    assert metrics["wall_time_s"] == pytest.approx(parts)
    # the same data and schedule from scratch: the warm start must not be worse on the volume
    code, out, err = run(["k-neas", "--scene", str(small_scene), "--preset", "tiny", "--output-dir", str(tmp_path / "o2"), *START_ONLY,
                          "warm-start", "anchor", "--stages.classical-start.algorithm", "fdk"], capsys)
    assert code == 0, err
    cold = json.loads((run_dir_of(out) / "metrics.json").read_text())
    assert "warm-start" not in cold["stages"] and metrics["psnr3d"] > cold["psnr3d"]


def test_peaks_bounds_set_where_material_one_labels_start_in_the_saved_run(small_scene, tmp_path, capsys, monkeypatch):
    """The peaks rule's ``first_label_threshold`` (half the first peak) travels from the bounds
    stage into the run's saved config, which re-evaluation and ``--resume`` read. The bounds
    volume is swapped for two noisy plateaus at 0.3 and 0.8, whose histogram has two peaks."""
    from kneas_method.engine import neural_pipeline

    real = neural_pipeline.estimate_bounds

    def two_plateaus(config, scene, run_dir, device, start=None, loss_scale=1.0, **kwargs):
        v = np.asarray(start[0], dtype=np.float64)
        inside = v > 0.5 * np.percentile(v, 99)
        rng = np.random.default_rng(0)
        plateaus = np.where(v > np.percentile(v[inside], 70), 0.8, 0.3) + rng.normal(0, 1e-3, v.shape)
        return real(config, scene, run_dir, device, start=(np.where(inside, plateaus, 0.0), start[1]), loss_scale=loss_scale, **kwargs)

    monkeypatch.setattr(neural_pipeline, "estimate_bounds", two_plateaus)
    code, out, err = run(["k-neas", "--scene", str(small_scene), "--preset", "tiny", "--output-dir", str(tmp_path / "o"),
                          *START_ONLY, "--stages.classical-start.algorithm", "fdk", "--bounds-k-rule", "peaks",
                          "--stages.warm-start.steps", "5", "--trainer.epochs", "1"], capsys)
    assert code == 0, err
    run_dir = run_dir_of(out)
    bounds = json.loads((run_dir / "bounds.json").read_text())
    assert bounds["K"] == 2 and bounds["k_chosen_by"] == "peaks"
    assert bounds["first_label_threshold"] == pytest.approx(0.15, abs=0.003)
    saved = json.loads((run_dir / "config.json").read_text())
    assert saved["model"]["first_label_threshold"] == pytest.approx(bounds["first_label_threshold"])
    assert load_run(run_dir).config.model.first_label_threshold == pytest.approx(bounds["first_label_threshold"])


def test_occupancy_term_gives_a_gradient_where_omega_is_saturated():
    """A material that starts far "outside" (Omega ~ 0) gets no MSE gradient; the occupancy
    cross-entropy still pulls its distance down where the target reaches its bounds."""
    cfg = _tiny_config()
    cfg = dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, s_init=100.0, field_options={"distance_bias": 1.0}))
    model = cfg.model.setup(scale=1.0)
    model.set_bounds([0.4, 0.3, 0.4], [0.0, 0.4, 0.7])
    points = torch.rand(256, 3) - 0.5
    targets = torch.full((256,), 0.9)  # the third material everywhere
    last = model.field.mlp[-1].bias

    def grad_of(weight):
        model.zero_grad()
        losses = model.volume_loss_dict(points, targets, occupancy_weight=weight)
        losses["total"].backward()
        return losses, last.grad[:3].clone()

    losses, g_mse = grad_of(0.0)
    assert "occupancy" not in losses and g_mse.abs().max() < 1e-12
    losses, g_occ = grad_of(0.01)
    assert float(losses["occupancy"].detach()) > 0
    assert (g_occ > 1e-4).all()  # every material's distance is pushed down (inside): the target reaches all three


def test_iterative_classical_start_end_to_end(small_scene, tmp_path, capsys):
    """``--stages.classical-start.algorithm sart``: reconstructed once (with the run's reconstruction
    options), the GMM fitted on it, the model started from it and anchored to it, metrics.json says so."""
    code, out, err = run(["k-neas", "--scene", str(small_scene), "--preset", "tiny", "--output-dir", str(tmp_path / "o"), *START_ONLY,
                          "--stages.classical-start.algorithm", "sart", "--stages.warm-start.steps", "20",
                          "--reconstruction.iterations", "2", "--model.quadrature", "voxel-planes",
                          "--stages.anchor.weight", "0.01", "--stages.anchor.edge-contrast", "0.2"], capsys)
    assert code == 0, err
    assert "on the voxel values of the SART start" in out and "fitting the model to the SART reconstruction" in out
    assert "its values held less at its sharp edges (half at a step of 0.2 of its range per voxel)" in out
    assert "quadrature: one sample where each ray crosses each voxel-centre plane" in out
    run_dir = run_dir_of(out)
    loaded = load_run(run_dir)  # the voxel grid travels in the checkpoint; the rendered evaluation used it
    assert loaded.model.quadrature == "voxel-planes" and loaded.model.voxel_count.tolist() == [24, 24, 24]
    bounds = json.loads((run_dir / "bounds.json").read_text())
    assert bounds["volume"] == "sart" and "SART" in bounds["source"]
    info = json.loads((run_dir / "sart_volume.json").read_text())
    assert info["settings"]["algorithm"] == "sart" and info["settings"]["iterations"] == 2
    assert np.load(run_dir / "sart_volume.npy").shape == (24, 24, 24)
    m = json.loads((run_dir / "metrics.json").read_text())
    assert m["stages"]["classical-start"]["algorithm"] == "sart" and "warm-start" in m["stages"]
    code, _, err = run(["k-neas", "--scene", str(small_scene), "--preset", "tiny", "--output-dir", str(tmp_path / "o2"),
                        *START_ONLY, "--stages.classical-start.algorithm", "sirt"], capsys)
    assert code == 2 and "asd-pocs" in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("how", ["volume", "rendered"])
def test_validation_scores_the_views_as_the_final_evaluation_makes_them(small_scene, tmp_path, how):
    from kneas_method.classical.projector import forward
    from kneas_method.engine.evaluate import render_views
    from kneas_method.evaluation.metrics import psnr2d

    scene = load_naf(small_scene)
    cfg = _tiny_config(eval_projections=how, eval_views=2)
    trainer = Trainer(cfg, scene, tmp_path, epochs=1, device="cpu", bounds=([0.4, 0.3, 0.4], [0.0, 0.4, 0.7]))
    idx = np.unique(np.round(np.linspace(0, len(scene.val) - 1, 2)).astype(int))
    angles, truth = np.asarray(scene.val.angles)[idx], np.asarray(scene.val.projections)[idx]
    projected = forward(sample_volume(trainer.model, scene.geometry), scene.geometry, angles)
    rendered = render_views(trainer.model, scene, angles, chunk=int(cfg.trainer.eval_chunk))
    expected = projected if how == "volume" else rendered
    other = rendered if how == "volume" else projected
    assert trainer.validate() == pytest.approx(float(np.mean(psnr2d(expected, truth))), rel=1e-6)
    assert float(np.mean(psnr2d(other, truth))) != pytest.approx(trainer.validate(), rel=1e-6)  # the two ways differ
