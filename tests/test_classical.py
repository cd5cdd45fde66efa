"""Classical reconstruction: the matched projector pair and SART / OS-SART / CGLS / ASD-POCS."""

import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from kneas_method.classical import (
    Projector,
    VoxelBackprojector,
    asd_pocs,
    back,
    cgls,
    choose_backprojector,
    forward,
    os_sart,
    pixels_per_voxel,
    sart,
    spread_order,
    total_variation,
)
from kneas_method.data.simulate import SimulationConfig, make_geometry, simulate_phantom
from kneas_method.errors import ConfigError, KneasError
from kneas_method.evaluation.metrics import psnr3d


def small_geometry(mode, offsets=False):
    """20 x 24 x 16 voxels of 5 x 6 x 7 mm, 30 x 30 detector; optional detector and volume offsets."""
    g = make_geometry(SimulationConfig(n_voxel=(20, 24, 16), voxel_mm=(5.0, 6.0, 7.0), n_detector=30, mode=mode))
    if offsets:
        g = replace(g, off_detector=(3.5 * g.d_detector[0], -2.2 * g.d_detector[1]),
                    off_origin=(2.0 * g.d_voxel[0], -1.5 * g.d_voxel[1], 1.0 * g.d_voxel[2]))
    return g


ANGLES = np.linspace(0.0, np.pi, 7, endpoint=False) + 0.1


@pytest.fixture(scope="module")
def tiny():
    """The built-in foot phantom at 24^3 (10 mm voxels), 32^2 detector, 20 training views."""
    return simulate_phantom("foot", SimulationConfig(n_voxel=24, voxel_mm=10, n_detector=32, n_train=20, n_val=4))


def relative_residual(scene, volume):
    b = scene.train.projections
    return float(np.linalg.norm(forward(volume, scene.geometry, scene.train.angles) - b) / np.linalg.norm(b))


# --------------------------------------------------------------------------------- projector
@pytest.mark.parametrize("mode", ["cone", "parallel"])
@pytest.mark.parametrize("offsets", [False, True])
def test_back_is_the_exact_adjoint_of_forward(mode, offsets):
    g = small_geometry(mode, offsets)
    rng = np.random.default_rng(1)
    x = rng.random(g.n_voxel)
    y = rng.random((len(ANGLES), g.n_detector[1], g.n_detector[0]))
    ax, aty = forward(x, g, ANGLES), back(y, g, ANGLES)  # float64 in, float64 work
    assert ax.dtype == np.float64 and aty.shape == g.n_voxel
    lhs, rhs = float(np.sum(ax * y)), float(np.sum(x * aty))
    assert lhs > 0 and abs(lhs - rhs) / lhs < 1e-12
    # float32 (the working precision of the algorithms) and small batches
    ax32 = forward(x.astype(np.float32), g, ANGLES, max_samples=500)
    aty32 = back(torch.as_tensor(y, dtype=torch.float32), g, ANGLES, max_samples=500)
    assert isinstance(aty32, torch.Tensor) and ax32.dtype == np.float32
    lhs32, rhs32 = float(np.sum(ax32.astype(np.float64) * y)), float(np.sum(x * aty32.double().numpy()))
    assert abs(lhs32 - rhs32) / lhs32 < 1e-4
    np.testing.assert_allclose(ax32, ax, rtol=1e-4, atol=1e-6)


def box_chords(g, angles, margin=0.0):
    """Exact chord lengths [N, nV, nU] (metres) of every ray through the volume box grown by
    ``margin`` voxels on every side (float64 slabs)."""
    o, d = g.rays(angles, dtype=torch.float64)
    vox = np.asarray(g.d_voxel)
    lo = np.asarray(g.off_origin) - np.asarray(g.n_voxel) * vox / 2 - margin * vox
    hi = lo + np.asarray(g.n_voxel) * vox + 2 * margin * vox
    o, d = o.numpy(), d.numpy()
    with np.errstate(divide="ignore", invalid="ignore"):
        ta, tb = (lo - o) / d, (hi - o) / d
    t_in = np.nanmax(np.minimum(ta, tb), -1).clip(0)
    t_out = np.nanmin(np.maximum(ta, tb), -1)
    return np.clip(t_out - t_in, 0, None) * np.linalg.norm(d, axis=-1) / g.scale


@pytest.mark.parametrize("mode", ["cone", "parallel"])
def test_forward_of_a_uniform_box_is_its_chord_length(mode):
    g = small_geometry(mode, offsets=True)
    p = forward(np.ones(g.n_voxel, np.float32), g, ANGLES)
    exact = box_chords(g, ANGLES)
    inner = exact > 0.5 * exact.max()
    rel = np.abs(p[inner] - exact[inner]) / exact[inner]
    # a ray crossing every slice of its dominant axis inside the box integrates exactly (n slices x
    # slice length); rays leaving through a side face see the half-voxel fade of the interpolation
    assert np.median(rel) < 1e-5 and np.percentile(rel, 75) < 0.01
    assert p.sum() == pytest.approx(exact.sum(), rel=0.03)
    # nothing at all beyond the half voxel the interpolation reaches
    assert np.all(p[box_chords(g, ANGLES, margin=0.5) == 0] == 0)
    assert p[exact == 0].max() > 0  # (but the fade itself is there)


def test_forward_of_a_ball_matches_the_analytic_projection_with_offsets():
    g = small_geometry("cone", offsets=True)
    centre = np.asarray(g.off_origin) * g.mm_per_unit + np.array([5.0, -8.0, 4.0])  # mm
    radius, level = 35.0, 0.7
    pts = g.voxel_centres(dtype=torch.float64).numpy() * g.mm_per_unit
    # supersampled (3^3) ball volume, data units
    dmm = np.asarray(g.d_voxel) * g.mm_per_unit
    vol = np.zeros(g.n_voxel)
    for off in np.stack(np.meshgrid(*[(np.arange(3) - 1) / 3] * 3, indexing="ij"), -1).reshape(-1, 3):
        vol += (np.linalg.norm(pts + off * dmm - centre, axis=-1) <= radius) * level / 27
    o, d = g.rays(ANGLES, dtype=torch.float64)
    o, d = o.numpy() * g.mm_per_unit, d.numpy()
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    along = np.sum((centre - o) * d, -1)
    dist2 = np.sum((centre - o) ** 2, -1) - along**2
    exact = level * 2 * np.sqrt(np.clip(radius**2 - dist2, 0, None)) / 1000.0
    p = forward(vol, g, ANGLES)
    obj = exact > 0.3 * exact.max()
    assert np.median(np.abs(p[obj] - exact[obj]) / exact[obj]) < 0.03
    assert p.sum() == pytest.approx(exact.sum(), rel=0.03)
    # the offsets matter: without them the shadow moves and the error is large
    p0 = forward(vol, replace(g, off_detector=(0.0, 0.0)), ANGLES)
    assert np.abs(p0 - exact).sum() > 3 * np.abs(p - exact).sum()


@pytest.mark.parametrize("mode", ["cone", "parallel"])
def test_voxel_backprojector_spreads_a_pixel_along_its_own_ray(mode):
    g = small_geometry(mode, offsets=True)
    y = np.zeros((len(ANGLES), g.n_detector[1], g.n_detector[0]), np.float32)
    y[2, 11, 19] = 1.0  # one pixel of one view, off-centre in u and v
    matched = back(y, g, ANGLES)
    voxel = VoxelBackprojector(g, ANGLES).back(torch.as_tensor(y)).numpy()
    cos = float(np.sum(matched * voxel) / np.linalg.norm(matched) / np.linalg.norm(voxel))
    assert cos > 0.6  # same ray; a flipped u or v axis gives ~0
    y_flip = np.zeros_like(y)
    y_flip[2, 11, g.n_detector[0] - 1 - 19] = 1.0
    flipped = VoxelBackprojector(g, ANGLES).back(torch.as_tensor(y_flip)).numpy()
    assert float(np.sum(matched * flipped)) < 0.2 * float(np.sum(matched * voxel))


def test_projector_bad_input_one_line_errors():
    g = small_geometry("cone")
    with pytest.raises(KneasError, match="nVoxel") as e:
        forward(np.ones((4, 4, 4)), g, ANGLES)
    assert "\n" not in str(e.value)
    with pytest.raises(KneasError, match=r"\[N, nV, nU\]"):
        back(np.ones((len(ANGLES), 30, 31)), g, ANGLES)
    vol = np.ones(g.n_voxel)
    vol[1, 2, 3] = np.nan
    with pytest.raises(KneasError, match="NaN"):
        forward(vol, g, ANGLES)
    with pytest.raises(KneasError, match="angle"):
        forward(np.ones(g.n_voxel), g, [])
    with pytest.raises(KneasError, match="view index"):
        Projector(g, ANGLES).forward(torch.ones(g.n_voxel), [len(ANGLES)])


# ------------------------------------------------------------------------------- algorithms
def test_spread_order_is_a_spread_permutation():
    for n in (1, 2, 7, 50):
        o = spread_order(n)
        assert sorted(o.tolist()) == list(range(n))
    o = spread_order(50)
    assert abs(int(o[1]) - int(o[0])) >= 16  # the second view is far from the first


@pytest.mark.parametrize("backprojector", ["voxel", "matched"])
def test_sart_residual_falls_and_volume_is_positive(tiny, backprojector):
    res = []
    vol = sart(tiny.train.projections, tiny.geometry, tiny.train.angles, iterations=5, backprojector=backprojector,
               progress=lambda i, n, r: res.append((i, n, r)))
    assert [i for i, _, _ in res] == [1, 2, 3, 4, 5] and all(n == 5 for _, n, _ in res)
    r = np.array([x for _, _, x in res])
    assert np.all(np.diff(r) <= 0.01 * r[:-1]) and r[-1] < 0.5 * r[0]
    assert vol.shape == tiny.geometry.n_voxel and vol.dtype == np.float32 and vol.min() >= 0
    assert relative_residual(tiny, vol) < 1.5 * r[-1]  # the sweep residual tracks the true one
    assert psnr3d(vol, tiny.image) > 25


def test_os_sart_with_one_view_per_subset_is_sart(tiny):
    args = (tiny.train.projections, tiny.geometry, tiny.train.angles)
    a = sart(*args, iterations=2, relaxation=0.7)
    b = os_sart(*args, subsets=len(tiny.train), iterations=2, relaxation=0.7)
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    res = []
    c = os_sart(*args, subsets=4, iterations=4, progress=lambda i, n, r: res.append(r))
    assert res[-1] < 0.6 * res[0] and c.min() >= 0


@pytest.mark.parametrize("backprojector", ["voxel", "matched"])
def test_stored_and_recomputed_normalisers_agree(tiny, monkeypatch, backprojector):
    from kneas_method.classical import iterative

    args = (tiny.train.projections, tiny.geometry, tiny.train.angles)
    stored = os_sart(*args, subsets=5, iterations=2, backprojector=backprojector)
    monkeypatch.setattr(iterative, "NORMALISER_CACHE_BYTES", 0)  # back-project V with every update instead
    np.testing.assert_allclose(os_sart(*args, subsets=5, iterations=2, backprojector=backprojector), stored,
                               rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("relaxation", [0.5, 1.0])
def test_asd_pocs_lowers_tv_and_beats_sart(tiny, relaxation):
    # ASD-POCS is SART + TV steps: compare at equal iterations and equal relaxation
    args = (tiny.train.projections, tiny.geometry, tiny.train.angles)
    s = sart(*args, iterations=5, relaxation=relaxation)
    a = asd_pocs(*args, iterations=5, relaxation=relaxation)
    assert total_variation(a) < 0.95 * total_variation(s)
    assert psnr3d(a, tiny.image) >= psnr3d(s, tiny.image)
    assert a.min() >= 0


def test_cgls_residual_falls(tiny):
    # textbook CGLS (matched pair): the residual falls monotonically
    res = []
    vol = cgls(tiny.train.projections, tiny.geometry, tiny.train.angles, iterations=8, backprojector="matched",
               progress=lambda i, n, r: res.append(r))
    r = np.array(res)
    assert len(r) == 8 and np.all(np.diff(r) <= 1e-6) and r[-1] < 0.4 * r[0]
    assert relative_residual(tiny, vol) == pytest.approx(r[-1], rel=1e-3)  # CGLS reports the exact residual


def test_cgls_with_the_voxel_backprojector_converges(tiny):
    # RTK's way (what "auto" picks for this detector): the scaled voxel-driven back-projector in the CG recursions
    res = []
    vol = cgls(tiny.train.projections, tiny.geometry, tiny.train.angles, iterations=8,
               progress=lambda i, n, r: res.append(r))
    assert res[-1] < 0.4 * res[0]
    assert relative_residual(tiny, vol) == pytest.approx(res[-1], rel=1e-3)
    assert psnr3d(vol, tiny.image) > psnr3d(np.zeros_like(vol), tiny.image) + 5


@pytest.mark.parametrize("name", ["sart", "os-sart", "cgls", "asd-pocs"])
def test_iterates_are_the_volumes_of_shorter_runs(tiny, name):
    # one 4-iteration run hands out the volume after each iteration: the iterate after n
    # iterations is what an n-iteration run returns (ASD-POCS clamps at 0 on return only)
    from kneas_method.classical.iterative import ALGORITHMS

    f = ALGORITHMS[name]
    args = (tiny.train.projections, tiny.geometry, tiny.train.angles)
    seen = {}
    last = f(*args, iterations=4, iterates=lambda i, x: seen.__setitem__(i, x.detach().cpu().numpy().copy()))
    assert sorted(seen) == [1, 2, 3, 4]
    for n in (1, 3):
        short = f(*args, iterations=n)
        got = np.clip(seen[n], 0, None) if name == "asd-pocs" else seen[n]
        np.testing.assert_allclose(got, short, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(np.clip(seen[4], 0, None) if name == "asd-pocs" else seen[4], last, rtol=1e-5, atol=1e-6)
    assert not np.allclose(seen[1], seen[4])


@pytest.fixture(scope="module")
def fine_detector():
    """``tiny`` with a 64^2 detector: pixels at the isocentre are 0.56 voxels wide."""
    return simulate_phantom("foot", SimulationConfig(n_voxel=24, voxel_mm=10, n_detector=64, n_train=20, n_val=4))


def test_auto_backprojector_follows_the_detector_pixel_at_the_isocentre(tiny, fine_detector):
    g = tiny.geometry
    expected = min(g.d_detector) * g.dso / g.dsd / max(g.d_voxel)
    assert pixels_per_voxel(g) == pytest.approx(expected) and expected > 1  # 32^2 detector: 1.12
    assert choose_backprojector("auto", g) == "voxel"
    assert pixels_per_voxel(fine_detector.geometry) < 1
    assert choose_backprojector("auto", fine_detector.geometry) == "matched"
    assert choose_backprojector("voxel", fine_detector.geometry) == "voxel"  # an explicit choice is kept
    parallel = replace(g, mode="parallel")
    assert pixels_per_voxel(parallel) == pytest.approx(min(g.d_detector) / max(g.d_voxel))


def test_cgls_on_a_fine_detector_does_not_diverge(fine_detector):
    # the voxel-driven back-projector point-samples a detector finer than the voxels and CGLS's
    # recursions run away; "auto" takes the matched adjoint there and converges
    s = fine_detector
    args = (s.train.projections, s.geometry, s.train.angles)
    res = []
    auto = cgls(*args, iterations=30, progress=lambda i, n, r: res.append(r))
    voxel = cgls(*args, iterations=30, backprojector="voxel")
    assert np.all(np.diff(res) <= 1e-6) and res[-1] < 0.2 * res[0]
    assert psnr3d(auto, s.image) > psnr3d(np.zeros_like(auto), s.image) + 5
    assert psnr3d(auto, s.image) > psnr3d(voxel, s.image) + 10
    tv_auto = asd_pocs(*args, iterations=5)
    assert psnr3d(tv_auto, s.image) > psnr3d(asd_pocs(*args, iterations=5, backprojector="voxel"), s.image)


def test_run_settings_record_the_backprojector_auto_picked(fine_detector):
    from kneas_method.classical.options import ReconstructionOptions
    from kneas_method.classical.reconstruct import reconstruct

    rec = reconstruct("cgls", fine_detector, ReconstructionOptions(iterations=1))
    assert rec.settings["backprojector"] == "matched"


def test_noisy_negative_line_integrals_and_warm_start(tiny):
    rng = np.random.default_rng(0)
    b = tiny.train.projections + rng.normal(0, 0.002, tiny.train.projections.shape).astype(np.float32)
    assert b.min() < 0
    args = (b, tiny.geometry, tiny.train.angles)
    for fn in (sart, asd_pocs):
        v = fn(*args, iterations=2)
        assert np.isfinite(v).all() and v.min() >= 0
    c = cgls(*args, iterations=3)
    assert np.isfinite(c).all()
    # warm start: two more sweeps from a two-sweep volume equal four sweeps (the sweep is deterministic)
    x2 = sart(*args, iterations=2)
    np.testing.assert_allclose(sart(*args, iterations=2, init=x2), sart(*args, iterations=4), rtol=1e-4, atol=1e-5)


def test_algorithm_bad_input_one_line_errors(tiny):
    g, a, b = tiny.geometry, tiny.train.angles, tiny.train.projections
    with pytest.raises(KneasError, match=r"\[N, nV, nU\]") as e:
        sart(b[:, :, :-1], g, a)
    assert "\n" not in str(e.value)
    with pytest.raises(KneasError, match="one projection per angle"):
        cgls(b, g, a[:-1])
    bad = b.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(KneasError, match="NaN"):
        asd_pocs(bad, g, a)
    with pytest.raises(ConfigError, match="subsets"):
        os_sart(b, g, a, subsets=len(a) + 1)
    with pytest.raises(ConfigError, match="iterations"):
        sart(b, g, a, iterations=0)
    with pytest.raises(ConfigError, match="relaxation"):
        sart(b, g, a, relaxation=-1)
    with pytest.raises(ConfigError, match="backprojector"):
        sart(b, g, a, backprojector="siddon")
    with pytest.raises(ConfigError, match="order"):
        sart(b, g, a, order="golden")
    with pytest.raises(KneasError, match="nVoxel"):
        sart(b, g, a, init=np.zeros((3, 3, 3)))
    with pytest.raises(KneasError, match="Geometry"):
        sart(b, "foot", a)


# ------------------------------------------------------------------ methods (kneas-train, kneas-eval)
def test_classical_methods_run_evaluate_and_score_materials(tmp_path, capsys):
    """``kneas-train sart|os-sart|cgls|asd-pocs`` with options, ``kneas-eval`` with per-material Dice
    by GMM thresholds; iterative beats FDK on the same scene."""
    from conftest import run, run_dir_of, simulated_foot
    from kneas_method.cli.eval import main as eval_main

    scene = simulated_foot(tmp_path, "smallfoot", 24, 10.0, n_train=20)
    psnr = {}
    for method, extra in [("fdk", []), ("sart", ["--reconstruction.iterations", "3"]),
                          ("os-sart", ["--reconstruction.subsets", "5", "--reconstruction.iterations", "3"]),
                          ("cgls", ["--reconstruction.iterations", "8"]),
                          ("asd-pocs", ["--reconstruction.iterations", "3", "--reconstruction.tv-steps", "10"])]:
        code, out, err = run([method, "--scene", str(scene), "--output-dir", str(tmp_path / "o")] + extra, capsys)
        assert code == 0, err
        assert "residual" in out or method == "fdk"  # per-iteration progress with the data residual
        run_dir = run_dir_of(out)
        m = json.loads((run_dir / "metrics.json").read_text())
        assert m["parameters"] == 0 and m["algorithm"] == method and m["settings"]["algorithm"] == method
        psnr[method] = m["psnr3d"]
        if method != "fdk":
            assert m["settings"]["iterations"] == int(extra[extra.index("--reconstruction.iterations") + 1])
    assert psnr["sart"] > psnr["fdk"] and psnr["asd-pocs"] > psnr["fdk"]
    ms = json.loads((run_dir_of(out) / "metrics.json").read_text())  # the asd-pocs run
    assert ms["settings"]["tv_steps"] == 10
    # kneas-eval: per-material Dice and surfaces from the volume thresholded at its GMM bounds
    with pytest.raises(SystemExit) as e:
        eval_main([str(run_dir), "-o", str(tmp_path / "ev"), "--no-figures"])
    assert e.value.code == 0
    ev = json.loads((tmp_path / "ev" / "metrics.json").read_text())
    mats = ev["materials"]
    assert mats["K"] >= 2 and len(mats["boundaries"]) == mats["K"] + 1 and mats["air_cut"] > 0
    assert 0 < mats["dice_mean"] <= 1 and mats["chamfer_mm_mean"] is not None
    assert mats["materials"]["soft tissue"]["dice"] > 0.5


def test_bad_reconstruction_option_is_a_one_line_error(tmp_path, capsys):
    from conftest import run, simulated_foot

    scene = simulated_foot(tmp_path, "smallfoot", 16, 15.0, n_train=6)
    code, out, err = run(["os-sart", "--scene", str(scene), "--output-dir", str(tmp_path / "o"),
                          "--reconstruction.subsets", "99"], capsys)
    assert code == 2 and err.strip().startswith("error:") and "subsets" in err and len(err.strip().splitlines()) == 1


def test_threshold_labels_and_fields_agree_with_a_naive_loop():
    from kneas_method.evaluation.surfaces import threshold_fields, threshold_labels

    rng = np.random.default_rng(0)
    vol = rng.random((6, 5, 4)).astype(np.float32)
    bnd, air = [0.0, 0.3, 0.6, 0.9], 0.1
    lab = threshold_labels(vol, bnd, air)
    for v, l in zip(vol.reshape(-1), lab.reshape(-1)):
        want = 0 if v < air else (1 if v < 0.3 else 2 if v < 0.6 else 3)
        assert l == want
    f = threshold_fields(vol, bnd, air)
    for k in range(3):
        np.testing.assert_array_equal(f[..., k] < 0, lab == k + 1)


def test_volume_material_metrics_of_the_exact_label_volume_are_perfect():
    from kneas_method.evaluation.surfaces import volume_material_metrics

    scene = simulate_phantom("foot", SimulationConfig(n_voxel=32, voxel_mm=7.0, n_detector=8, n_train=2, n_val=1))
    from kneas_method.evaluation.surfaces import gt_levels

    exact = np.concatenate([[0.0], gt_levels(scene)])[scene.labels].astype(np.float32)  # piecewise constant
    m = volume_material_metrics(exact, scene, surfaces=False)
    assert m["K"] == 3 and m["dice_mean"] == pytest.approx(1.0)
    assert m["gmm"]["k_rule"] == m["gmm"]["k_rule_used"] == "bic"
    peaks = volume_material_metrics(exact, scene, k_rule="peaks", surfaces=False)  # the cpu preset's rule: one class per level
    assert peaks["K"] == 3 and peaks["gmm"]["k_rule_used"] == "peaks" and peaks["dice_mean"] == pytest.approx(1.0)
    noisy = exact + np.random.default_rng(0).normal(0, 0.08, exact.shape).astype(np.float32)
    assert volume_material_metrics(noisy, scene, surfaces=False)["dice_mean"] < 0.99
    # bounds fitted on other values (the at-noise rule's filtered volume), the volume itself thresholded at them
    beside = volume_material_metrics(noisy, scene, surfaces=False, fit_values=exact, fit_values_are="the exact volume")
    assert beside["boundaries"] == pytest.approx(m["boundaries"]) and beside["gmm"]["fitted_on"] == "the exact volume"
    assert beside["dice_mean"] < 0.99 and m["gmm"]["fitted_on"] == "the volume"
    # thresholds given (a model's own bounds): no mixture fitted, air below half the first class's mean
    given = volume_material_metrics(noisy, scene, surfaces=False, boundaries=m["boundaries"], boundaries_are="the exact bounds")
    assert given["boundaries"] == pytest.approx(m["boundaries"]) and "gmm" not in given and given["boundaries_are"] == "the exact bounds"
    first = noisy[(noisy >= m["boundaries"][0]) & (noisy < m["boundaries"][1])]
    assert given["air_cut"] == pytest.approx(0.5 * first.mean()) and "thresholds at the exact bounds" in given["definition"]
    assert given["dice_mean"] < 0.99


def test_trace_scores_every_count_and_keeps_the_best(tmp_path, capsys):
    """``--trace``: the psnr3d of every count is that of a run stopped there; the best count's figures are recorded."""
    from conftest import run, run_dir_of, simulated_foot

    scene = simulated_foot(tmp_path, "smallfoot", 16, 15.0, n_train=8)
    code, out, err = run(["sart", "--scene", str(scene), "--output-dir", str(tmp_path / "o"), "--reconstruction.iterations", "4",
                          "--trace"], capsys)
    assert code == 0, err
    trace = json.loads((run_dir_of(out) / "metrics.json").read_text())["trace"]
    assert len(trace["psnr3d"]) == 4
    best = trace["best"]
    assert f"best count {best['iterations']} of 4" in out
    assert best["psnr3d"] == max(trace["psnr3d"]) and trace["psnr3d"][best["iterations"] - 1] == best["psnr3d"]
    code, out, err = run(["sart", "--scene", str(scene), "--output-dir", str(tmp_path / "o"),
                          "--reconstruction.iterations", str(best["iterations"])], capsys)
    short = json.loads((run_dir_of(out) / "metrics.json").read_text())
    assert short["psnr3d"] == pytest.approx(best["psnr3d"], abs=1e-3) and short["ssim3d"] == pytest.approx(best["ssim3d"], abs=1e-3)
    code, out, err = run(["fdk", "--scene", str(scene), "--output-dir", str(tmp_path / "o"), "--trace"], capsys)
    assert code == 2 and "fdk has no iterations" in err and len(err.strip().splitlines()) == 1
