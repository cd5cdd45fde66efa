import math

import pytest
import torch

from kneas_method.errors import ConfigError
from kneas_method.losses.eikonal import EikonalLossConfig
from kneas_method.losses.floater import FloaterLossConfig
from kneas_method.losses.intensity import IntensityLossConfig


def sphere(scale=1.0, r=0.5):
    def fn(x):  # [P, 3] -> [P, 2]: two concentric spheres
        n = x.norm(dim=-1, keepdim=True)
        return scale * torch.cat([n - r, n - r / 2], dim=-1)

    return fn


def points(n=400):
    torch.manual_seed(0)
    x = torch.randn(n, 3)
    return x / x.norm(dim=-1, keepdim=True) * (0.2 + 0.6 * torch.rand(n, 1))  # away from the centre


@pytest.mark.parametrize("mode", ["autograd", "finite-difference"])
@pytest.mark.parametrize("scale,expected", [(1.0, 0.0), (2.0, 1.0), (0.5, 0.25)])
def test_eikonal_on_analytic_spheres(mode, scale, expected):
    loss = EikonalLossConfig(mode=mode, fd_step=1e-3).setup()
    value = loss(sphere(scale), points())
    assert value.item() == pytest.approx(expected, abs=1e-4)


def test_eikonal_autograd_and_fd_agree_and_reuse_distances():
    fn = sphere(2.0)
    x = points()
    auto = EikonalLossConfig(mode="autograd").setup()
    fd = EikonalLossConfig(mode="finite-difference", fd_step=1e-3).setup()
    g_auto = auto.gradients(fn, x)
    g_fd = fd.gradients(fn, x)
    assert g_auto.shape == (len(x), 2, 3)
    assert torch.allclose(g_auto, g_fd, atol=1e-3)
    # the model's path: distances already computed on points that require grad
    xg = x.clone().requires_grad_(True)
    d = fn(xg)
    calls = []
    counting = lambda p: calls.append(1) or fn(p)
    reused = auto(counting, xg, d)
    assert not calls and reused.item() == pytest.approx(1.0, abs=1e-4)
    # mask keeps only some points
    mask = torch.zeros(len(x), dtype=torch.bool)
    assert auto(fn, x, mask=mask).item() == 0.0


def test_eikonal_gradients_flow_to_parameters():
    w = torch.tensor(1.5, requires_grad=True)
    fn = lambda x: w * (x.norm(dim=-1, keepdim=True) - 0.5)
    for mode in ("autograd", "finite-difference"):
        w.grad = None
        loss = EikonalLossConfig(mode=mode, fd_step=1e-3).setup()(fn, points(50))
        loss.backward()
        assert w.grad.item() == pytest.approx(2 * (1.5 - 1.0), rel=1e-2)  # d/dw (w-1)^2


def test_eikonal_rejects_unknown_mode():
    with pytest.raises(ConfigError, match="autograd, finite-difference"):
        EikonalLossConfig(mode="exact").setup()


def test_intensity_and_floater_losses():
    I = torch.tensor([0.5, 1.0])
    p = torch.tensor([math.log(2.0), 0.0])  # exp(-p) = 0.5, 1
    assert IntensityLossConfig().setup()(I, p).item() == pytest.approx(0.0, abs=1e-7)
    assert IntensityLossConfig().setup()(torch.tensor([0.0, 0.0]), p).item() == pytest.approx((0.25 + 1.0) / 2)
    fl = FloaterLossConfig().setup()
    assert fl(torch.tensor([1.0, 0.5])).item() == pytest.approx(0.125)
    assert fl.active(0.0) and fl.active(0.19) and not fl.active(0.2) and not fl.active(0.9)
    assert FloaterLossConfig(fraction=0.5).setup().active(0.4)
