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
