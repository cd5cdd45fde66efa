import json

import numpy as np
import pytest
import torch

from kneas_method.bounds import Bounds, GMMBounds, load_bounds
from kneas_method.errors import ConfigError, KneasError

MEANS = np.array([0.2, 0.5, 0.9])
STDS = np.array([0.03, 0.04, 0.05])
COUNTS = np.array([1500, 1000, 700])


def three_materials(seed=0, air=2000):
    rng = np.random.default_rng(seed)
    parts = [rng.normal(m, s, n) for m, s, n in zip(MEANS, STDS, COUNTS)]
    parts.append(np.abs(rng.normal(0, 0.002, air)))  # air: near-zero attenuation
    return rng.permutation(np.concatenate(parts))


def true_valleys():
    """Minima of the generating mixture density between adjacent means (independent grid)."""
    w = COUNTS / COUNTS.sum()
    out = []
    for k in range(2):
        x = np.linspace(MEANS[k], MEANS[k + 1], 20001)
        dens = sum(wi * np.exp(-0.5 * ((x - m) / s) ** 2) / s for wi, m, s in zip(w, MEANS, STDS))
        out.append(x[np.argmin(dens)])
    return np.array(out)


@pytest.fixture(scope="module")
def fitted():
    values = three_materials()
    return values, GMMBounds().fit(torch.as_tensor(values).reshape(10, -1))  # any shape, torch ok


def test_bic_picks_three_and_boundaries_sit_in_the_valleys(fitted):
    values, gb = fitted
    assert gb.n_components_ == 3
    assert min(gb.bic_, key=gb.bic_.get) == 3 and set(gb.bic_) == {1, 2, 3, 4}
    assert np.allclose(gb.means_, MEANS, atol=0.01)
    assert np.allclose(gb.stds_, STDS, atol=0.01)
    assert np.all(np.diff(gb.means_) > 0)  # sorted by mean
    b = gb.boundaries_
    assert b.shape == (4,) and b[0] == 0.0
    assert np.all(b[1:3] > gb.means_[:2]) and np.all(b[1:3] < gb.means_[1:])
    assert np.allclose(b[1:3], true_valleys(), atol=0.02)
    # b_1, b_2 are minima of the fitted mixture between the means
    for k in (1, 2):
        grid = np.linspace(gb.means_[k - 1], gb.means_[k], 999)
        assert gb.density(b[k]) <= gb.density(grid).min() + 1e-9
    # upper bound: 1.15 x 99.5th percentile of the non-air values
    kept = values[values > gb.air_threshold_]
    assert len(kept) == COUNTS.sum()  # the auto air threshold removes exactly the air
    assert b[3] == pytest.approx(1.15 * np.percentile(kept, 99.5), rel=1e-12)
    # beta_k = b_k, alpha_k = b_{k+1} - b_k, exactly
    assert np.array_equal(gb.betas_, b[:-1])
    assert np.array_equal(gb.alphas_, np.diff(b))
    assert gb.warnings_ == []


def test_given_n_components_overrides_bic():
    gb = GMMBounds(n_components=2).fit(three_materials())
    assert gb.n_components_ == 2 and len(gb.alphas_) == 2 and len(gb.boundaries_) == 3
    assert min(gb.bic_, key=gb.bic_.get) == 3  # BIC still recorded, but not used


def test_scale_invariance_of_the_fit():
    # model units depend on the scene's scale: the procedure must not
    values = three_materials()
    a = GMMBounds().fit(values)
    b = GMMBounds().fit(values * 25.0)
    assert b.n_components_ == a.n_components_
    assert np.allclose(b.boundaries_, 25.0 * a.boundaries_, rtol=1e-3)


def test_alternative_estimators():
    values = three_materials()
    q = GMMBounds(method="quantile").fit(values)
    kept = values[values > q.air_threshold_]
    assert q.n_components_ == 3
    assert np.allclose([np.mean(kept < v) for v in q.boundaries_[1:3]], [1 / 3, 2 / 3], atol=1e-3)
    bay = GMMBounds(method="bayes").fit(values)
    for k in (1, 2):  # weighted component densities equal at the boundary
        x = bay.boundaries_[k]
        d = [w * np.exp(-0.5 * ((x - m) / s) ** 2) / s for w, m, s in
             zip(bay.weights_[k - 1:k + 1], bay.means_[k - 1:k + 1], bay.stds_[k - 1:k + 1])]
        assert d[0] == pytest.approx(d[1], rel=0.02)
    with pytest.raises(ConfigError, match="method"):
        GMMBounds(method="kmeans").fit(values)


def test_no_valley_falls_back_to_midpoint_with_warning():
    values = np.random.default_rng(3).normal(0.5, 0.1, 4000)  # one material, forced into two
    with pytest.warns(UserWarning, match="midpoint"):
        gb = GMMBounds(n_components=2).fit(values)
    assert gb.boundaries_[1] == pytest.approx(gb.means_.mean())
    assert any("midpoint" in w for w in gb.to_dict()["warnings"])


def test_to_dict_round_trip_and_files(fitted, tmp_path):
    _, gb = fitted
    d = json.loads(json.dumps(gb.to_dict()))
    assert d["K"] == 3 and d["settings"]["upper_factor"] == 1.15 and set(d["bic"]) == {"1", "2", "3", "4"}
    bounds = GMMBounds.from_dict(d)
    assert isinstance(bounds, Bounds) and bounds.K == 3
    assert np.allclose(bounds.alphas, gb.alphas_) and np.allclose(bounds.betas, gb.betas_)
    assert np.allclose(bounds.boundaries, gb.boundaries_)
    path = tmp_path / "bounds.json"
    path.write_text(json.dumps(d))
    assert load_bounds(path) == bounds
    assert GMMBounds.from_dict({"boundaries": [0.0, 0.3, 1.0]}) == Bounds((0.3, 0.7), (0.0, 0.3))


@pytest.mark.parametrize("bad, match", [
    ({"alphas": [1.0, 1.0], "betas": [0.5]}, "as many"),
    ({"alphas": [1.0, -1.0], "betas": [0.0, 0.5]}, "alpha"),
    ({"alphas": [1.0, 1.0], "betas": [0.5, 0.2]}, "increasing"),
    ({"alphas": [1.0], "betas": [-0.1]}, ">= 0"),
    ({"alphas": [1.0], "betas": ["x"]}, "numbers"),
    ({"boundaries": [0.0, 0.5, 0.4]}, "increasing"),
    ({"K": 2, "alphas": [1.0], "betas": [0.0]}, "K = 2"),
    ({"lower": [0.0]}, "alphas"),
])
def test_invalid_user_bounds_are_one_line_errors(bad, match):
    with pytest.raises(ConfigError, match=match) as err:
        GMMBounds.from_dict(bad)
    assert "\n" not in str(err.value)


def test_bad_bounds_file(tmp_path):
    p = tmp_path / "b.json"
    p.write_text("{not json")
    with pytest.raises(ConfigError, match="not valid JSON"):
        load_bounds(p)
    with pytest.raises(ConfigError, match="does not exist"):
        load_bounds(tmp_path / "missing.json")


def test_plot_writes_png(fitted, tmp_path):
    values, gb = fitted
    out = gb.plot(tmp_path / "figs" / "gmm.png", values=values)
    data = out.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000


def test_empty_prior_model_is_a_clear_error():
    with pytest.raises(KneasError, match="looks empty"):
        GMMBounds().fit(np.zeros((8, 8, 8)))
    with pytest.raises(KneasError, match="looks empty"):
        GMMBounds(air_threshold=0.5).fit(np.random.default_rng(0).uniform(0, 0.4, 1000))
    with pytest.raises(KneasError, match="not fitted"):
        GMMBounds().to_dict()


# ------------------------------------------------ K on a regularised reconstruction
TV_LEVELS = (0.15, 0.30, 0.50, 0.80)


def tv_like_volume(seed=0, n=60000):
    """Values of a TV-regularised reconstruction: the largest material flattened into a
    spike (std 2e-4) on its textured shoulder, three more materials, partial-volume voxels."""
    rng = np.random.default_rng(seed)
    parts = [0.15 + rng.normal(0, 2e-4, int(0.35 * n)), rng.normal(0.15, 0.015, int(0.15 * n)),
             rng.normal(0.30, 0.02, int(0.30 * n)), rng.normal(0.50, 0.03, int(0.12 * n)),
             rng.normal(0.80, 0.05, int(0.05 * n)), rng.uniform(0.02, 0.8, int(0.03 * n))]
    return rng.permutation(np.concatenate(parts))


def test_paper_rule_on_a_tv_volume_misses_a_material():
    """The failure the cpu preset's rule exists for: the spike takes components, BIC stops
    at K = 3 and one boundary lies past the 0.5 material (which then has no label)."""
    gb = GMMBounds(max_components=6).fit(tv_like_volume())
    inner = gb.boundaries_[1:-1]
    between = [lo < b < hi for b, (lo, hi) in zip(inner, zip(TV_LEVELS, TV_LEVELS[1:]))]
    assert gb.n_components_ < len(TV_LEVELS) or not all(between)


def test_min_std_and_valley_rule_find_every_material_of_a_tv_volume():
    gb = GMMBounds(max_components=6, min_std=0.02, k_rule="bic-valleys").fit(tv_like_volume())
    assert gb.n_components_ == len(TV_LEVELS)
    inner = gb.boundaries_[1:-1]
    for b, lo, hi in zip(inner, TV_LEVELS, TV_LEVELS[1:]):
        assert lo + 0.03 < b < hi - 0.03, (np.round(gb.boundaries_, 3), TV_LEVELS)
    assert not gb.warnings_
    assert gb.placeable_[gb.n_components_] is True
    assert any(v is False for v in gb.placeable_.values())  # a lower-BIC K was skipped: no valley
    d = gb.to_dict()
    assert d["settings"]["k_rule"] == "bic-valleys" and d["settings"]["min_std"] == 0.02
    assert d["placeable"][str(gb.n_components_)] is True


def test_valley_rule_does_not_split_a_skewed_material():
    rng = np.random.default_rng(1)
    values = np.concatenate([0.2 + rng.gamma(2.0, 0.02, 40000), rng.normal(0.7, 0.03, 10000)])
    bic = GMMBounds(max_components=6).fit(values)
    assert bic.n_components_ > 2 and bic.warnings_  # BIC alone splits the skewed one, boundaries at midpoints
    gb = GMMBounds(max_components=6, k_rule="bic-valleys").fit(values)
    assert gb.n_components_ == 2 and not gb.warnings_
    assert 0.35 < gb.boundaries_[1] < 0.6


def test_valley_rule_equals_bic_when_bic_k_has_valleys(fitted):
    values, gb = fitted
    other = GMMBounds(k_rule="bic-valleys").fit(values)
    assert other.n_components_ == gb.n_components_
    np.testing.assert_allclose(other.boundaries_, gb.boundaries_)


def test_restarts_keep_a_low_contrast_material_one_start_merges():
    """Six materials, three of them 0.04 apart (abdomen's muscle, liver, kidney): from one
    k-means start the K = 6 mixture lands in a poor optimum and BIC keeps K = 5 (two of the
    close materials in one component); the best of three starts has all six."""
    rng = np.random.default_rng(0)
    levels, weights = [0.15, 0.25, 0.29, 0.33, 0.5, 0.85], [0.35, 0.2, 0.15, 0.05, 0.15, 0.1]
    values = np.concatenate([rng.normal(v, 0.012, int(20000 * w)) for v, w in zip(levels, weights)])
    one = GMMBounds(max_components=8, k_rule="bic-valleys").fit(values)
    assert one.n_components_ == 5
    best = GMMBounds(max_components=8, k_rule="bic-valleys", n_init=3).fit(values)
    assert best.n_components_ == 6 and not best.warnings_
    np.testing.assert_allclose(best.means_, levels, atol=0.005)
    assert all(lo < v < hi for v, lo, hi in zip(levels, best.boundaries_[:-1], best.boundaries_[1:]))


@pytest.mark.parametrize("kw, match", [({"k_rule": "aic"}, "K rule"), ({"min_std": -0.1}, "min_std"),
                                       ({"min_std": 1.5}, "min_std"), ({"min_std": float("nan")}, "min_std")])
def test_bad_k_settings_are_one_line_errors(kw, match):
    with pytest.raises(ConfigError, match=match):
        GMMBounds(**kw).fit(three_materials())


# ----------------------------------------------------------------- the peaks K rule
ABDOMEN_LIKE = [0.15, 0.25, 0.29, 0.33, 0.5, 0.85]  # three soft levels 0.04 apart, the kidney-like one small


def tv_spikes(seed=0, n=300_000, levels=ABDOMEN_LIKE, weights=(0.45, 0.25, 0.12, 0.015, 0.02, 0.005)):
    """A TV-regularised reconstruction's values: each material a plateau (a spike of width 1e-3),
    on a smear of partial-volume edge voxels between and around the levels (the rest of n)."""
    rng = np.random.default_rng(seed)
    parts = [rng.normal(v, 1e-3, int(n * w)) for v, w in zip(levels, weights)]
    smear = n - sum(p.size for p in parts)
    parts.append(rng.uniform(0.05, 0.9, smear))
    return rng.permutation(np.concatenate(parts))


def naive_peaks(h, min_prominence):
    """Oracle for ``histogram_peaks``' peak test: local maxima (plateaus at their left end) of
    ``h`` padded with 0, prominence by its definition: the peak's height above the higher of
    the two lowest points reached before a higher value on either side."""
    g = np.r_[0.0, h, 0.0]
    out = []
    i = 1
    while i < g.size - 1:
        j = i
        while j + 1 < g.size - 1 and g[j + 1] == g[i]:
            j += 1  # a flat top spans i..j
        if g[i - 1] < g[i] and g[j + 1] < g[i]:
            left = g[:i][::-1]
            stop = np.nonzero(left > g[i])[0]
            lmin = left[: stop[0] if stop.size else left.size].min()
            right = g[j + 1:]
            stop = np.nonzero(right > g[i])[0]
            rmin = right[: stop[0] if stop.size else right.size].min()
            if g[i] - max(lmin, rmin) >= min_prominence:
                out.append((i + j) // 2 - 1)
        i = j + 1
    return np.array(out, dtype=int)


def test_histogram_peaks_agree_with_the_naive_oracle():
    from kneas_method.bounds import PEAK_BIN_WIDTH, histogram_peaks

    rng = np.random.default_rng(3)
    for trial in range(5):
        z = np.concatenate([rng.normal(rng.uniform(0.1, 1.0), rng.uniform(0.002, 0.05), rng.integers(200, 5000))
                            for _ in range(rng.integers(1, 6))] + [rng.uniform(0, 1.1, 2000)])
        peaks, valleys, prom = histogram_peaks(z, top=1.15, min_fraction=0.0)
        edges = np.arange(0.0, 1.15 + PEAK_BIN_WIDTH, PEAK_BIN_WIDTH)
        h = np.log1p(np.histogram(z, edges)[0].astype(float))
        h = np.convolve(np.r_[h[0], h, h[-1]], [0.25, 0.5, 0.25], mode="valid")
        expect = naive_peaks(h, 1.5)
        centre = 0.5 * (edges[1:] + edges[:-1])
        np.testing.assert_allclose(peaks, centre[expect])
        assert np.all(prom >= 1.5) and valleys.size == max(peaks.size - 1, 0)
        for lo, v, hi in zip(peaks[:-1], valleys, peaks[1:]):
            i0, iv, i1 = (int(round((t - centre[0]) / PEAK_BIN_WIDTH)) for t in (lo, v, hi))
            assert lo < v < hi and h[iv] == h[i0:i1 + 1].min()


def test_peaks_rule_finds_every_plateau_and_does_not_depend_on_the_seed():
    """Six TV plateaus, three of them 0.04 apart and one of those 1.5 % of the values (abdomen's
    kidney): one material per plateau, each plateau inside its own material, no mixture fitted,
    and the same bounds at every seed although there are more values than max_samples."""
    values = tv_spikes()
    gb = GMMBounds(max_components=8, k_rule="peaks").fit(values)
    assert gb.n_components_ == len(ABDOMEN_LIKE) and gb.k_rule_used_ == "peaks" and gb.gmm_ is None
    np.testing.assert_allclose(gb.means_, ABDOMEN_LIKE, atol=0.004)
    for v, lo, hi in zip(ABDOMEN_LIKE, gb.boundaries_[:-1], gb.boundaries_[1:]):
        assert lo + 0.005 < v < hi - 0.005, (np.round(gb.boundaries_, 3), ABDOMEN_LIKE)
    assert gb.weights_.sum() == pytest.approx(1.0) and np.all(gb.stds_ > 0)
    other = GMMBounds(max_components=8, k_rule="peaks", random_state=7).fit(values)
    np.testing.assert_array_equal(other.boundaries_, gb.boundaries_)
    d = gb.to_dict()
    assert d["k_rule_used"] == "peaks" and len(d["peaks"]) == len(ABDOMEN_LIKE) and d["bic"] == {}
    assert GMMBounds.from_dict(d).K == len(ABDOMEN_LIKE)


@pytest.mark.parametrize("rule", ["peaks", "bic-valleys"])
def test_cover_percentile_puts_a_dense_tail_inside_the_last_material_and_keeps_the_rest(rule):
    """A real scan's bone: a thin tail (0.3 % of the values) far above the 99.5th percentile. With
    cover_percentile the top bound reaches that percentile of the tail; under the peaks rule the
    materials, their inner boundaries and the histogram's unit stay those without it (a mixture rule
    may give the tail a material of its own, now that its boundary lies below the top). A few edge
    voxels' overshoot (a piecewise-constant volume's, 0.01 %) leave the capped top as it is."""
    rng = np.random.default_rng(0)
    body = np.r_[rng.normal(0.1, 0.004, 40_000), rng.normal(0.2, 0.004, 60_000)]
    values = np.r_[body, np.linspace(0.3, 0.9, 300)]
    capped = GMMBounds(max_components=4, k_rule=rule).fit(values)
    cover = GMMBounds(max_components=4, k_rule=rule, cover_percentile=99.99).fit(values)
    assert capped.boundaries_[-1] < 0.3 and cover.boundaries_[-1] > 0.85
    assert cover.boundaries_[-1] == pytest.approx(np.percentile(values, 99.99))
    assert cover.unit_ == capped.unit_ and cover.n_components_ >= capped.n_components_
    if rule == "peaks":
        assert cover.n_components_ == capped.n_components_ == 2
        np.testing.assert_array_equal(cover.boundaries_[:-1], capped.boundaries_[:-1])
    assert cover.to_dict()["settings"]["cover_percentile"] == 99.99
    overshoot = np.r_[body, np.linspace(0.2, 0.3, 10)]  # 10 edge voxels above the capped top
    np.testing.assert_array_equal(GMMBounds(max_components=4, k_rule=rule, cover_percentile=99.99).fit(overshoot).boundaries_,
                                  GMMBounds(max_components=4, k_rule=rule).fit(overshoot).boundaries_)
    with pytest.raises(ConfigError, match="cover_percentile must be a percentile"):
        GMMBounds(cover_percentile=101).fit(values)


def test_peaks_rule_finds_well_separated_materials(fitted):
    values, ref = fitted  # three materials 0.3-0.4 apart, 0.03-0.05 wide: three clear peaks
    gb = GMMBounds(max_components=6, k_rule="peaks").fit(values)
    assert gb.n_components_ == 3 and gb.k_rule_used_ == "peaks"
    np.testing.assert_allclose(gb.means_, MEANS, atol=0.03)
    assert np.all(np.abs(gb.boundaries_[1:-1] - true_valleys()) < 0.05)


def test_peaks_rule_falls_back_to_bic_valleys_on_a_smeared_histogram():
    """Noise smears the materials (a noisy scan): the second material is a shoulder of the
    first, with no valley before it, so the histogram has one peak and K comes from the mixtures."""
    rng = np.random.default_rng(0)
    values = np.concatenate([rng.normal(0.2, 0.12, 40000), rng.normal(0.6, 0.15, 10000)])
    values = values[values > 0.01]
    gb = GMMBounds(max_components=6, k_rule="peaks").fit(values)
    assert gb.k_rule_used_ == "bic-valleys (the histogram has 1 peak)" and len(gb.peaks_) == 1 and gb.gmm_ is not None
    ref = GMMBounds(max_components=6, k_rule="bic-valleys").fit(values)
    assert gb.n_components_ == ref.n_components_
    np.testing.assert_array_equal(gb.boundaries_, ref.boundaries_)


def test_peaks_rule_with_k_given_fits_the_mixture(fitted):
    values, gb = fitted
    given = GMMBounds(n_components=3, k_rule="peaks").fit(values)
    assert given.k_rule_used_ == "given" and given.gmm_ is not None
    np.testing.assert_allclose(given.boundaries_, GMMBounds(n_components=3).fit(values).boundaries_)


def test_peaks_rule_plot_and_bad_method(tmp_path):
    gb = GMMBounds(k_rule="peaks").fit(tv_spikes(n=50_000))
    png = gb.plot(tmp_path / "peaks.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(ConfigError, match="peaks"):
        GMMBounds(k_rule="peaks", method="quantile").fit(tv_spikes(n=50_000))


def test_peaks_rule_fits_the_fallback_values_only_when_the_histogram_has_fewer_than_two_peaks(fitted):
    values, _ = fitted  # three clear peaks: the fallback is not even computed

    def never():
        raise AssertionError("the fallback was computed although the histogram has three peaks")

    gb = GMMBounds(max_components=6, k_rule="peaks").fit(values, fallback=never)
    assert gb.k_rule_used_ == "peaks" and gb.n_components_ == 3
    rng = np.random.default_rng(0)  # one peak (as in the test above): the mixtures are fitted to the fallback values
    smeared = np.concatenate([rng.normal(0.2, 0.12, 40000), rng.normal(0.6, 0.15, 10000)])
    smeared = smeared[smeared > 0.01]
    gb = GMMBounds(max_components=6, k_rule="peaks").fit(smeared, fallback=lambda: values)
    assert gb.k_rule_used_ == "bic-valleys on the fallback values (the histogram has 1 peak)" and len(gb.peaks_) == 1
    ref = GMMBounds(max_components=6, k_rule="bic-valleys").fit(values)
    np.testing.assert_array_equal(gb.boundaries_, ref.boundaries_)
    assert gb.n_kept_ == ref.n_kept_


def noisy_nested_spheres(n=48, noise=0.1, seed=0):
    """A ball of 0.2 holding a ball of 0.5 and one of 0.9, in air, plus noise correlated over about a
    voxel (a Gaussian-blurred white noise of std ``noise``), clipped at 0 as a reconstruction is:
    (levels [3], clean [n, n, n], noisy [n, n, n] float32)."""
    from scipy import ndimage

    g = (np.arange(n) - (n - 1) / 2) / (n / 2)
    x, y, z = np.meshgrid(g, g, g, indexing="ij")
    v = np.where(np.sqrt(x ** 2 + y ** 2 + z ** 2) < 0.85, 0.2, 0.0)
    v = np.where(np.sqrt((x - 0.25) ** 2 + y ** 2 + z ** 2) < 0.45, 0.5, v)
    v = np.where(np.sqrt((x + 0.4) ** 2 + y ** 2 + z ** 2) < 0.25, 0.9, v)
    w = ndimage.gaussian_filter(np.random.default_rng(seed).normal(0, 1, v.shape), 1.0)
    return np.array([0.2, 0.5, 0.9]), v, np.clip(v + w * noise / w.std(), 0, None).astype(np.float32)


@pytest.mark.parametrize("noise", [0.1, 0.12])
def test_bounds_of_a_noisy_volume_after_the_edge_preserving_filter_keep_each_level_inside_a_material(noise):
    """The bounds stage's fallback (a histogram with one peak): the mixtures fitted to the volume
    after ``histogram_smoothing`` put each of the three levels in a material of its own, well inside
    it; fitted to the raw noisy values, a boundary falls on the lowest level (0.2), splitting it."""
    from kneas_method.engine.bounds_stage import histogram_smoothing

    levels, _, noisy = noisy_nested_spheres(noise=noise)
    raw = GMMBounds(max_components=6, k_rule="peaks").fit(noisy)
    smoothed = GMMBounds(max_components=6, k_rule="peaks").fit(noisy, fallback=lambda: histogram_smoothing(noisy))
    assert smoothed.k_rule_used_.startswith("bic-valleys on the fallback values")

    def margin(b):
        return np.abs(levels[:, None] - b[None, 1:-1]).min()

    which = np.searchsorted(smoothed.boundaries_, levels) - 1
    assert np.unique(which).size == 3, np.round(smoothed.boundaries_, 3)
    assert margin(smoothed.boundaries_) > 0.05, np.round(smoothed.boundaries_, 3)
    assert margin(raw.boundaries_) < 0.03, np.round(raw.boundaries_, 3)
    out = histogram_smoothing(torch.from_numpy(noisy))  # torch in, numpy out, same values
    np.testing.assert_allclose(out, histogram_smoothing(noisy), atol=1e-6)
    assert out.shape == noisy.shape and out.dtype == np.float32


@pytest.mark.parametrize("rule", ["bic", "bic-valleys"])
def test_a_tail_of_extreme_values_does_not_put_a_boundary_above_the_upper_bound(rule):
    # two materials and 0.3 % of values far above them, as the end slices of a scan truncated along its axis
    rng = np.random.default_rng(0)
    values = np.concatenate([rng.normal(0.2, 0.01, 10_000), rng.normal(0.5, 0.01, 10_000), rng.normal(5.0, 0.3, 60)])
    g = GMMBounds(max_components=4, k_rule=rule, n_init=2).fit(values)  # raised "upper bound ... does not exceed" before
    b = g.boundaries_
    assert np.all(np.diff(b) > 0) and b[-1] == pytest.approx(1.15 * np.percentile(values, 99.5))
    assert g.bic_[g.n_components_] > min(g.bic_.values())  # a K of lower BIC was passed over: its boundary lay above b[-1]
    if rule == "bic":
        assert any("above the upper bound" in w for w in g.warnings_)
