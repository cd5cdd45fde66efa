import pytest
import torch

from kneas_method.errors import ConfigError
from kneas_method.fields.sdf_field import SurfaceBoundary
from kneas_method.selectors.hard import HardSelectorConfig
from kneas_method.selectors.soft import SoftSelectorConfig, sequential_weights


def reference_weights(o):
    K = o.shape[-1]
    w = torch.empty_like(o)
    for i in range(K):
        w[:, i] = o[:, i]
        for j in range(i + 1, K):
            w[:, i] = w[:, i] * (1 - o[:, j])
    return w


@pytest.mark.parametrize("K", [1, 2, 3, 5])
def test_soft_weights_formula_bounds_and_gradients(K):
    torch.manual_seed(K)
    sel = SoftSelectorConfig().setup(num_materials=K)
    boundary = SurfaceBoundary(20.0)
    d = (torch.randn(200, K) * 0.1).requires_grad_(True)
    mu_bar = torch.rand(200, K) + torch.arange(K)
    mu, w = sel(d, mu_bar, boundary)
    o = boundary(d)
    assert torch.allclose(w, reference_weights(o), atol=1e-6)
    assert torch.all(w >= 0)
    total = w.sum(-1)
    assert torch.all(total <= 1 + 1e-6)
    assert torch.allclose(total, 1 - torch.prod(1 - o, -1), atol=1e-6)  # the rest is air
    assert torch.allclose(mu, (w * mu_bar).sum(-1))
    mu.sum().backward()
    assert d.grad is not None and d.grad.abs().sum() > 0
    assert boundary.log_s.grad is not None and boundary.log_s.grad != 0


def test_soft_single_material_is_neas():
    sel = SoftSelectorConfig().setup(num_materials=1)
    b = SurfaceBoundary()
    d, mb = torch.randn(30, 1), torch.rand(30, 1)
    mu, _ = sel(d, mb, b)
    assert torch.allclose(mu, mb[:, 0] * torch.sigmoid(-20 * d[:, 0]))


def test_highest_material_wins_inside_all_surfaces():
    o = torch.tensor([[1.0, 1.0, 1.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    w = sequential_weights(o)
    assert torch.equal(w, torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]]))


def test_soft_approaches_hard_as_s_grows():
    torch.manual_seed(0)
    d = torch.randn(1000, 2) * 0.3
    d = d + 0.05 * torch.sign(d)  # keep away from the surfaces
    mu_bar = torch.rand(1000, 2) + torch.tensor([0.0, 1.0])
    hard = HardSelectorConfig().setup(num_materials=2)
    soft = SoftSelectorConfig().setup(num_materials=2)
    errors = []
    for s in (5.0, 50.0, 500.0):
        b = SurfaceBoundary(s)
        with torch.no_grad():
            errors.append((soft(d, mu_bar, b)[0] - hard(d, mu_bar, b)[0]).abs().max().item())
    assert errors[0] > errors[1] > errors[2] and errors[2] < 1e-6


def test_hard_selector_definition():
    b = SurfaceBoundary(20.0)
    hard = HardSelectorConfig().setup(num_materials=2)
    d = torch.tensor([[-0.1, -0.05], [-0.1, 0.05], [0.1, 0.3]])
    mb = torch.tensor([[1.0, 2.0]] * 3)
    mu, w = hard(d, mb, b)
    o = b(d)
    expected = torch.stack([2.0 * o[0, 1], 1.0 * o[1, 0], 1.0 * o[2, 0]])
    assert torch.allclose(mu, expected)
    assert w[0, 0] == 0 and w[1, 1] == 0


@pytest.mark.parametrize("K", [1, 3, 4])
def test_hard_selector_rejects_other_k(K):
    with pytest.raises(ConfigError, match=r"only with K = 2.*got K = %d" % K):
        HardSelectorConfig().setup(num_materials=K)
