"""Material labels, matching and surface metrics against exact ground truth (evaluation.surfaces)."""

import numpy as np
import pytest

from kneas_method.errors import KneasError
from kneas_method.evaluation.surfaces import (
    gt_levels,
    labels_from_weights,
    map_labels,
    match_materials,
    material_metrics,
    membership_grid,
    query_grid,
    visible_fields,
)
from conftest import exact_sphere_model, sphere_scene


@pytest.fixture(scope="module")
def scene():
    return sphere_scene()


def test_exact_sdf_scores_zero_error_and_dice_one(scene):
    model = exact_sphere_model(scene)
    r = material_metrics(model, scene, factor=2)
    voxel_mm = 8.0
    assert r["fscore_threshold_mm"] == pytest.approx(voxel_mm)
    assert [m["gt_label"] for m in r["matching"]] == [1, 2]
    for name in ("soft", "bone"):
        m = r["materials"][name]
        assert m["dice"] == pytest.approx(1.0)
        # prediction: marching cubes on the exact SDF; ground truth: marching cubes on the exact
        # membership mask at 2x resolution -> only the mask's staircase (< 1/4 voxel) remains
        assert m["chamfer_mm"] < 0.25 * voxel_mm
        assert m["fscore"] == pytest.approx(1.0)
        assert m["pred_surface_points"] > 100 and m["gt_surface_points"] > 100
    assert r["dice_mean"] == pytest.approx(1.0)
    assert np.allclose(r["dice_matrix"], np.eye(2))


def test_shifted_sdf_error_is_about_half_the_shift(scene):
    shift = 8.0  # one voxel along x: mean nearest distance between the spheres ~ shift/2
    r = material_metrics(exact_sphere_model(scene, shift_mm=(shift, 0.0, 0.0)), scene, factor=2)
    for name in ("soft", "bone"):
        m = r["materials"][name]
        assert 0.3 * shift < m["chamfer_mm"] < 0.7 * shift
        assert m["dice"] < 0.9
    # the finer the ground-truth grid, the smaller the exact-SDF error
    exact2 = material_metrics(exact_sphere_model(scene), scene, factor=2)["materials"]["soft"]["chamfer_mm"]
    exact3 = material_metrics(exact_sphere_model(scene), scene, factor=3)["materials"]["soft"]["chamfer_mm"]
    assert exact3 < exact2


def test_labels_from_weights_air_threshold():
    w = np.array([[0.1, 0.2], [0.6, 0.1], [0.2, 0.5], [0.3, 0.3]])
    assert labels_from_weights(w).tolist() == [0, 1, 2, 1]
    assert labels_from_weights(w, air_threshold=0.65).tolist() == [0, 1, 2, 0]


def test_matching_with_more_and_fewer_materials():
    levels = [0.28, 0.5, 0.9]
    # K = 4 > M = 3: two predicted materials land on the same label
    assert match_materials([0.25, 0.3, 0.55, 1.0], levels) == [1, 1, 2, 3]
    # K = 2 < M = 3
    assert match_materials([0.3, 0.8], levels) == [1, 3]
    pred = np.array([0, 1, 2, 3, 4], dtype=np.uint8)
    assert map_labels(pred, [1, 1, 2, 3]).tolist() == [0, 1, 1, 2, 3]


def test_a_material_nearest_air_is_air():
    """A near-air material (the partial-volume shell just outside the object) is air, not the
    lowest tissue: its voxels count as air and it has no surface of its own."""
    levels = [0.28, 0.5, 0.9]
    assert match_materials([0.059, 0.3, 0.9], levels) == [0, 1, 3]
    assert match_materials([0.15, 0.3], levels) == [1, 1]  # nearer 0.28 than 0: tissue
    pred = np.array([0, 1, 2, 3], dtype=np.uint8)
    assert map_labels(pred, [0, 1, 3]).tolist() == [0, 0, 1, 3]


def test_a_near_air_shell_does_not_count_as_tissue(scene):
    """Two materials: the outer one is turned into a thin low-attenuation shell around the sphere;
    with air a candidate, the inner material alone is scored against the outer label."""
    from kneas_method.evaluation.surfaces import _score_materials

    gt = np.asarray(scene.labels)
    inside = gt > 0
    # a shell of one voxel around the object, labelled as a predicted material of mu ~ 0.02
    from scipy.ndimage import binary_dilation

    shell = binary_dilation(inside) & ~inside
    pred = np.where(shell, 1, np.where(gt == 1, 2, np.where(gt == 2, 3, 0))).astype(np.uint8)
    levels = gt_levels(scene)
    r = _score_materials(scene, pred, np.array([0.02, levels[0], levels[1]]), None, fine=2, definition="", settings={})
    assert [m["gt_label"] for m in r["matching"]] == [0, 1, 2]
    assert r["matching"][0]["gt_name"] == "air"
    assert r["materials"]["soft"]["dice"] == pytest.approx(1.0)
    assert r["materials"]["bone"]["dice"] == pytest.approx(1.0)


def test_visible_fields_is_the_csg_of_the_selector():
    d = np.array([[-1.0, 0.5, 2.0],    # only material 1 inside -> 1 visible
                  [-1.0, -0.5, 2.0],   # 1 and 2 inside -> 2 covers 1
                  [-1.0, -0.5, -0.2],  # all inside -> 3 visible
                  [1.0, 1.0, 1.0]])    # air
    e = visible_fields(d)
    vis = np.where((e < 0).any(-1), np.argmax(e < 0, -1) + 1, 0)
    assert vis.tolist() == [1, 2, 3, 0]
    assert ((e < 0).sum(-1) <= 1).all()  # at most one visible material per point


def test_query_grid_chunks_agree(scene):
    model = exact_sphere_model(scene)
    a = query_grid(model, scene.geometry, chunk=100_000)
    b = query_grid(model, scene.geometry, chunk=37)
    for k in ("mu", "weights", "distances"):
        assert a[k].dtype == np.float32 and np.allclose(a[k], b[k], atol=1e-5)
    assert a["weights"].shape == (16, 16, 16, 2)
    # the grid is the scene's voxel grid: voxel centre [a, b, c] at (x_a, y_b, z_c)
    pts = scene.geometry.voxel_centres()[3, 5, 7][None]
    assert np.allclose(a["distances"][3, 5, 7], model.query(pts)["distances"][0].detach().numpy(), atol=1e-6)


def test_fine_grid_and_membership(scene):
    fg = scene.geometry.refined(2)
    assert fg.n_voxel == (32, 32, 32) and fg.scale == scene.geometry.scale
    assert np.allclose([n * d for n, d in zip(fg.n_voxel, fg.d_voxel)], [n * d for n, d in zip(scene.geometry.n_voxel, scene.geometry.d_voxel)])
    assert np.array_equal(membership_grid(scene, scene.geometry), scene.labels)
    assert np.allclose(gt_levels(scene), [0.3, 0.8], atol=0.1)


def test_foot_levels_from_the_phantom():
    from kneas_method.data.simulate import simulate_phantom
    from conftest import TINY_SIM

    foot = simulate_phantom("foot", TINY_SIM)
    assert gt_levels(foot).tolist() == [0.28, 0.5, 0.9]


def test_no_labels_is_a_user_error(scene):
    import dataclasses

    bare = dataclasses.replace(scene, labels=None, membership=None)
    with pytest.raises(KneasError, match="ground-truth labels"):
        material_metrics(exact_sphere_model(scene), bare)


def test_matching_uses_the_reconstructed_attenuation_not_the_raw_head():
    """Hard selector: mu = mu_1 * Omega(d_1) can reach soft tissue (0.28) with a raw head at 0.5
    and a half-occupied material; matching must follow what the model reconstructs."""
    from kneas_method.evaluation.surfaces import match_materials, material_mean_attenuation

    labels = np.array([1, 1, 1, 2, 2, 0])
    heads = np.array([[0.5, 0.9]] * 6)
    weights = np.array([[0.56, 0.0]] * 3 + [[0.0, 1.0]] * 2 + [[0.1, 0.0]])
    mu = np.array([0.28, 0.28, 0.28, 0.9, 0.9, 0.05])
    levels = [0.28, 0.5, 0.9]
    assert match_materials(material_mean_attenuation(heads, weights, labels), levels) == [2, 3]  # raw heads: marrow
    mean = material_mean_attenuation(heads, weights, labels, mu=mu)
    assert np.allclose(mean, [0.28, 0.9]) and match_materials(mean, levels) == [1, 3]


class ShellModel:
    """Stands in for a trained K = 3 model on the sphere scene: soft tissue (the big sphere),
    bone (the small one) and, between them, a partial-volume shell 7 mm thick (under one 8 mm
    voxel) around the bone, labelled a third material. Its attenuation ramps as an edge's
    does: 0.72 on the bone's side, 0.45 on the soft tissue's; its mean, 0.58, matches it to bone."""

    has_surfaces = True
    num_materials = 3

    def __init__(self, geometry, shell_mm: float = 7.0, inner_mm: float = 3.5):
        self.geometry, self.shell_mm, self.inner_mm = geometry, shell_mm, inner_mm

    def query(self, points):
        import torch

        from conftest import BIG, SMALL, sphere_sdf_model_units

        mm = self.geometry.mm_per_unit
        shell = (SMALL[0], SMALL[1] + self.shell_mm)
        d = sphere_sdf_model_units(points, self.geometry, spheres=(BIG, shell, SMALL))  # [P, 3]
        e = torch.from_numpy(visible_fields(d.numpy()))
        lab = torch.where((e < 0).any(-1), (e < 0).float().argmax(-1) + 1, torch.zeros(len(points), dtype=torch.long))
        weights = torch.nn.functional.one_hot(lab, 4)[:, 1:].float()
        ramp = torch.where(d[:, 2] * mm < self.inner_mm, torch.tensor(0.72), torch.tensor(0.45))
        mu = torch.stack([torch.zeros(len(points)), torch.full((len(points),), 0.3), ramp, torch.full((len(points),), 0.8)], -1)
        mu = mu.gather(1, lab[:, None])[:, 0]
        return {"distances": d, "weights": weights, "mu": mu, "mu_materials": torch.tensor([0.3, 0.58, 0.8]).expand(len(points), 3)}


def test_a_partial_volume_shell_matched_to_bone_is_split_at_its_edge_midpoint(scene):
    model = ShellModel(scene.geometry)
    raw = material_metrics(model, scene, factor=2, shells=False)
    clean = material_metrics(model, scene, factor=2)
    assert [m["gt_label"] for m in raw["matching"]] == [1, 2, 2]
    assert clean["shells_relabelled"] and not raw["shells_relabelled"]
    assert clean["shell_cells_moved"]["surface_grid_cells"]["2"] > 0
    assert clean["shell_cells_moved"]["voxels"]["2"] > 0
    bone_raw, bone = raw["materials"]["bone"], clean["materials"]["bone"]
    # as is, the bone's surface is the shell's outside, 7 mm out; split at the ramp, 3.5 mm
    assert bone_raw["chamfer_mm"] > 5.0
    assert bone["chamfer_mm"] < bone_raw["chamfer_mm"] - 2.0
    assert bone["dice"] > bone_raw["dice"]
    assert clean["materials"]["soft"]["dice"] >= raw["materials"]["soft"]["dice"]
