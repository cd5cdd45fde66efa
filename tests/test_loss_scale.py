"""The losses of a scan in a scanner's units weigh as on NAF's normalised scale (engine.loss_scale)."""

import dataclasses

import numpy as np
import pytest
import torch

from kneas_method import methods, presets, registry
from kneas_method.classical.reconstruct import reconstruct
from kneas_method.data.naf import load_naf
from kneas_method.data.scene import Views
from kneas_method.engine.loss_scale import LOSS_SCALE_TOP, loss_scale
from kneas_method.stages.anchor import build_anchor
from kneas_method.stages.materials_refit import refit_materials
from kneas_method.engine.trainer import Trainer

from conftest import simulated_foot

UNIT = 40.0  # a scanner's /m against NAF's normalised [0, 1] /m: water at ~20 /m


@pytest.fixture(scope="module")
def foot(tmp_path_factory):
    return load_naf(simulated_foot(tmp_path_factory.mktemp("scene"), "scalefoot", 16, 15.0, n_train=6))


def in_units(scene, factor: float):
    """The same scan with every attenuation times ``factor`` (line integrals and volume)."""
    return dataclasses.replace(scene, train=Views(scene.train.angles, scene.train.projections * factor),
                               val=Views(scene.val.angles, scene.val.projections * factor), image=scene.image * factor)


def test_naf_scale_is_its_own_unit_and_a_scanners_is_brought_to_it(foot):
    assert loss_scale(foot) == 1.0  # NAF-normalised: the losses as they always were
    top = float(np.percentile(np.asarray(reconstruct("fdk", foot).volume), 99.5))
    assert top < LOSS_SCALE_TOP
    scanner = in_units(foot, UNIT)
    assert loss_scale(scanner) == pytest.approx(UNIT * top / LOSS_SCALE_TOP, rel=1e-4)
    assert loss_scale(scanner) > 1.0


def test_the_pipeline_measures_a_scans_unit_once(foot, tmp_path, monkeypatch, capsys):
    """One FDK for the unit, whatever the run trains (its prior included); no cache of it anywhere."""
    import kneas_method.classical.reconstruct as rec
    from conftest import run
    from kneas_method.data.naf import save_naf

    calls = []
    real = rec.reconstruct
    monkeypatch.setattr(rec, "reconstruct", lambda *a, **k: calls.append(a[0]) or real(*a, **k))
    path = save_naf(in_units(foot, UNIT), tmp_path / "scanner.pickle")
    code, out, err = run(["k-neas", "--scene", str(path), "--preset", "tiny", "--trainer.epochs", "1", "--trainer.prior-epochs", "1",
                          "--trainer.eval-every", "0", "--output-dir", str(tmp_path / "o")], capsys)
    assert code == 0, err
    assert calls == ["fdk"] and "losses measured in units of" in out  # the prior and the model share it


def rays(n_obj: int, n_air: int) -> dict:
    """A training batch without projections: ``n_obj`` object rays, then ``n_air`` air rays, through the box."""
    torch.manual_seed(1)
    n = n_obj + n_air
    o = torch.tensor([0.0, -3.0, 0.0]).expand(n, 3).clone()
    d = torch.cat([torch.rand(n, 2) * 0.4 - 0.2, torch.ones(n, 1)], -1)[:, [0, 2, 1]]
    return {"origins": o, "directions": d, "is_air": torch.arange(n) >= n_obj, "near": 2.0, "far": 4.0}


def _model(bounds, unit: float):
    torch.manual_seed(0)
    cfg = presets.resolve(dataclasses.replace(methods.k_neas.config, preset="tiny"))
    model = cfg.model.setup()
    model.set_bounds([unit * a for a in bounds[0]], [unit * b for b in bounds[1]])
    model.loss_scale = unit
    return model


def test_every_model_loss_of_a_scan_in_other_units_is_the_normalised_ones():
    bounds = ([0.2, 0.3, 0.5], [0.0, 0.2, 0.5])
    plain, scaled = _model(bounds, 1.0), _model(bounds, UNIT)
    batch = rays(12, 4)
    p = torch.where(batch["is_air"], 0.0, 0.3)
    for progress in (0.1, 0.5):  # with and without the floater term
        g1, g2 = torch.Generator().manual_seed(3), torch.Generator().manual_seed(3)
        a = plain.loss_dict({**batch, "projections": p}, progress, generator=g1)
        b = scaled.loss_dict({**batch, "projections": UNIT * p}, progress, generator=g2)
        assert set(a) == set(b)
        for key in a:
            assert float(b[key].detach()) == pytest.approx(float(a[key].detach()), rel=1e-4, abs=1e-12), key
    points = torch.rand(64, 3) * 1.6 - 0.8
    targets = torch.rand(64) * 0.8
    queried = torch.arange(64) % 3 != 0
    for kw in ({}, {"queried": queried}):
        a = plain.volume_loss_dict(points, targets, occupancy_weight=0.1, **kw)
        b = scaled.volume_loss_dict(points, UNIT * targets, occupancy_weight=0.1, **kw)
        for key in a:
            assert float(b[key].detach()) == pytest.approx(float(a[key].detach()), rel=1e-4), key


def test_the_anchor_of_a_scan_in_other_units_weighs_as_the_normalised_one(foot, tmp_path):
    cfg = presets.resolve(dataclasses.replace(registry.load("methods", "k-neas").config, method="k-neas", preset="tiny"))
    bounds = ([0.4, 0.3, 0.4], [0.0, 0.4, 0.7])
    volume = np.asarray(foot.image, dtype=np.float32)
    losses = []
    for unit in (1.0, UNIT):
        trainer = Trainer(cfg, foot, tmp_path / str(unit), epochs=1, device="cpu",
                          bounds=([unit * a for a in bounds[0]], [unit * b for b in bounds[1]]))
        trainer.model.loss_scale = unit  # as loss_scale gives a scan in these units
        anchor = build_anchor(trainer, unit * volume, weight=0.5, points_per_step=300, occupancy_weight=0.1)
        with torch.no_grad():
            losses.append(float(anchor.loss(trainer.model, trainer.generator)))
    assert losses[0] > 0 and losses[1] == pytest.approx(losses[0], rel=1e-4)


def test_a_trainer_measures_a_scanners_scan_in_its_unit(foot, tmp_path):
    cfg = presets.resolve(dataclasses.replace(registry.load("methods", "k-neas").config, method="k-neas", preset="tiny"))
    plain = Trainer(cfg, foot, tmp_path / "plain", epochs=1, device="cpu", bounds=([0.4, 0.3, 0.4], [0.0, 0.4, 0.7]),
                    loss_scale=loss_scale(foot))
    scanner = Trainer(cfg, in_units(foot, UNIT), tmp_path / "scanner", epochs=1, device="cpu",
                      bounds=([UNIT * 0.4, UNIT * 0.3, UNIT * 0.4], [0.0, UNIT * 0.4, UNIT * 0.7]), loss_scale=loss_scale(in_units(foot, UNIT)))
    assert plain.model.loss_scale == 1.0
    assert scanner.model.loss_scale == pytest.approx(loss_scale(in_units(foot, UNIT)))
    volume = np.asarray(foot.image, dtype=np.float32) * UNIT
    refit_materials(scanner, volume, [UNIT * 0.5, UNIT * 0.5], [0.0, UNIT * 0.5], steps=1, points_per_step=64, occupancy_weight=0.0)
    assert scanner.model.loss_scale == pytest.approx(loss_scale(in_units(foot, UNIT)))  # the refitted model keeps it


def test_a_field_without_bounds_gives_its_attenuation_in_the_scans_unit():
    cfg = presets.resolve(dataclasses.replace(methods.naf.config, preset="tiny"))
    models = []
    for unit in (1.0, UNIT):
        torch.manual_seed(0)
        model = cfg.model.setup()
        model.attenuation_unit.fill_(unit)
        model.loss_scale = unit
        models.append(model)
    points = torch.rand(64, 3) * 1.6 - 0.8
    with torch.no_grad():
        assert torch.allclose(models[1].query(points)["mu"], UNIT * models[0].query(points)["mu"], rtol=1e-5)
    batch = rays(8, 0)
    a = models[0].loss_dict({**batch, "projections": torch.full((8,), 0.3)}, 0.5, generator=torch.Generator().manual_seed(3))
    b = models[1].loss_dict({**batch, "projections": torch.full((8,), 0.3 * UNIT)}, 0.5, generator=torch.Generator().manual_seed(3))
    assert float(b["total"].detach()) == pytest.approx(float(a["total"].detach()), rel=1e-4)
    # the unit travels with the weights; a checkpoint from before it (no such key) was trained in data units
    state = models[1].state_dict()
    assert float(state["attenuation_unit"]) == UNIT
    fresh = cfg.model.setup()
    fresh.load_state_dict(state)
    assert float(fresh.attenuation_unit) == UNIT
    del state["attenuation_unit"]
    fresh.load_state_dict(state)
    assert float(fresh.attenuation_unit) == 1.0


def test_a_trainer_gives_a_field_without_bounds_the_scans_unit(foot, tmp_path):
    cfg = presets.resolve(dataclasses.replace(registry.load("methods", "naf").config, method="naf", preset="tiny"))
    scanner = Trainer(cfg, in_units(foot, UNIT), tmp_path, epochs=1, device="cpu", loss_scale=loss_scale(in_units(foot, UNIT)))
    assert float(scanner.model.attenuation_unit) == pytest.approx(scanner.model.loss_scale) and scanner.model.loss_scale > 1.0


def test_neas_wide_default_bounds_are_in_the_scans_unit(foot, tmp_path):
    from kneas_method.fields.attenuation import default_bounds

    cfg = presets.resolve(dataclasses.replace(registry.load("methods", "neas-1m").config, method="neas-1m", preset="tiny"))
    plain = Trainer(cfg, foot, tmp_path / "plain", epochs=1, device="cpu")  # the prior's trainer: no bounds given
    scanner = Trainer(cfg, in_units(foot, UNIT), tmp_path / "scanner", epochs=1, device="cpu", loss_scale=loss_scale(in_units(foot, UNIT)))
    alphas, betas = default_bounds(1)
    assert plain.model.bounds == (pytest.approx(alphas), pytest.approx(betas))
    unit = scanner.model.loss_scale
    assert unit > 1.0 and scanner.model.bounds == (pytest.approx([unit * a for a in alphas]), pytest.approx([unit * b for b in betas]))


def test_the_wide_bounds_option_is_in_the_scans_unit(foot, tmp_path):
    from kneas_method.engine.bounds_stage import estimate_bounds
    from kneas_method.fields.attenuation import default_bounds

    cfg = presets.resolve(dataclasses.replace(registry.load("methods", "k-neas").config, method="k-neas", preset="tiny",
                                              bounds_source="wide"))
    alphas, betas = default_bounds(int(cfg.model.num_materials))
    plain = estimate_bounds(cfg, foot, tmp_path, "cpu")
    assert plain.alphas == alphas and plain.betas == betas
    scanner = in_units(foot, UNIT)
    unit = loss_scale(scanner)
    scaled = estimate_bounds(cfg, scanner, tmp_path, "cpu", loss_scale=unit)
    assert scaled.alphas == pytest.approx([unit * a for a in alphas]) and scaled.betas == pytest.approx([unit * b for b in betas])
