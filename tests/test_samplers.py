
import numpy as np
import pytest
import torch

from kneas_method.data.scene import Scene, Views
from kneas_method.datamanagers.ct import CTDataManagerConfig
from kneas_method.errors import CheckpointError
from kneas_method.geometry import Geometry
from kneas_method.samplers.pixels import ObjectAirPixelSamplerConfig
from kneas_method.samplers.rays import StratifiedRaySamplerConfig

MU_BALL = 2.0  # data units, 1/m
R_BALL_MM = 30.0


def ball_scene(n_views=6, n_det=16):
    """A ball of mu = 2 /m, radius 30 mm, exact cone-beam projections."""
    g = Geometry.from_mm(mode="cone", DSD=1500.0, DSO=1000.0, nDetector=(n_det, n_det), dDetector=(128.0 / n_det * 1.5,) * 2,
                         nVoxel=(16, 16, 16), dVoxel=(8.0, 8.0, 8.0))
    angles = np.linspace(0, np.pi, n_views, endpoint=False)
    o, d = g.rays(angles, dtype=torch.float64)
    r = R_BALL_MM / g.mm_per_unit
    dn = d / d.norm(dim=-1, keepdim=True)
    closest = (o - (o * dn).sum(-1, keepdim=True) * dn).norm(dim=-1)
    chord_model = 2 * torch.sqrt(torch.clamp(r**2 - closest**2, min=0))
    p = (MU_BALL * chord_model / g.scale).float().numpy()
    return Scene(name="ball", geometry=g, train=Views(angles, p), val=Views(angles[:2] + 0.1, p[:2]))


def test_pixel_sampler_object_and_air():
    proj = np.zeros((2, 6, 5), np.float32)
    proj[0, 1:3, 1:4] = 1.0  # 6 object pixels in view 0
    proj[1, :, :] = 0.5
    proj[1, 0, 0] = 0.0  # one air pixel in view 1
    s = ObjectAirPixelSamplerConfig(num_object=4, num_air=3).setup(projections=proj)
    g = torch.Generator().manual_seed(0)
    obj, air = s.sample(0, g)
    assert obj.shape == (4, 2) and air.shape == (3, 2)
    assert np.all(proj[0, obj[:, 0], obj[:, 1]] > 0) and np.all(proj[0, air[:, 0], air[:, 1]] == 0)
    assert len({tuple(x) for x in obj.tolist()}) == 4 and len({tuple(x) for x in air.tolist()}) == 3
    # fewer pixels than asked: all of them, once
    obj, air = ObjectAirPixelSamplerConfig(num_object=100, num_air=100).setup(projections=proj).sample(1, g)
    assert len(obj) == 29 and len({tuple(x) for x in obj.tolist()}) == 29
    assert air.tolist() == [[0, 0]]
    _, air = ObjectAirPixelSamplerConfig(num_object=2, num_air=0).setup(projections=proj).sample(0, g)
    assert air.shape == (0, 2)


def test_stratified_and_even_ray_samples():
    sampler = StratifiedRaySamplerConfig().setup()
    g = torch.Generator().manual_seed(1)
    t = sampler.sample(1.0, 3.0, 50, 8, True, generator=g)
    assert t.shape == (50, 8)
    edges = torch.linspace(1.0, 3.0, 9)
    assert torch.all(t >= edges[:-1] - 1e-6) and torch.all(t <= edges[1:] + 1e-6)
    assert torch.all(t[:, 1:] > t[:, :-1])
    assert t.std(0).min() > 0.05  # jittered
    t2 = sampler.sample(torch.full((4,), 1.0), torch.full((4,), 3.0), 4, 5, False)
    assert torch.allclose(t2, torch.linspace(1.0, 3.0, 5).expand(4, 5))


def make_dm(seed=0, n_object=20, n_air=10, **kw):
    cfg = CTDataManagerConfig(num_object_rays=n_object, num_air_rays=n_air)
    return cfg.setup(scene=ball_scene(**kw), seed=seed)


def test_datamanager_batches():
    dm = make_dm()
    proj = torch.as_tensor(dm.scene.train.projections)
    seen = []
    for _ in range(dm.steps_per_epoch):
        b = dm.next_train()
        seen.append(b["view"])
        assert b["epoch"] == 0
        pix, air = b["pixels"], b["is_air"]
        assert b["origins"].shape == b["directions"].shape == (30, 3)
        assert air.sum() == 10 and (~air).sum() == 20 and not air[:20].any()
        values = proj[b["view"], pix[:, 0], pix[:, 1]]
        assert torch.all(values[~air] > 0) and torch.all(values[air] == 0)
        assert torch.equal(b["projections"], values)
        assert len({tuple(x) for x in pix.tolist()}) == 30  # without replacement
        o, d = dm.geometry.rays(dm.scene.train.angles[b["view"] : b["view"] + 1], pixels=pix[None])
        assert torch.allclose(b["directions"], d[0]) and torch.allclose(b["origins"], o[0])
    assert sorted(seen) == list(range(dm.num_train_views))  # one step per view per epoch
    assert dm.next_train()["epoch"] == 1
    assert (b["near"], b["far"]) == dm.geometry.near_far


def test_datamanager_views_subsampling_and_seed():
    cfg = CTDataManagerConfig(num_object_rays=8, num_air_rays=2)
    dm = cfg.setup(scene=ball_scene(), seed=0, views=3)
    assert dm.num_train_views == 3
    a = [make_dm(seed=3).next_train()["pixels"] for _ in range(2)]
    assert torch.equal(a[0], a[1])
    assert not torch.equal(a[0], make_dm(seed=4).next_train()["pixels"])


def test_datamanager_state_dict_resume_reproduces_batches():
    straight = make_dm(seed=7)
    for _ in range(8):  # past an epoch boundary (6 views)
        straight.next_train()
    state = straight.state_dict()
    expected = [straight.next_train() for _ in range(7)]
    resumed = make_dm(seed=123)  # a different seed: the state must carry everything
    resumed.load_state_dict(state)
    for e in expected:
        b = resumed.next_train()
        assert b["view"] == e["view"] and b["epoch"] == e["epoch"]
        assert torch.equal(b["pixels"], e["pixels"])
    with pytest.raises(CheckpointError, match="training views"):
        make_dm(n_views=4).load_state_dict(state)


def test_ball_scene_has_object_and_air():
    s = ball_scene()
    p = s.train.projections
    assert (p > 0).sum() > 50 and (p == 0).sum() > 50
    # central ray crosses the full diameter: p = mu * 2r (in metres)
    assert p.max() == pytest.approx(MU_BALL * 2 * R_BALL_MM / 1000, rel=0.05)
