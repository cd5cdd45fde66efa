
import pytest
import torch

from kneas_method.errors import ConfigError
from kneas_method.fields.attenuation import (
    IndependentAttenuationConfig, SharedAttenuationConfig, SingleAttenuationConfig, default_bounds,
)
from kneas_method.fields.naf_field import NAFFieldConfig
from kneas_method.fields.sdf_field import SDFFieldConfig, SurfaceBoundary
from kneas_method.model import build_component

TINY = {"num_levels": 2, "log2_hashmap_size": 8, "base_resolution": 4}


def n_params(m):
    return sum(p.numel() for p in m.parameters())


def tiny_encoding():
    return build_component("encodings", "hashgrid", TINY).setup()


def test_attenuation_parameter_counts_match_spec():
    # single: Linear(8,64)+Linear(64,1); shared: body Linear(8,64) + K x [Linear(64,64)+Linear(64,1)];
    # independent: K x [Linear(8,64)+Linear(64,64)+Linear(64,1)]
    assert n_params(SingleAttenuationConfig().setup(feature_dim=8, num_materials=1)) == 576 + 65
    assert n_params(SharedAttenuationConfig().setup(feature_dim=8, num_materials=4)) == 576 + 4 * (4160 + 65)
    assert n_params(IndependentAttenuationConfig().setup(feature_dim=8, num_materials=2)) == 2 * (576 + 4160 + 65)


@pytest.mark.parametrize("cfg,K", [(SingleAttenuationConfig(), 1), (SharedAttenuationConfig(), 3), (IndependentAttenuationConfig(), 2)])
def test_attenuation_respects_bounds(cfg, K):
    net = cfg.setup(feature_dim=8, num_materials=K)
    alphas = [0.5 + k for k in range(K)]
    betas = [0.2 * k for k in range(K)]
    net.set_bounds(alphas, betas)
    f = torch.randn(500, 8) * 50  # saturate the sigmoid both ways
    mu = net(f)
    assert mu.shape == (500, K)
    a, b = torch.tensor(alphas), torch.tensor(betas)
    assert torch.all(mu >= b - 1e-6) and torch.all(mu <= a + b + 1e-6)
    assert torch.allclose(mu, a * torch.sigmoid(net.raw(f)) + b)
    state = net.state_dict()
    assert torch.equal(state["alphas"], a) and torch.equal(state["betas"], b)
    fresh = cfg.setup(feature_dim=8, num_materials=K)
    fresh.load_state_dict(state)
    assert torch.equal(fresh(f), mu)


def test_single_attenuation_rejects_k_and_bad_bounds():
    with pytest.raises(ConfigError, match="single"):
        SingleAttenuationConfig().setup(feature_dim=8, num_materials=2)
    net = SharedAttenuationConfig().setup(feature_dim=8, num_materials=2)
    with pytest.raises(ConfigError, match="exactly 2"):
        net.set_bounds([1.0], [0.0])
    with pytest.raises(ConfigError, match="alpha > 0"):
        net.set_bounds([1.0, -1.0], [0.0, 1.0])


def test_default_bounds_wide_for_one_material():
    assert default_bounds(1) == ([3.4], [0.1])
    a, b = default_bounds(3)
    assert b[0] == pytest.approx(0.1) and b[-1] + a[-1] == pytest.approx(3.5) and b == sorted(b)


def test_sdf_field_shapes_and_gradients():
    field = SDFFieldConfig().setup(encoding=tiny_encoding(), num_materials=3)
    x = (torch.rand(64, 3) * 2 - 1).requires_grad_(True)
    out = field(x)
    d, f = out.distances, out.features
    assert d.shape == (64, 3) and f.shape == (64, 8) and d.dtype == torch.float32
    (g,) = torch.autograd.grad(d.sum(), x, create_graph=True)
    assert g.abs().sum() > 0
    g.pow(2).sum().backward()  # second order through the hash grid
    assert field.encoding.parameters().__next__().grad is not None
    # points outside the encoding's box are clamped, not an error
    d_out = field(torch.tensor([[5.0, 0.0, 0.0], [1.0, 0.0, 0.0]])).distances
    assert torch.allclose(d_out[0], d_out[1])


def test_surface_boundary():
    omega = SurfaceBoundary()
    assert abs(omega.s.item() - 20.0) < 1e-4 and omega.s.requires_grad and n_params(omega) == 1
    d = torch.tensor([-1.0, 0.0, 1.0])
    o = omega(d)
    assert torch.allclose(o, torch.sigmoid(-20 * d))
    assert o[0] > 0.99 and o[1] == 0.5 and o[2] < 0.01  # inside (d<0) is occupied
    omega(torch.tensor([-0.05, 0.02])).sum().backward()
    assert omega.log_s.grad is not None and omega.log_s.grad != 0


def test_naf_field_non_negative_and_trainable():
    field = NAFFieldConfig().setup(encoding=tiny_encoding())
    assert field.has_surfaces is False and field.num_distances == 0
    x = torch.rand(100, 3) * 2 - 1
    mu = field(x).mu
    assert mu.shape == (100,) and torch.all(mu >= 0)
    mu.sum().backward()
    assert all(p.grad is not None for p in field.parameters())
    with pytest.raises(ConfigError, match="activation"):
        NAFFieldConfig(activation="tanh").setup(encoding=tiny_encoding())


def test_encoding_selectable_by_name_frequency():
    pytest.importorskip("kneas_method.fields.frequency")
    enc = build_component("encodings", "frequency", {"num_frequencies": 4}).setup()
    field = SDFFieldConfig().setup(encoding=enc, num_materials=2)
    out = field(torch.rand(10, 3))
    d, f = out.distances, out.features
    assert d.shape == (10, 2) and field.mlp[0].in_features == enc.n_output_dims
