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


# -- surface smoothness (the band correction's fits) ---------------------------------------

def _naive_surface_smoothness(grads, grads_step, distances, width):
    """One point and material at a time: the oracle of ``surface_smoothness``."""
    total, count = 0.0, 0
    for p in range(grads.shape[0]):
        for k in range(grads.shape[1]):
            w = math.exp(-(float(distances[p, k]) / width) ** 2)
            total += w * sum((float(grads[p, k, i]) - float(grads_step[p, k, i])) ** 2 for i in range(3))
            count += 1
    return total / count


def test_surface_smoothness_matches_the_naive_oracle():
    from kneas_method.losses.curvature import surface_smoothness

    g = torch.Generator().manual_seed(3)
    grads, step, dist = torch.randn(7, 2, 3, generator=g), torch.randn(7, 2, 3, generator=g), torch.randn(7, 2, generator=g)
    assert float(surface_smoothness(grads, step, dist, 0.7)) == pytest.approx(_naive_surface_smoothness(grads, step, dist, 0.7), rel=1e-5)


def _sphere_gradients(x, centre, radius):
    """Distances [P, 1] and their gradients [P, 1, 3] of a sphere."""
    r = x - centre
    n = r.norm(dim=-1, keepdim=True)
    return n - radius, (r / n)[:, None, :]


def test_surface_smoothness_is_zero_for_a_plane_and_grows_with_curvature():
    from kneas_method.losses.curvature import surface_smoothness

    g = torch.Generator().manual_seed(4)
    h = 0.02
    u = torch.randn(500, 3, generator=g)
    step = h * u / u.norm(dim=-1, keepdim=True)
    # a plane: every normal the same
    x = torch.rand(500, 3, generator=g) * 0.1
    normal = torch.tensor([0.6, 0.0, 0.8])
    d = (x @ normal)[:, None]
    plane = surface_smoothness(normal.expand(500, 1, 3), normal.expand(500, 1, 3), d, h)
    assert float(plane) == 0.0
    # spheres: points on each surface, the term ~ (h / R)^2, so a 4x smaller sphere gives ~16x more
    values = []
    for radius in (0.4, 0.1):
        dirs = torch.randn(500, 3, generator=g)
        on = radius * dirs / dirs.norm(dim=-1, keepdim=True)
        d, grads = _sphere_gradients(on, torch.zeros(3), radius)
        _, grads_step = _sphere_gradients(on + step, torch.zeros(3), radius)
        values.append(float(surface_smoothness(grads, grads_step, d, h)))
    assert values[0] > 0 and 10 < values[1] / values[0] < 25
    # far from every surface a point does not count
    far = torch.full((500, 1), 10 * h)
    assert float(surface_smoothness(grads, grads_step, far, h)) < 1e-30
