import dataclasses
import json

import pytest
import torch

from kneas_method import presets, registry
from kneas_method.config import to_dict, update_from_dict
from kneas_method.errors import ConfigError
from kneas_method.methods import TrainConfig

NAMES = ["k-neas", "kselector", "kselector-floater", "kselector-shared", "naf", "neas-1m", "neas-2m"]

# SPEC §6: K, attenuation, selector, floater, bounds source
TABLE = {
    "neas-1m": (1, "single", "soft", False, "wide"),
    "neas-2m": (2, "independent", "hard", False, "auto"),
    "kselector": (3, "independent", "soft", False, "auto"),
    "kselector-floater": (3, "independent", "soft", True, "auto"),
    "kselector-shared": (3, "shared", "soft", False, "auto"),
    "k-neas": (3, "shared", "soft", True, "auto"),
}


def test_all_methods_registered():
    specs = registry.methods()
    assert set(NAMES) <= set(specs)
    for name in NAMES:
        assert specs[name].config.method == name and specs[name].description


@pytest.mark.parametrize("name", sorted(TABLE))
def test_method_table(name):
    c = registry.load("methods", name).config
    K, att, sel, floater, bounds = TABLE[name]
    assert (c.model.num_materials, c.model.attenuation, c.model.selector, c.model.floater, c.bounds_source) == (K, att, sel, floater, bounds)
    assert c.model.field == "sdf"


def test_naf_method_has_no_sdf():
    c = registry.load("methods", "naf").config
    assert c.model.field == "naf" and c.bounds_source == "none" and not c.model.floater


@pytest.mark.parametrize("name", NAMES)
def test_every_method_forward_backward(name):
    spec = registry.load("methods", name)
    cfg = presets.resolve(dataclasses.replace(spec.config, preset="tiny"))
    torch.manual_seed(0)
    model = cfg.model.setup(scale=2.0)
    n = 6
    o = torch.tensor([0.0, -3.0, 0.0]).expand(n, 3).clone()
    d = torch.stack([torch.linspace(-0.2, 0.2, n), torch.ones(n), torch.zeros(n)], -1)
    is_air = torch.tensor([False] * 4 + [True] * 2)
    batch = {"origins": o, "directions": d, "projections": torch.where(is_air, 0.0, 0.2), "is_air": is_air, "near": 2.0, "far": 4.0}
    loss = model.loss_dict(batch, progress=0.0)
    assert torch.isfinite(loss["total"])
    loss["total"].backward()
    grads = [p.grad for p in model.parameters()]
    assert all(g is not None for g in grads[:1])
    enc = next(model.field.encoding.parameters())
    assert enc.grad is not None and enc.grad.abs().sum() > 0
    model.eval()
    with torch.no_grad():
        out = model.render(o, d, 2.0, 4.0)
    assert out.intensity.shape == (n,) and torch.all(torch.isfinite(out.intensity))


@pytest.mark.parametrize("name", NAMES)
def test_train_config_round_trips_through_json(name):
    base = registry.load("methods", name).config
    for cfg in (base, presets.resolve(dataclasses.replace(base, preset="tiny", seed=5, views=10))):
        data = json.loads(json.dumps(to_dict(cfg)))
        back = update_from_dict(TrainConfig(), data)
        assert back == cfg
    custom = dataclasses.replace(base, model=dataclasses.replace(base.model, alphas=(1.0, 2.0), betas=(0.0, 1.0), encoding_options={"num_levels": 4, "per_level_scale": 1.5}))
    assert update_from_dict(TrainConfig(), json.loads(json.dumps(to_dict(custom)))) == custom


def test_presets_fill_only_unset_values(monkeypatch):
    c = registry.load("methods", "k-neas").config
    c = dataclasses.replace(c, preset="paper", model=dataclasses.replace(c.model, num_samples=77, encoding_options={"log2_hashmap_size": 12}))
    r = presets.resolve(c)
    assert r.model.num_samples == 77 and r.model.num_eval_samples == 128
    assert r.model.encoding_options["log2_hashmap_size"] == 12 and r.model.encoding_options["num_levels"] == 14
    assert r.trainer.epochs == 1000 and r.datamanager.num_object_rays == 512 and r.datamanager.num_air_rays == 128
    assert r.trainer.lr == 1e-3 and r.trainer.lr_decay_at == 0.5 and r.trainer.lr_decay_factor == 0.1
    assert r.model.lambda_floater == 0.1 and r.model.lambda_eikonal == 0.01 and r.model.floater_fraction == 0.2
    assert presets.resolve(r) == r  # idempotent


def test_cpu_preset_narrows_the_attenuation_networks_and_older_runs_keep_their_width():
    """The cpu preset's attenuation networks are 32 wide (the paper's 64 elsewhere), for every
    surface method and its prior; the user's width wins; a config.json written before (no
    ``hidden_dim``) is read at the 64 it was trained with, so it loads and resumes."""
    from kneas_method.engine.bounds_stage import prior_config
    from kneas_method.engine.loading import config_from_dict

    for name in ("k-neas", "neas-2m", "neas-1m"):
        base = dataclasses.replace(registry.load("methods", name).config, method=name)
        cpu = presets.resolve(dataclasses.replace(base, preset="cpu"))
        assert cpu.model.attenuation_options == {"hidden_dim": 32}
        assert presets.resolve(cpu) == cpu  # idempotent
        assert presets.resolve(dataclasses.replace(base, preset="paper")).model.attenuation_options == {"hidden_dim": 64}
        net = cpu.model.setup(scale=1.0).attenuation
        first = net.body[0] if hasattr(net, "body") else (net.net[0] if hasattr(net, "net") else net.nets[0][0])
        assert first.out_features == 32
        saved = to_dict(cpu)
        assert config_from_dict(saved, "config.json").model.attenuation_options == {"hidden_dim": 32}
        older = {"method": name, "preset": "cpu", "model": {**saved["model"], "attenuation_options": {}},
                 "trainer": {"epochs": 80, "warm_start_steps": 300}}  # written before the cpu preset's width, in the flat settings
        assert config_from_dict(older, "config.json").model.attenuation_options == {"hidden_dim": 64}
    told = dataclasses.replace(base, preset="cpu", model=dataclasses.replace(base.model, attenuation_options={"hidden_dim": 48}))
    assert presets.resolve(told).model.attenuation_options == {"hidden_dim": 48}
    k = presets.resolve(dataclasses.replace(registry.load("methods", "k-neas").config, method="k-neas", preset="cpu"))
    assert prior_config(k).model.attenuation_options == {"hidden_dim": 32}
    naf = presets.resolve(dataclasses.replace(registry.load("methods", "naf").config, method="naf", preset="cpu"))
    assert naf.model.attenuation_options == {} and config_from_dict(to_dict(naf), "config.json").model.attenuation_options == {}


def test_cpu_preset_hash_grid_reaches_half_a_voxel_and_older_runs_keep_their_scale():
    """The cpu preset's finest hash-grid level has about two cells per voxel of a 128^3 grid
    (scale 1.75: 263 across the box; 1.6, 168, before 2026-11-29); the user's scale wins; a
    config.json written with the old scale is read at it, so the run loads as it was trained."""
    from kneas_method.engine.loading import config_from_dict
    from kneas_method.fields.hash_grid import HashGridConfig, hash_grid_layout

    base = dataclasses.replace(registry.load("methods", "k-neas").config, method="k-neas")
    cpu = presets.resolve(dataclasses.replace(base, preset="cpu"))
    finest = hash_grid_layout(HashGridConfig(**cpu.model.encoding_options)).resolutions[-1]
    assert 2 * 128 <= finest <= 2 * 128 * 1.1
    saved = to_dict(cpu)
    assert config_from_dict(saved, "config.json").model.encoding_options["per_level_scale"] == 1.75
    older = {**saved, "model": {**saved["model"], "encoding_options": {**saved["model"]["encoding_options"], "per_level_scale": 1.6}}}
    assert config_from_dict(older, "config.json").model.encoding_options["per_level_scale"] == 1.6
    told = dataclasses.replace(base, preset="cpu", model=dataclasses.replace(base.model, encoding_options={"per_level_scale": 1.5}))
    assert presets.resolve(told).model.encoding_options["per_level_scale"] == 1.5


def test_cpu_preset_skips_empty_space_unless_told_not_to():
    c = dataclasses.replace(registry.load("methods", "k-neas").config, preset="cpu")
    assert presets.resolve(c).model.occupancy_grid is True
    assert presets.resolve(dataclasses.replace(c, preset="paper")).model.occupancy_grid is False  # the paper's sampler
    off = dataclasses.replace(c, model=dataclasses.replace(c.model, occupancy_grid=False))
    assert presets.resolve(off).model.occupancy_grid is False  # the user's choice wins


def test_cpu_preset_scores_projections_of_the_volume_unless_told_not_to():
    c = dataclasses.replace(registry.load("methods", "k-neas").config, preset="cpu")
    cpu = presets.resolve(c)
    assert cpu.trainer.eval_projections == "volume"
    assert any("Joseph projector" in note for note in presets.describe(cpu))
    paper = presets.resolve(dataclasses.replace(c, preset="paper"))
    assert paper.trainer.eval_projections == "rendered"  # the paper's evaluation
    assert not any("Joseph" in note for note in presets.describe(paper))
    told = dataclasses.replace(c, trainer=dataclasses.replace(c.trainer, eval_projections="rendered"))
    assert presets.resolve(told).trainer.eval_projections == "rendered"  # the user's choice wins
    with pytest.raises(ConfigError, match="eval_projections"):
        presets.resolve(dataclasses.replace(c, trainer=dataclasses.replace(c.trainer, eval_projections="exact")))


def test_cpu_preset_drops_the_rate_late_unless_told_otherwise():
    c = dataclasses.replace(registry.load("methods", "k-neas").config, preset="cpu")
    cpu = presets.resolve(c)
    assert cpu.trainer.lr_decay_at == 0.85
    assert any("lr_decay_at 0.85" in note for note in presets.describe(cpu))
    paper = presets.resolve(dataclasses.replace(c, preset="paper"))
    assert paper.trainer.lr_decay_at == 0.5  # SPEC: x0.1 after 500 of 1000 epochs
    assert not any("lr_decay_at" in note for note in presets.describe(paper))
    told = dataclasses.replace(c, trainer=dataclasses.replace(c.trainer, lr_decay_at=0.5))
    assert presets.resolve(told).trainer.lr_decay_at == 0.5  # the user's choice wins
    for bad in (1.5, -0.1, "late", True):
        with pytest.raises(ConfigError, match="lr.decay.at"):
            presets.resolve(dataclasses.replace(c, trainer=dataclasses.replace(c.trainer, lr_decay_at=bad)))


def test_cpu_preset_picks_k_by_histogram_peaks_unless_told_otherwise():
    c = dataclasses.replace(registry.load("methods", "k-neas").config, preset="cpu")
    cpu = presets.resolve(c)
    assert (cpu.bounds_max_materials, cpu.bounds_k_rule, cpu.bounds_min_std, cpu.bounds_gmm_restarts) == (8, "peaks", 0.0, 3)
    note = next(n for n in presets.describe(cpu) if "bounds:" in n)
    assert "one material per histogram peak" in note and "K = 1..8" in note and "the best of 3 GMM starts" in note
    assert note.endswith("on the voxel values of the ASD-POCS start; the top bound 1.15 x the 99.5th percentile or the 99.99th, "
                         "whichever is higher; K by BIC on the start after an edge-preserving filter where it fits the views to their noise")
    valleys = presets.resolve(dataclasses.replace(c, bounds_k_rule="bic-valleys"))
    note = next(n for n in presets.describe(valleys) if "bounds:" in n)
    assert "K by the lowest BIC with every boundary a density valley, K = 1..8" in note
    # a mixture boundary rule asked for (no K rule given): the preset's mixture K rule, not an error
    assert presets.resolve(dataclasses.replace(c, bounds_method="quantile")).bounds_k_rule == "bic-valleys"
    for name in ("paper", "tiny"):  # the paper's K = 1..4 by BIC, sklearn's default regulariser, one start
        other = presets.resolve(dataclasses.replace(c, preset=name))
        assert (other.bounds_max_materials, other.bounds_k_rule, other.bounds_min_std, other.bounds_gmm_restarts) == (4, "bic", 0.0, 1)
        assert any("bounds: K by BIC, K = 1..4, on the voxel values of a NeAS-1M prior" in n for n in presets.describe(other))
    told = presets.resolve(dataclasses.replace(c, bounds_max_materials=4, bounds_k_rule="bic", bounds_min_std=0.0, bounds_gmm_restarts=1))
    assert (told.bounds_max_materials, told.bounds_k_rule, told.bounds_min_std, told.bounds_gmm_restarts) == (4, "bic", 0.0, 1)  # the user wins
    assert any("bounds: K by BIC, K = 1..4, on the voxel values of the ASD-POCS start" in n for n in presets.describe(told))
    with pytest.raises(ConfigError, match="bounds-gmm-restarts"):
        presets.resolve(dataclasses.replace(c, bounds_gmm_restarts=0))
    with pytest.raises(ConfigError, match="bounds-max-materials"):
        presets.resolve(dataclasses.replace(c, bounds_max_materials=0))
    with pytest.raises(ConfigError, match="bounds-min-std"):
        presets.resolve(dataclasses.replace(c, bounds_min_std=2.0))
    with pytest.raises(ConfigError, match="bounds_k_rule"):
        presets.resolve(dataclasses.replace(c, bounds_k_rule="aic"))


def test_auto_preset_says_why(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    name, reason = presets.choose("auto")
    assert name == "cpu" and "no CUDA" in reason
    assert presets.resolve(registry.load("methods", "k-neas").config).preset == "cpu"
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda i=0: "FakeGPU")
    assert presets.choose("auto")[0] == "paper"
    with pytest.raises(ConfigError, match="unknown preset"):
        presets.choose("fast")


def test_num_materials_override_and_errors():
    kneas = registry.load("methods", "k-neas").config
    assert presets.resolve(dataclasses.replace(kneas, preset="tiny", num_materials=4)).model.num_materials == 4
    for name, K, msg in (("neas-2m", 3, "hard selector"), ("neas-1m", 2, "single-material"), ("naf", 2, "no materials")):
        with pytest.raises(ConfigError, match=msg):
            presets.resolve(dataclasses.replace(registry.load("methods", name).config, preset="tiny", num_materials=K))
    # the hard selector refuses K != 2 when built directly too
    cfg = presets.resolve(dataclasses.replace(registry.load("methods", "neas-2m").config, preset="tiny"))
    with pytest.raises(ConfigError, match="only with K = 2"):
        dataclasses.replace(cfg.model, num_materials=3).setup()


def test_neas_2m_and_k_neas_share_one_prior():
    """NeAS-2M and K-NeAS are compared under the same bounds: the same prior config (hence key)."""
    from kneas_method import presets
    from kneas_method.engine.bounds_stage import prior_config
    from kneas_method.methods import k_neas, neas_2m

    a = prior_config(presets.resolve(dataclasses.replace(k_neas.config, preset="tiny")))
    b = prior_config(presets.resolve(dataclasses.replace(neas_2m.config, preset="tiny")))
    assert a.model == b.model and a.trainer == b.trainer and a.datamanager == b.datamanager


def test_peaks_k_rule_is_a_choice_the_run_states(tmp_path):
    """``--bounds-k-rule peaks``: the note says what it does, a boundary method it would ignore is
    refused before any work, and the bounds stage records which rule decided K."""
    import numpy as np

    from conftest import sphere_scene
    from kneas_method.engine.bounds_stage import estimate_bounds

    c = dataclasses.replace(registry.load("methods", "k-neas").config, preset="cpu", bounds_k_rule="peaks")
    cfg = presets.resolve(c)
    note = next(n for n in presets.describe(cfg) if "bounds:" in n)
    assert "one material per histogram peak" in note
    with pytest.raises(ConfigError, match="bounds-method bayes"):
        presets.resolve(dataclasses.replace(c, bounds_method="bayes"))
    presets.resolve(dataclasses.replace(c, bounds_method="bayes", num_materials=3))  # K given: the rule is not used
    rng = np.random.default_rng(0)
    volume = np.zeros(40 ** 3)
    volume[: 30000] = 0.3 + rng.normal(0, 1e-3, 30000)  # two TV plateaus on a partial-volume smear
    volume[30000: 36000] = 0.8 + rng.normal(0, 1e-3, 6000)
    volume[36000: 40000] = rng.uniform(0.05, 0.85, 4000)
    result = estimate_bounds(cfg, sphere_scene(), tmp_path, torch.device("cpu"), start=(volume.reshape(40, 40, 40), "asd-pocs"))
    assert result.K == 2 and result.details["k_chosen_by"] == "peaks" and "histogram peaks" in result.source
    assert 0.3 < result.betas[1] < 0.8 and result.details["gmm"]["peaks"] == pytest.approx([0.3, 0.8], abs=0.004)
    assert result.details["first_label_threshold"] == pytest.approx(0.15, abs=0.002)  # half material 1's level
    assert (tmp_path / "figures" / "gmm_bounds.png").is_file() and result.details["smoothed"] is None
    # a noisy volume (one peak): the mixtures are fitted after the bilateral filter, and the run's bounds say so
    from test_bounds import noisy_nested_spheres

    levels, _, noisy = noisy_nested_spheres()
    noisy_cfg = dataclasses.replace(cfg, bounds_max_materials=6, bounds_gmm_restarts=1)
    result = estimate_bounds(noisy_cfg, sphere_scene(), tmp_path, torch.device("cpu"), start=(noisy, "asd-pocs"))
    assert result.details["smoothed"] == {"filter": "bilateral", "sigma_voxels": 3.0, "range_fraction": 0.1}
    assert result.details["k_chosen_by"] == "bic-valleys on the ASD-POCS after a bilateral filter (the histogram has 1 peak)"
    assert result.source == "gmm (gmm) on the ASD-POCS"
    boundaries = np.array(result.details["gmm"]["boundaries"])
    assert np.unique(np.searchsorted(boundaries, levels)).size == 3  # each level in a material of its own


def four_levels_in_noise(noise=0.05, seed=0, n=40):
    """A body at 0.2 holding spheres at 0.3, 0.6 and 0.9, with correlated noise of std ``noise``: the
    levels ``[4]`` and the volume ``[n, n, n]`` (a noisy start whose histogram keeps fewer peaks than levels)."""
    import numpy as np
    from scipy import ndimage

    g = (np.arange(n) - (n - 1) / 2) / (n / 2)
    x, y, z = np.meshgrid(g, g, g, indexing="ij")
    v = np.where(np.sqrt(x ** 2 + y ** 2 + z ** 2) < 0.9, 0.2, 0.0)
    v = np.where(np.sqrt((x - 0.3) ** 2 + y ** 2 + z ** 2) < 0.45, 0.6, v)
    v = np.where(np.sqrt((x + 0.45) ** 2 + (y - 0.3) ** 2 + z ** 2) < 0.25, 0.3, v)
    v = np.where(np.sqrt((x + 0.45) ** 2 + (y + 0.3) ** 2 + z ** 2) < 0.25, 0.9, v)
    w = ndimage.gaussian_filter(np.random.default_rng(seed).normal(0, 1, v.shape), 0.7)
    return np.array([0.2, 0.3, 0.6, 0.9]), np.clip(v + w * noise / w.std(), 0, None).astype(np.float32)


def test_a_start_at_the_views_noise_gets_the_at_noise_k_rule(tmp_path):
    """refine-classical's ``bounds_at_noise_k_rule`` (BIC on the start after the edge-preserving filter):
    on a noisy start the peaks rule leaves two of four levels in one material, the at-noise rule gives
    each level a material of its own, and the bounds record which rule decided; the paper's procedure
    has no such rule, and ``--bounds-at-noise-k-rule peaks`` keeps the peaks everywhere."""
    import numpy as np

    from conftest import sphere_scene
    from kneas_method.engine.bounds_stage import at_noise_k_rule, estimate_bounds

    base = dataclasses.replace(registry.load("methods", "k-neas").config, preset="cpu")
    cfg = presets.resolve(base)
    assert cfg.bounds_at_noise_k_rule == "bic" and cfg.bounds_k_rule == "peaks"
    assert presets.resolve(dataclasses.replace(base, procedure="paper")).bounds_at_noise_k_rule is None
    assert "where it fits the views to their noise" in next(n for n in presets.describe(cfg) if "bounds:" in n)
    levels, noisy = four_levels_in_noise()

    def materials(result):  # how many materials the four levels fall in
        return np.unique(np.searchsorted(np.array(result.details["gmm"]["boundaries"]), levels)).size

    scene, start = sphere_scene(), (noisy, "asd-pocs")
    peaks = estimate_bounds(cfg, scene, tmp_path / "a", torch.device("cpu"), start=start)
    assert peaks.details["at_noise_rule"] is None and materials(peaks) == 3
    at_noise = estimate_bounds(cfg, scene, tmp_path / "b", torch.device("cpu"), start=start, start_at_noise=True)
    assert at_noise.details["at_noise_rule"] == "bic" and at_noise.details["k_chosen_by"] == "bic"
    assert at_noise.details["smoothed"] == {"filter": "bilateral", "sigma_voxels": 3.0, "range_fraction": 0.1}
    assert materials(at_noise) == 4 and at_noise.K >= 4
    kept = presets.resolve(dataclasses.replace(base, bounds_at_noise_k_rule="peaks"))
    same = estimate_bounds(kept, scene, tmp_path / "c", torch.device("cpu"), start=start, start_at_noise=True)
    assert same.details["at_noise_rule"] is None and same.details["k_chosen_by"] == "peaks" and materials(same) == 3
    given_cfg = presets.resolve(dataclasses.replace(base, num_materials=3))
    given = estimate_bounds(given_cfg, scene, tmp_path / "d", torch.device("cpu"), start=start, start_at_noise=True)
    assert given.K == 3 and given.details["at_noise_rule"] is None  # K given: no rule picks it
    assert "where it fits the views to their noise" not in next(n for n in presets.describe(given_cfg) if "bounds:" in n)
    assert at_noise_k_rule(cfg) == "bic" and at_noise_k_rule(kept) is None and at_noise_k_rule(given_cfg) is None


@pytest.mark.parametrize("name", ["paper", "cpu", "tiny"])
def test_preset_validation_and_checkpoints_fall_on_the_last_epoch(name):
    """Each preset's validation and checkpoint intervals divide its epochs, so the last epoch is
    validated and checkpointed whatever the schedule (the cpu preset's steps were doubled once,
    and its intervals with them)."""
    t = presets.TABLE[name]["trainer"]
    assert t["epochs"] % t["eval_every"] == 0 and t["epochs"] % t["checkpoint_every"] == 0
    assert t["prior_epochs"] % t["checkpoint_every"] == 0


def test_a_bounds_warning_is_said_once_not_raised_again_as_a_python_warning(tmp_path, capsys):
    import warnings

    import numpy as np

    from conftest import sphere_scene
    from kneas_method.engine.bounds_stage import estimate_bounds

    cfg = presets.resolve(dataclasses.replace(registry.load("methods", "k-neas").config, preset="cpu", num_materials=2))
    volume = np.random.default_rng(3).normal(0.5, 0.1, 40 ** 3).clip(0.01)  # one material, forced into two: no valley
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a Python warning would fail here
        result = estimate_bounds(cfg, sphere_scene(), tmp_path, torch.device("cpu"), start=(volume.reshape(40, 40, 40), "asd-pocs"))
    said = [line for line in capsys.readouterr().out.splitlines() if "bounds warning:" in line]
    assert result.K == 2 and len(said) >= 1 and any("midpoint" in line for line in said)
