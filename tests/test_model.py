import dataclasses
import math

import pytest
import torch

from kneas_method import methods, presets
from kneas_method.errors import ConfigError
from kneas_method.renderer import beer_lambert, segment_lengths


def tiny(spec, **kw):
    cfg = dataclasses.replace(spec.config, preset="tiny", **kw)
    return presets.resolve(cfg)


def model_of(spec, scale=1.0, **kw):
    torch.manual_seed(0)
    return tiny(spec, **kw).model.setup(scale=scale)


@pytest.mark.parametrize("scale", [1.0, 4.5])
def test_constant_mu_renders_exact_chord(scale):
    model = model_of(methods.neas_1m, scale=scale)
    mu = 1.7  # data units, 1/m
    model.query = lambda pts: {"mu": torch.full((len(pts),), mu)}
    origins = torch.tensor([[0.0, -3.0, 0.0], [2.0, 0.0, 0.0]])
    directions = torch.tensor([[0.0, 2.0, 0.0], [-1.0, 0.5, 0.5]])
    near, far = 1.0, 2.2
    out = model.render(origins, directions, near, far, n_samples=33, stratified=False)
    length_m = (far - near) * directions.norm(dim=-1) / scale
    assert torch.allclose(out.line_integral, mu * length_m, rtol=1e-6)
    assert torch.allclose(out.intensity, torch.exp(-mu * length_m), rtol=1e-6)


def test_renderer_functions():
    t = torch.tensor([[0.0, 1.0, 3.0]])
    d = torch.tensor([[0.0, 3.0, 4.0]])
    delta = segment_lengths(t, d, scale=2.0)
    assert torch.allclose(delta, torch.tensor([[2.5, 5.0, 0.0]]))
    I, line = beer_lambert(torch.tensor([[1.0, 2.0, 100.0]]), delta)
    assert line.item() == pytest.approx(12.5) and I.item() == pytest.approx(math.exp(-12.5))


def test_render_and_query_shapes():
    model = model_of(methods.k_neas)
    o = torch.tensor([[0.0, -3.0, 0.0]] * 4)
    d = torch.tensor([[0.0, 1.0, 0.05 * k] for k in range(4)])
    model.eval()
    out = model.render(o, d, 2.0, 4.0)
    assert out.intensity.shape == (4,) and out.line_integral.shape == (4,)
    assert torch.allclose(out.intensity, torch.exp(-out.line_integral))
    assert torch.all(out.intensity <= 1) and torch.all(out.intensity > 0)
    q = model.query(torch.rand(10, 3))
    assert set(q) == {"mu", "weights", "distances", "mu_materials"}
    assert q["weights"].shape == (10, 3) and q["mu_materials"].shape == (10, 3)
    naf = model_of(methods.naf)
    assert not naf.has_surfaces and naf.num_materials == 0
    assert set(naf.query(torch.rand(5, 3))) == {"mu"}
    with pytest.raises(ConfigError, match="no materials"):
        naf.set_bounds([1.0], [0.0])


def test_bounds_in_data_units_and_state_dict():
    model = model_of(methods.k_neas)
    assert model.num_materials == 3 and model.has_surfaces
    model.set_bounds([0.2, 0.3, 1.0], [0.0, 0.2, 0.5])
    q = model.query(torch.rand(50, 3) * 2 - 1)
    mb = q["mu_materials"]
    assert torch.all(mb >= torch.tensor([0.0, 0.2, 0.5]) - 1e-6) and torch.all(mb <= torch.tensor([0.2, 0.5, 1.5]) + 1e-6)
    state = model.state_dict()
    other = model_of(methods.k_neas)
    other.load_state_dict(state)
    assert other.bounds == model.bounds
    # given in the config
    m1 = model_of(methods.neas_1m)
    assert m1.bounds == ([pytest.approx(3.4)], [pytest.approx(0.1)])  # NeAS wide defaults


def batch(n_obj=12, n_air=4):
    torch.manual_seed(1)
    o = torch.tensor([0.0, -3.0, 0.0]).expand(n_obj + n_air, 3).clone()
    d = torch.cat([torch.rand(n_obj + n_air, 2) * 0.4 - 0.2, torch.ones(n_obj + n_air, 1)], -1)[:, [0, 2, 1]]
    is_air = torch.zeros(n_obj + n_air, dtype=torch.bool)
    is_air[n_obj:] = True
    p = torch.where(is_air, 0.0, 0.3)
    return {"origins": o, "directions": d, "projections": p, "is_air": is_air, "near": 2.0, "far": 4.0}


def test_loss_dict_terms_and_floater_schedule():
    model = model_of(methods.k_neas)
    b = batch()
    early = model.loss_dict(b, progress=0.1)
    late = model.loss_dict(b, progress=0.5)
    assert set(early) == {"intensity", "floater", "eikonal", "total"}
    assert set(late) == {"intensity", "eikonal", "total"}
    assert torch.allclose(early["total"], early["intensity"] + early["floater"] + early["eikonal"])
    # the floater term is λ_aux · mean((I_air − 1)^2) of the air rays
    assert early["floater"].item() > 0 and early["floater"].item() < 0.1 * 1.0
    no_floater = model_of(methods.kselector).loss_dict(b, progress=0.0)
    assert "floater" not in no_floater
    naf = model_of(methods.naf).loss_dict(b, progress=0.0)
    assert set(naf) == {"intensity", "total"}


def test_eikonal_in_model_matches_component_on_same_points():
    model = model_of(methods.neas_1m)
    torch.manual_seed(3)
    x = (torch.rand(100, 3) * 1.6 - 0.8).requires_grad_(True)
    q = model.query(x)
    reuse = model.eikonal(model.field.distances, x, q["distances"])
    fresh = model.eikonal(model.field.distances, x.detach())
    assert reuse.item() == pytest.approx(fresh.item(), rel=1e-5)
    fd_cfg = tiny(methods.neas_1m)
    fd_model = dataclasses.replace(fd_cfg.model, eikonal_mode="finite-difference", eikonal_fraction=0.5).setup()
    # default step: half the finest cell (tiny grid: base 4, 3 levels -> 16 cells over [-1, 1])
    assert fd_model.eikonal.step == pytest.approx(1 / 16)
    assert "eikonal" in fd_model.loss_dict(batch(), 0.5)


def test_one_training_step_reduces_intensity_loss():
    model = model_of(methods.neas_1m)
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    b = batch()
    g = torch.Generator().manual_seed(0)
    first = None
    for _ in range(6):
        g.manual_seed(0)
        loss = model.loss_dict(b, 0.5, generator=g)
        first = loss["intensity"].item() if first is None else first
        opt.zero_grad()
        loss["total"].backward()
        opt.step()
    assert loss["intensity"].item() < first
