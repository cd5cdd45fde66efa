"""Analytic phantoms: exact projections, priority rule, volumes and the built-in anatomy."""

import math

import numpy as np
import pytest
import torch

from kneas_method.data.phantoms import PHANTOM_NAMES, Phantom, Primitive, euler_rotation, get_phantom
from kneas_method.errors import SceneError
from kneas_method.geometry import Geometry


def geom(mode="cone", n_det=(24, 20), d_det=6.0, n_vox=16, d_vox=16.0, **kw):
    return Geometry.from_mm(mode=mode, DSD=1500.0, DSO=1000.0, nDetector=n_det, dDetector=(d_det, d_det),
                            nVoxel=(n_vox,) * 3, dVoxel=(d_vox,) * 3, **kw)


def rays_mm(g, angles):
    o, d = g.rays(torch.as_tensor(np.asarray(angles, dtype=np.float64)), dtype=torch.float64)
    k = g.mm_per_unit
    return o.numpy().reshape(-1, 3) * k, d.numpy().reshape(-1, 3) * k


def single(kind, centre, half, euler=(0, 0, 0), level=0.5):
    return Phantom("one", "one primitive", ("stuff",), (level,), (Primitive(kind, centre, half, 1, 1, euler),))


def sampled_integral(ph, o, d, near, far, n=40000):
    """Reference: midpoint rule of mu along each ray with n samples (metres)."""
    t = near + (np.arange(n) + 0.5) / n * (far - near)
    out = []
    for oi, di in zip(o, d):
        mu = ph.mu_at(oi[None] + t[:, None] * di[None])
        out.append(mu.sum() * (far - near) / n * np.linalg.norm(di) / 1000.0)
    return np.array(out)


# ------------------------------------------------------------------ exact chords
@pytest.mark.parametrize("mode", ["cone", "parallel"])
def test_sphere_projection_matches_closed_form_chord(mode):
    g = geom(mode)
    centre, radius, level = np.array([5.0, -3.0, 2.0]), 30.0, 0.6
    ph = single("ellipsoid", tuple(centre), (radius,) * 3, level=level)
    angles = np.array([0.0, 0.7, 2.0])
    proj = ph.project(g, angles)
    assert proj.shape == (3, 20, 24) and proj.dtype == np.float32
    o, d = rays_mm(g, angles)
    dn = d / np.linalg.norm(d, axis=1, keepdims=True)
    w = centre - o
    dist2 = (w * w).sum(1) - (w * dn).sum(1) ** 2
    chord_mm = 2 * np.sqrt(np.clip(radius ** 2 - dist2, 0, None))
    expect = level * chord_mm / 1000.0
    np.testing.assert_allclose(proj.reshape(-1), expect, atol=2e-7)
    assert (expect > 0).sum() > 20 and (expect == 0).sum() > 20  # both hits and misses exercised


def test_box_and_cylinder_along_rays_give_exact_lengths():
    # parallel beam at theta = 0 travels along -x exactly (zero y, z components)
    g = geom("parallel", n_det=(8, 8), d_det=4.0)
    box = single("box", (3.0, 0.0, 0.0), (25.0, 11.0, 11.0), level=0.4)
    p = box.project(g, [0.0])[0]
    np.testing.assert_allclose(p[2:6, 2:6], 0.4 * 50.0 / 1000.0, rtol=1e-6)  # pixels |u|,|v| <= 6 < 11
    assert np.all(p[[0, 7], :] == 0) and np.all(p[:, [0, 7]] == 0)  # |u| = 14 > 11: miss
    # cylinder whose axis is the ray direction: degenerate quadratic (a = 0)
    cyl = single("cylinder", (0.0, 0.0, 0.0), (9.0, 9.0, 40.0), euler=(0, 90, 0), level=0.3)
    p = cyl.project(g, [0.0])[0]
    np.testing.assert_allclose(p[3:5, 3:5], 0.3 * 80.0 / 1000.0, rtol=1e-6)  # |u|,|v| = 2
    assert p[0, 0] == 0


@pytest.mark.parametrize("kind,half,euler", [
    ("ellipsoid", (40.0, 22.0, 15.0), (30, 20, 10)),
    ("cylinder", (20.0, 12.0, 35.0), (15, 60, -20)),
    ("box", (30.0, 14.0, 20.0), (40, -25, 35)),
])
def test_rotated_primitives_match_sampled_line_integral(kind, half, euler):
    g = geom("cone", n_det=(6, 5), d_det=12.0)
    ph = single(kind, (4.0, -6.0, 3.0), half, euler=euler)
    angles = [0.4]
    o, d = rays_mm(g, angles)
    near, far = g.near_far
    exact = ph.project(g, angles).reshape(-1)
    ref = sampled_integral(ph, o, d, near, far)
    assert (ref > 0).sum() >= 6
    # midpoint rule with 40k samples over ~0.45 units: error <= 2 steps * mu
    step_m = (far - near) / 40000 * np.linalg.norm(d, axis=1) / 1000.0
    assert np.all(np.abs(exact - ref) <= 2 * 0.5 * step_m + 1e-7)


def test_culled_projection_equals_dense_projection():
    ph = get_phantom("foot")
    for g in (geom("cone", offDetector=(7.0, -5.0)), geom("parallel")):
        angles = np.array([0.1, 1.3, 2.9])
        p = ph.project(g, angles, chunk=100)  # tiny chunks: several row batches per view
        o, d = rays_mm(g, angles)
        near, far = g.near_far
        dense = ph.project_rays(o, d, near, far).reshape(p.shape)
        np.testing.assert_allclose(p, dense, atol=1e-7)
        assert p.max() > 0.02


def test_parallel_projection_opposite_views_are_mirror_images():
    g = geom("parallel", n_det=(20, 16), d_det=10.0)
    ph = get_phantom("chest")
    p = ph.project(g, [0.8, 0.8 + math.pi])
    np.testing.assert_allclose(p[1], p[0][:, ::-1], atol=1e-6)


# ---------------------------------------------------------------- priority rule
def nested(marrow_priority):
    prims = (
        Primitive("ellipsoid", (0.0, 0.0, 0.0), (40.0, 40.0, 40.0), 2, 5, name="cortex"),
        Primitive("ellipsoid", (0.0, 0.0, 0.0), (20.0, 20.0, 20.0), 1, marrow_priority, name="marrow"),
    )
    return Phantom("nested", "marrow in cortex", ("marrow", "cortex"), (0.3, 0.9), prims)


def test_priority_rule_nested_marrow_inside_cortex():
    g = geom("parallel", n_det=(2, 2), d_det=1e-3)  # four rays within 1 um of the central axis
    shown, hidden = nested(6), nested(4)
    p_shown = shown.project(g, [0.3]).mean()
    p_hidden = hidden.project(g, [0.3]).mean()
    assert p_shown == pytest.approx((0.9 * 40 + 0.3 * 40) / 1000.0, rel=1e-6)
    assert p_hidden == pytest.approx(0.9 * 80 / 1000.0, rel=1e-6)
    pts = np.array([[0.0, 0.0, 0.0], [30.0, 0.0, 0.0], [0.0, 0.0, 50.0]])
    assert shown.label_at(pts).tolist() == [1, 2, 0]
    assert hidden.label_at(pts).tolist() == [2, 2, 0]
    np.testing.assert_allclose(shown.mu_at(pts), [0.3, 0.9, 0.0])


def test_equal_priority_later_primitive_wins_and_air_cavity_cuts():
    prims = (
        Primitive("box", (0.0, 0.0, 0.0), (30.0, 30.0, 30.0), 1, 1),
        Primitive("box", (10.0, 0.0, 0.0), (10.0, 30.0, 30.0), 2, 1),
        Primitive("ellipsoid", (-15.0, 0.0, 0.0), (5.0, 5.0, 5.0), 0, 3),  # air pocket
    )
    ph = Phantom("t", "t", ("a", "b"), (0.2, 0.8), prims)
    assert ph.label_at(np.array([[15.0, 0, 0], [-5.0, 0, 0], [-15.0, 0, 0]])).tolist() == [2, 1, 0]
    g = geom("parallel", n_det=(2, 2), d_det=1e-3)
    p = ph.project(g, [0.0]).mean()  # along x through everything
    assert p == pytest.approx((0.2 * (40 - 10) + 0.8 * 20) / 1000.0, rel=1e-6)


# ------------------------------------------------------------- points & volumes
def test_label_mu_and_labels_grid_are_consistent():
    g = geom("cone", n_vox=12, d_vox=20.0)
    for name in PHANTOM_NAMES:
        ph = get_phantom(name)
        lab = ph.labels(g)
        assert lab.shape == (12, 12, 12) and lab.dtype == np.uint8
        pts = g.voxel_centres(dtype=torch.float64).numpy().reshape(-1, 3) * g.mm_per_unit
        np.testing.assert_array_equal(lab.reshape(-1), ph.label_at(pts))
        mu = ph.mu_at(pts)
        levels = np.concatenate([[0.0], ph.levels])
        np.testing.assert_allclose(mu, levels[lab.reshape(-1)])
        assert set(np.unique(lab)) <= set(range(len(ph.materials) + 1))


def test_volume_is_partial_volume_mean_and_matches_projection_integral():
    # parallel beam: sum over a projection * pixel area = volume integral of mu
    g = geom("parallel", n_det=(64, 64), d_det=4.0, n_vox=32, d_vox=8.0)
    pix_m2 = (4.0 / 1000.0) ** 2
    vox_m3 = (8.0 / 1000.0) ** 3
    sphere = single("ellipsoid", (7.0, -4.0, 3.0), (50.0, 50.0, 50.0), level=0.5)
    exact = 0.5 * 4 / 3 * math.pi * 0.05 ** 3  # [1/m * m^3]
    proj_int = sphere.project(g, [0.6])[0].sum(dtype=np.float64) * pix_m2
    assert proj_int == pytest.approx(exact, rel=5e-3)
    v1, v3 = sphere.volume(g, supersample=1), sphere.volume(g, supersample=3)
    assert v3.dtype == np.float32 and v3.shape == (32, 32, 32)
    assert ((v3 > 0) & (v3 < 0.5)).any()  # partial-volume voxels on the surface
    assert set(np.unique(v1)) <= {0.0, 0.5}
    assert v3.sum(dtype=np.float64) * vox_m3 == pytest.approx(exact, rel=1.5e-2)
    ph = get_phantom("abdomen")
    proj_int = ph.project(g, [0.3])[0].sum(dtype=np.float64) * pix_m2
    vol_int = ph.volume(g, supersample=3).sum(dtype=np.float64) * vox_m3
    assert vol_int == pytest.approx(proj_int, rel=2e-2)


def test_volume_slab_chunking_does_not_change_result():
    g = geom("cone", n_vox=10, d_vox=24.0)
    ph = get_phantom("jaw")
    np.testing.assert_array_equal(ph.volume(g, supersample=2), ph.volume(g, supersample=2, max_points=500))


# ------------------------------------------------------------ built-in anatomy
def test_registry_and_unknown_name():
    assert PHANTOM_NAMES == ("foot", "jaw", "chest", "abdomen")
    with pytest.raises(SceneError, match="foot, jaw, chest, abdomen"):
        get_phantom("knee")


@pytest.mark.parametrize("name", PHANTOM_NAMES)
def test_builtin_phantom_is_sane(name):
    ph = get_phantom(name)
    assert ph.name == name and ph.description and ph.describe()
    assert 10 <= len(ph.primitives) <= 40
    assert len(ph.materials) == len(ph.levels) >= 3
    assert all(0.0 < v <= 1.0 for v in ph.levels)
    assert list(ph.levels) == sorted(ph.levels)  # labels in ascending attenuation
    lo, hi = ph.bounds_mm()
    assert np.all(lo >= -120.0) and np.all(hi <= 120.0)
    # every material actually appears, and nothing lies outside the +-120 mm cube
    rng = np.random.default_rng(0)
    pts = rng.uniform(-125, 125, size=(60000, 3))
    lab = ph.label_at(pts)
    outside = np.abs(pts).max(1) > 120
    assert np.all(lab[outside] == 0)
    used = {int(p.material) for p in ph.primitives} - {0}
    assert used == set(range(1, len(ph.materials) + 1))
    # not rotationally trivial about z
    inside = pts[lab > 0][:8000]
    for ang in (math.pi / 2, 0.6):
        rz = euler_rotation((math.degrees(ang), 0, 0))
        assert np.mean(ph.label_at(inside @ rz.T) != ph.label_at(inside)) > 0.05


def material_centre_label(ph, name_part):
    ps = [p for p in ph.primitives if name_part in p.name]
    assert ps, name_part
    return ps, ph.label_at(np.array([p.centre for p in ps]))


def unit_surface(kind, rng, n):
    """n points on the surface of the unit shape of ``kind`` (local coordinates)."""
    if kind == "ellipsoid":
        q = rng.normal(size=(n, 3))
        return q / np.linalg.norm(q, axis=1, keepdims=True)
    if kind == "box":
        q = rng.uniform(-1, 1, size=(n, 3))
        return q / np.abs(q).max(1, keepdims=True)
    a = rng.uniform(0, 2 * np.pi, n)
    side = np.stack([np.cos(a), np.sin(a), rng.uniform(-1, 1, n)], 1)
    r = np.sqrt(rng.uniform(0, 1, n))
    cap = np.stack([r * np.cos(a), r * np.sin(a), np.sign(rng.uniform(-1, 1, n))], 1)
    return np.where((np.arange(n) % 2 == 0)[:, None], side, cap)


def test_foot_bones_have_marrow_inside_cortex():
    ph = get_phantom("foot")
    mi, ci = ph.materials.index("marrow") + 1, ph.materials.index("cortical bone") + 1
    assert ph.levels[mi - 1] < ph.levels[ci - 1]
    marrows = [p for p in ph.primitives if p.name.endswith("marrow")]
    assert len(marrows) >= 8
    rng = np.random.default_rng(1)
    for m in marrows:
        cortex = next(p for p in ph.primitives if p.name == m.name.replace("marrow", "cortex"))
        assert cortex.priority < m.priority and ph.label_at(np.array([m.centre]))[0] == mi
        # points on the marrow surface lie inside the cortical primitive (a shell around it)
        q = unit_surface(m.kind, rng, 400) * 0.995
        surf = np.asarray(m.centre) + (q * np.asarray(m.half)) @ m.rotation.T
        assert cortex.contains(surf).all(), m.name
        assert not m.contains((q / 0.995 * 1.01 * np.asarray(m.half)) @ m.rotation.T + np.asarray(m.centre)).any()
    # a ray across the tibia shaft crosses soft tissue, cortex, marrow, cortex, soft tissue
    x = np.linspace(-100, 10, 400)
    line = ph.label_at(np.stack([x, np.full_like(x, 6.0), np.full_like(x, 60.0)], 1))
    runs = [int(v) for i, v in enumerate(line) if i == 0 or v != line[i - 1]]
    assert runs == [0, 1, ci, mi, ci, 1, 0]


def test_jaw_teeth_are_densest_and_chest_lungs_lowest():
    jaw = get_phantom("jaw")
    teeth, lab = material_centre_label(jaw, "tooth")
    assert len(teeth) >= 8
    assert np.all(np.asarray(jaw.levels)[lab - 1] == max(jaw.levels))
    assert max(jaw.levels) >= 0.9 and min(jaw.levels) <= 0.35  # high contrast
    chest = get_phantom("chest")
    lungs, lab = material_centre_label(chest, "lung")
    st = chest.levels[chest.materials.index("soft tissue")]
    assert len(lungs) == 2 and np.all(np.asarray(chest.levels)[lab - 1] < st)
    assert chest.levels[chest.materials.index("lung")] < 0.1


def test_abdomen_has_four_or_more_distinct_levels_present():
    ph = get_phantom("abdomen")
    g = geom("cone", n_vox=24, d_vox=10.0)
    lab = ph.labels(g)
    present = sorted(set(np.unique(lab).tolist()) - {0})
    assert len({ph.levels[i - 1] for i in present}) >= 4
    soft = [v for v in ph.levels if v < 0.4]
    assert len(set(soft)) >= 4  # fat, muscle, liver, kidney


def test_bad_definitions_raise_scene_error():
    with pytest.raises(SceneError):
        Primitive("torus", (0, 0, 0), (1, 1, 1), 1, 1)
    with pytest.raises(SceneError):
        Primitive("box", (0, 0, 0), (1, 0, 1), 1, 1)
    with pytest.raises(SceneError):
        Phantom("x", "x", ("a",), (0.1,), (Primitive("box", (0, 0, 0), (1, 1, 1), 2, 1),))
    with pytest.raises(SceneError):
        get_phantom("foot").label_at(np.zeros((3, 2)))
