"""Simulator, geometry defaults, noise, and the volume projector the simulator uses."""

import math

import numpy as np
import pytest
import torch

from kneas_method.data.naf import load_naf, save_naf
from kneas_method.data.simulate import (
    SimulationConfig,
    add_noise,
    make_angles,
    make_geometry,
    simulate_from_volume,
    simulate_phantom,
)
from kneas_method.classical.projector import forward
from kneas_method.errors import ConfigError, KneasError, SceneError


class SphereStandIn:
    """Analytic stand-in phantom: one sphere (radius mm, centre mm, level 1/m)."""

    name = "sphere"
    materials = ("ball",)

    def __init__(self, radius=40.0, centre=(10.0, -5.0, 8.0), level=0.8):
        self.radius, self.centre, self.level = radius, np.asarray(centre, float), level
        self.levels = (level,)

    def label_at(self, pts_mm):
        pts = np.asarray(pts_mm, dtype=np.float64)
        return (np.linalg.norm(pts - self.centre, axis=-1) <= self.radius).astype(np.int64)

    def mu_at(self, pts_mm):
        return self.label_at(pts_mm) * self.level

    def project(self, geometry, angles):
        o, d = geometry.rays(angles, dtype=torch.float64)
        o, d = o.numpy() * geometry.mm_per_unit, d.numpy()
        d = d / np.linalg.norm(d, axis=-1, keepdims=True)
        rel = self.centre - o
        along = np.sum(rel * d, -1)
        dist2 = np.sum(rel * rel, -1) - along**2
        chord_mm = 2 * np.sqrt(np.clip(self.radius**2 - dist2, 0, None))
        return (self.level * chord_mm / 1000.0).astype(np.float32)

    def volume(self, geometry, supersample=3):
        axes = [a.double().numpy() * geometry.mm_per_unit for a in geometry.voxel_axes()]
        d = np.asarray(geometry.d_voxel) * geometry.mm_per_unit
        offs = (np.arange(supersample) + 0.5) / supersample - 0.5
        acc = np.zeros(geometry.n_voxel)
        for ox in offs:
            for oy in offs:
                for oz in offs:
                    pts = np.stack(np.meshgrid(axes[0] + ox * d[0], axes[1] + oy * d[1], axes[2] + oz * d[2], indexing="ij"), -1)
                    acc += self.mu_at(pts)
        return (acc / supersample**3).astype(np.float32)

    def labels(self, geometry):
        pts = geometry.voxel_centres(dtype=torch.float64).numpy() * geometry.mm_per_unit
        return self.label_at(pts).astype(np.uint8)

    def describe(self):
        return f"sphere r={self.radius} mm, mu={self.level}"


TINY = SimulationConfig(n_voxel=16, voxel_mm=8.0, n_detector=16, n_train=4, n_val=4)


def test_default_config_matches_naf_conventions():
    cfg = SimulationConfig()
    assert (cfg.n_voxel, cfg.voxel_mm, cfg.dsd_mm, cfg.dso_mm, cfg.n_train, cfg.n_val) == (128, 2.0, 1500, 1000, 50, 50)
    assert cfg.total_angle_deg == 180 and cfg.noise is False and cfg.random_val_angles


def test_angles_train_even_val_random_in_range():
    cfg = SimulationConfig(n_train=10, n_val=7, total_angle_deg=180, start_angle_deg=30, seed=3)
    train, val = make_angles(cfg)
    expected = np.radians(30 + np.arange(10) * 18.0)
    np.testing.assert_allclose(train, expected, atol=1e-12)
    assert len(val) == 7 and np.all(np.diff(val) >= 0)
    assert np.all(val >= math.radians(30)) and np.all(val < math.radians(210))
    _, val2 = make_angles(cfg)
    np.testing.assert_array_equal(val, val2)  # seeded
    _, val3 = make_angles(SimulationConfig(n_train=10, n_val=7, start_angle_deg=30, seed=4))
    assert not np.allclose(val, val3)
    _, even = make_angles(SimulationConfig(n_train=4, n_val=4, random_val_angles=False))
    np.testing.assert_allclose(np.degrees(even), [22.5, 67.5, 112.5, 157.5])


@pytest.mark.parametrize("mode", ["cone", "parallel"])
def test_detector_sees_the_whole_volume_box_from_every_angle(mode):
    cfg = SimulationConfig(n_voxel=32, voxel_mm=4.0, n_detector=24, mode=mode)
    g = make_geometry(cfg)
    assert g.n_detector == (24, 24)
    # Project the volume box's corners (and edge midpoints) onto the detector for many angles.
    h = np.asarray(g.volume_half_size)
    pts = np.array([[a, b, c] for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1)]) * h
    angles = torch.linspace(0, 2 * math.pi, 361, dtype=torch.float64)
    rot, src = g.rotations(angles).numpy(), g.source_positions(angles).numpy()
    local = np.einsum("nji,npj->npi", rot, pts[None] - src[:, None])  # R^T (x - t)
    if mode == "cone":
        u, v = g.dsd * local[..., 0] / local[..., 2], g.dsd * local[..., 1] / local[..., 2]
    else:
        u, v = local[..., 0], local[..., 1]
    half_det = 12 * g.d_detector[0]
    reach = max(np.abs(u).max(), np.abs(v).max())
    assert reach <= half_det  # nothing of the box falls off the detector
    assert reach > 0.9 * half_det  # and the detector is not needlessly large
    # Projecting a volume of ones: positive in the centre, vanishing at the corners.
    p = forward(np.ones(g.n_voxel, np.float32), g, np.radians([0, 45, 90]))
    assert p[:, 11:13, 11:13].min() > 0 and p[:, 0, 0].max() == 0


def test_geometry_overrides_and_invalid_configs():
    g = make_geometry(SimulationConfig(n_voxel=(8, 10, 12), voxel_mm=3.0, n_detector=20, detector_mm=5.0))
    assert g.n_voxel == (8, 10, 12) and g.n_detector == (20, 20)
    assert math.isclose(g.to_mm()["dDetector"][0], 5.0)
    with pytest.raises(ConfigError, match="mode"):
        make_geometry(SimulationConfig(mode="fan"))
    with pytest.raises(ConfigError, match="dsd_mm"):
        make_geometry(SimulationConfig(dsd_mm=900))
    with pytest.raises(ConfigError, match="n_train"):
        make_geometry(SimulationConfig(n_train=0))
    with pytest.raises(ConfigError, match="dso_mm"):
        make_geometry(SimulationConfig(n_voxel=128, voxel_mm=20.0))


def test_noise_is_poisson_gaussian_and_keeps_negative_values():
    rng = np.random.default_rng(0)
    p = np.full((2, 64, 64), 1.0, np.float32)
    p[0, :8] = 0.0
    noisy = add_noise(p, photons=1e5, electronic_sigma=10.0, rng=rng)
    assert noisy.dtype == np.float32
    air = noisy[0, :8]
    # as TIGRE's noise model: air scatters about 0 on both sides, negative values kept (not clipped at 0)
    assert 0.3 < float(np.mean(air < 0)) < 0.7 and abs(float(air.mean())) < 1e-3
    sel = noisy[1]
    assert abs(float(sel.mean()) - 1.0) < 2e-3
    # std of -log(counts/I0) ~ 1/sqrt(I0 e^-1) for Poisson-dominated noise
    expected = 1 / math.sqrt(1e5 * math.exp(-1))
    assert 0.8 * expected < float(sel.std()) < 1.3 * expected
    few = add_noise(np.full((1, 8, 8), 20.0), photons=100, electronic_sigma=0, rng=rng)
    assert np.allclose(few, math.log(100))  # counts clipped to 1


def test_simulate_phantom_tiny_with_stand_in(tmp_path):
    ph = SphereStandIn()
    scene = simulate_phantom(ph, TINY)
    assert scene.train.projections.shape == (4, 16, 16) and scene.val.projections.shape == (4, 16, 16)
    assert scene.image.shape == (16, 16, 16) and scene.labels.shape == (16, 16, 16)
    assert scene.materials == ("ball",) and scene.meta["phantom"] == "sphere"
    for k in ("accuracy", "filter", "totalAngle", "startAngle", "numTrain", "numVal", "convert", "rescale_slope",
              "rescale_intercept", "normalize", "noise", "randomAngle"):
        assert k in scene.meta
    # central ray of view 0 passes close to the centre: chord ~ 2r
    assert scene.train.projections.max() == pytest.approx(0.8 * 0.080, rel=0.05)
    # membership in model units agrees with the label volume at voxel centres
    centres = scene.geometry.voxel_centres(dtype=torch.float64).reshape(-1, 3).numpy()
    np.testing.assert_array_equal(scene.membership(centres), scene.labels.reshape(-1))
    # it is a valid NAF scene: save and load back
    path = save_naf(scene, tmp_path / "sphere_4.pickle")
    back = load_naf(path)
    np.testing.assert_array_equal(back.train.projections, scene.train.projections)
    np.testing.assert_array_equal(back.image, scene.image)
    assert back.geometry == scene.geometry


def test_simulate_noise_option_changes_projections_reproducibly():
    ph = SphereStandIn()
    clean = simulate_phantom(ph, TINY)
    cfg = SimulationConfig(**{**TINY.to_dict(), "noise": True, "photons": 1e4})
    a, b = simulate_phantom(ph, cfg), simulate_phantom(ph, cfg)
    np.testing.assert_array_equal(a.train.projections, b.train.projections)
    assert not np.array_equal(a.train.projections, clean.train.projections)
    assert a.meta["noise"] == 1 and clean.meta["noise"] == 0
    assert np.abs(a.train.projections - clean.train.projections).mean() < 0.05


def test_volume_projector_agrees_with_exact_projection():
    ph = SphereStandIn(radius=50.0)
    cfg = SimulationConfig(n_voxel=40, voxel_mm=4.0, n_detector=32, n_train=3, n_val=1)
    g = make_geometry(cfg)
    angles = np.radians([0.0, 50.0, 100.0])
    exact = ph.project(g, angles)
    vol = ph.volume(g)
    approx = forward(vol, g, angles)
    assert approx.shape == exact.shape and approx.dtype == np.float32
    obj = exact > 0
    rel = np.abs(approx[obj] - exact[obj]) / exact[obj]
    assert np.median(rel) < 0.01  # measured 0.5 % (the old trilinear ray marcher: the same)
    # partial-volume bleed outside the shadow is small, and the total attenuation is conserved
    assert np.abs(approx[~obj]).max() < 0.2 * exact.max()
    assert approx.sum() == pytest.approx(exact.sum(), rel=0.005)
    # batching changes nothing; float64 work agrees with float32
    np.testing.assert_allclose(forward(vol, g, angles, max_samples=997), approx, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(forward(vol.astype(np.float64), g, angles), approx, rtol=1e-4, atol=1e-6)


def test_volume_projector_uniform_slab_exact_length():
    # A volume of ones, parallel beam along x at angle 0 through the centre: integral = box length.
    cfg = SimulationConfig(n_voxel=(20, 8, 8), voxel_mm=5.0, n_detector=8, mode="parallel")
    g = make_geometry(cfg)
    p = forward(np.ones(g.n_voxel, np.float32), g, [0.0])
    # one sample per voxel slice along x, 20 slices x 5 mm = 100 mm
    assert p[0, 3:5, 3:5] == pytest.approx(0.100, rel=0.005)
    with pytest.raises(KneasError, match="nVoxel"):
        forward(np.ones((4, 4, 4), np.float32), g, [0.0])


def test_simulate_from_volume_uses_projector_and_records_meta():
    ph = SphereStandIn(radius=30.0, centre=(0, 0, 0), level=1.0)
    g = make_geometry(TINY)
    vol = ph.volume(g)
    scene = simulate_from_volume(vol, TINY, meta={"convert": True, "rescale_slope": 2.0})
    assert scene.image.shape == (16, 16, 16) and scene.labels is None
    assert scene.meta["convert"] is True and scene.meta["rescale_slope"] == 2.0
    exact = ph.project(scene.geometry, scene.train.angles)
    obj = exact > 0.01
    assert np.median(np.abs(scene.train.projections[obj] - exact[obj]) / exact[obj]) < 0.1
    with pytest.raises(SceneError, match="negative"):
        simulate_from_volume(-vol, TINY)
    with pytest.raises(SceneError, match="3-D"):
        simulate_from_volume(vol[0], TINY)


# ----------------------------------------------------------------------------- scene resolution
def test_resolve_scene_file_public_and_errors(tmp_path):
    from kneas_method.data.scenes import resolve_scene

    scene = simulate_phantom(SphereStandIn(), TINY)
    path = save_naf(scene, tmp_path / "mine.pickle")
    s = resolve_scene(str(path))
    assert s.source == f"file {path}" and s.name == "mine"
    data = tmp_path / "data"
    save_naf(scene, data / "foot_50.pickle")
    s = resolve_scene("foot", data_dir=data, cache_dir=tmp_path / "cache")
    assert s.name == "foot" and s.source == f"public benchmark {data / 'foot_50.pickle'}"
    assert not (tmp_path / "cache").exists()
    with pytest.raises(SceneError, match="neither an existing file nor a built-in scene .built-in: foot, jaw, chest, abdomen"):
        resolve_scene("knee", data_dir=data)
    with pytest.raises(SceneError, match="neither an existing file"):
        resolve_scene(str(tmp_path / "nope.pickle"), data_dir=data)
    (data / "jaw_50.pickle").write_bytes(b"not a pickle")  # a damaged download that shadows the built-in jaw
    with pytest.raises(SceneError, match=r"jaw_50\.pickle: .*not a readable scene pickle.*stands in for the built-in 'jaw': remove it"):
        resolve_scene("jaw", data_dir=data, cache_dir=tmp_path / "cache")


def test_builtin_scene_cached_and_regenerated_on_config_change(tmp_path, monkeypatch):
    from kneas_method.data import scenes

    tiny = SimulationConfig(n_voxel=8, voxel_mm=30.0, n_detector=8, n_train=2, n_val=1)
    monkeypatch.setattr(scenes, "SimulationConfig", lambda: tiny)  # the "default" config, made tiny
    monkeypatch.setenv("KNEAS_CACHE", str(tmp_path / "envcache"))
    first = scenes.resolve_scene("jaw", data_dir=tmp_path / "nodata")
    path = tmp_path / "envcache" / "jaw_2.pickle"
    assert path.is_file() and first.source == f"built-in phantom jaw (cached at {path})"
    assert first.materials and first.membership is not None and first.labels is not None
    stamp = path.stat().st_mtime_ns
    second = scenes.resolve_scene("jaw", data_dir=tmp_path / "nodata")
    assert path.stat().st_mtime_ns == stamp  # served from the cache
    np.testing.assert_array_equal(second.train.projections, first.train.projections)
    # a changed default config regenerates the cached file
    changed = SimulationConfig(n_voxel=8, voxel_mm=30.0, n_detector=10, n_train=2, n_val=1)
    monkeypatch.setattr(scenes, "SimulationConfig", lambda: changed)
    third = scenes.resolve_scene("jaw", data_dir=tmp_path / "nodata")
    assert third.train.projections.shape == (2, 10, 10)
    # a damaged cache file is replaced, not fatal
    path.write_bytes(b"garbage")
    fourth = scenes.resolve_scene("jaw", data_dir=tmp_path / "nodata")
    assert fourth.train.projections.shape == (2, 10, 10)
    assert sorted(p.name for p in path.parent.iterdir()) == ["jaw_2.pickle"]
