"""Partial-volume shells (kneas_method.evaluation.partial_volume) against a naive oracle."""

import itertools

import numpy as np
import pytest

from kneas_method.evaluation.partial_volume import CORE_SHARE, opening_width, relabel_fields, relabel_shells, shell_counts


def naive_relabel(labels, mu, levels, f=1):
    """The rule cell by cell. A cell of k is thin when no w-cube inside k's region holds a cell
    within f cells of it (the grid's edge repeated); its 26-connected piece of k is coreless when
    under 5 % of the piece's cells lie in such cubes. It moves when thin, with a higher label
    within f cells and a lower one: any lower label if the piece is coreless, else a lower
    material (not air). It takes the nearest level among the labels but k with a core cell within
    f cells, and stays k when there is none."""
    lab = np.asarray(labels)
    lv = np.concatenate([[0.0], np.asarray(levels, float)])
    X, Y, Z = lab.shape
    w = opening_width(f)
    clip = lambda i, n: min(max(i, 0), n - 1)  # noqa: E731

    def at(x, y, z):
        return lab[clip(x, X), clip(y, Y), clip(z, Z)]

    def in_cube(x, y, z, k):  # some w-cube holding (x, y, z) lies inside k's region
        for ox, oy, oz in itertools.product(range(w), repeat=3):
            x0, y0, z0 = x - ox, y - oy, z - oz
            if all(at(x0 + a, y0 + b, z0 + c) == k for a, b, c in itertools.product(range(w), repeat=3)):
                return True
        return False

    def around(x, y, z):
        return [(x + a, y + b, z + c) for a, b, c in itertools.product(range(-f, f + 1), repeat=3)]

    def piece(x, y, z):  # the 26-connected cells of the same label
        k, seen, todo = lab[x, y, z], {(x, y, z)}, [(x, y, z)]
        while todo:
            c = todo.pop()
            for d in itertools.product((-1, 0, 1), repeat=3):
                n = (c[0] + d[0], c[1] + d[1], c[2] + d[2])
                if n not in seen and 0 <= n[0] < X and 0 <= n[1] < Y and 0 <= n[2] < Z and lab[n] == k:
                    seen.add(n)
                    todo.append(n)
        return seen

    grid = list(itertools.product(range(X), range(Y), range(Z)))
    core = {c: in_cube(*c, lab[c]) for c in grid}
    out = lab.copy()
    for x, y, z in grid:
        k = int(lab[x, y, z])
        if k == 0 or any(core[cc] and lab[cc] == k for cc in (tuple(clip(p, n) for p, n in zip(c, (X, Y, Z))) for c in around(x, y, z))):
            continue
        cells = piece(x, y, z)
        coreless = sum(core[c] for c in cells) < CORE_SHARE * len(cells)
        near = {int(at(*c)) for c in around(x, y, z)} - {k}
        lower = {j for j in near if lv[j] < lv[k] and (coreless or j != 0)}
        if not lower or not any(lv[j] > lv[k] for j in near):
            continue
        bodies = {int(lab[cc]) for cc in (tuple(clip(p, n) for p, n in zip(c, (X, Y, Z))) for c in around(x, y, z))
                  if core[cc]} - {k}
        if bodies:
            out[x, y, z] = min(sorted(bodies), key=lambda j: abs(mu[x, y, z] - lv[j]))
    return out


def _slab_scene(thickness, shape=(14, 6, 6)):
    """Soft tissue (1, 0.25) | a shell of cancellous bone (2, 0.5) `thickness` cells thick | cortical bone (3, 0.85)."""
    lab = np.ones(shape, np.uint8)
    lab[7:] = 3
    lab[7 - thickness:7] = 2
    mu = np.choose(lab, [0.0, 0.25, 0.5, 0.85]).astype(np.float32)
    return lab, mu


def test_a_one_voxel_shell_between_soft_tissue_and_cortical_bone_goes_to_the_nearer_level():
    lab, mu = _slab_scene(1)
    mu[6] = 0.65  # two thirds cortical: nearer cortical bone (0.85) than soft tissue (0.25)
    mu[6, :, :3] = 0.40  # one third: nearer soft tissue
    out = relabel_shells(lab, mu, [0.25, 0.5, 0.85])
    assert (out == 2).sum() == 0
    assert (out[6, :, 3:] == 3).all() and (out[6, :, :3] == 1).all()
    assert (out[:6] == lab[:6]).all() and (out[7:] == lab[7:]).all()
    assert shell_counts(lab, out) == {2: 36}


def test_a_layer_two_voxels_thick_keeps_its_label():
    lab, mu = _slab_scene(2)
    assert (relabel_shells(lab, mu, [0.25, 0.5, 0.85]) == lab).all()


def test_a_thin_layer_with_nothing_denser_beside_it_is_not_a_shell():
    lab = np.zeros((10, 5, 5), np.uint8)
    lab[3:] = 1
    lab[2] = 2  # a dense skin on the outside: air below, soft tissue below, nothing higher
    mu = np.choose(lab, [0.0, 0.25, 0.5]).astype(np.float32)
    assert (relabel_shells(lab, mu, [0.25, 0.5]) == lab).all()


def test_a_thin_rim_of_a_thick_body_of_the_material_stays_and_a_sheet_beyond_it_does_not():
    """Soft tissue | bone, with a sheet of bone one voxel thick between soft tissue and enamel,
    joined to the bone's thick body: within one voxel of the body it is the body's rim (bone);
    further out it is the edge between soft tissue and enamel."""
    lab = np.ones((14, 8, 8), np.uint8)
    lab[9:, :, :] = 2  # a thick bone body
    lab[3:9, :, 4] = 2  # a sheet of bone one voxel thick, joined to the body
    lab[3:9, :, 5:] = 3  # enamel beside it
    mu = np.choose(lab, [0.0, 0.18, 0.62, 1.0]).astype(np.float32)
    mu[3:9, :, 4] = 0.7  # past the midpoint of soft tissue and enamel
    out = relabel_shells(lab, mu, [0.18, 0.62, 1.0])
    assert (out[8, :, 4] == 2).all()  # the rim, beside the body
    assert (out[3:7, :, 4] == 3).all()  # the sheet's far part: the edge of the enamel
    assert (out[9:] == 2).all()


def test_on_a_twice_finer_grid_the_shell_is_two_cells_and_a_three_cell_layer_stays():
    lab, mu = _slab_scene(2, shape=(16, 6, 6))
    out = relabel_shells(lab, mu, [0.25, 0.5, 0.85], cells_per_voxel=2)
    assert (out == 2).sum() == 0
    lab3, mu3 = _slab_scene(3, shape=(16, 6, 6))
    assert (relabel_shells(lab3, mu3, [0.25, 0.5, 0.85], cells_per_voxel=2) == lab3).all()


@pytest.mark.parametrize("f", [1, 2])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_fast_rule_equals_the_naive_oracle_on_random_label_grids(seed, f):
    rng = np.random.default_rng(seed)
    # blocky random labels, so that thick and thin parts both occur
    coarse = rng.integers(0, 4, size=(4, 4, 3))
    lab = np.kron(coarse, np.ones((3, 2, 3), int))[:10, :7, :8].astype(np.uint8)
    speckle = rng.random(lab.shape) < 0.08  # isolated cells and small clumps: pieces with no core
    lab[speckle] = rng.integers(0, 4, int(speckle.sum()))
    levels = [0.2, 0.45, 0.9]
    mu = (np.choose(lab, [0.0] + levels) + rng.normal(0, 0.15, lab.shape)).astype(np.float32)
    fast = relabel_shells(lab, mu, levels, cells_per_voxel=f)
    assert (fast == naive_relabel(lab, mu, levels, f)).all()
    assert (fast != lab).any()


def test_the_fields_follow_the_new_labels_and_nothing_else_moves():
    lab, mu = _slab_scene(1)
    mu[6] = 0.65
    K = 3
    e = np.full(lab.shape + (K,), 1.0, np.float32)
    for k in range(1, K + 1):
        e[..., k - 1][lab == k] = -1.0
    out = relabel_shells(lab, mu, [0.25, 0.5, 0.85])
    e2 = relabel_fields(e, lab, out, margin=0.1)
    visible = np.where((e2 < 0).any(-1), np.argmax(e2 < 0, -1) + 1, 0)
    assert (visible == out).all()
    same = lab == out
    assert (e2[same] == e[same]).all()
