"""The voxel-planes quadrature (Joseph's rule on the scene's voxel grid) against the classical projector."""

from dataclasses import replace

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from kneas_method import methods, presets
from kneas_method.classical import forward
from kneas_method.data.simulate import SimulationConfig, make_geometry
from kneas_method.errors import ConfigError
from kneas_method.occupancy import box_of
from kneas_method.renderer import integrate_samples, voxel_plane_samples

ANGLES = np.linspace(0.0, np.pi, 5, endpoint=False) + 0.3


def geometry(mode, offsets):
    g = make_geometry(SimulationConfig(n_voxel=(12, 10, 8), voxel_mm=(5.0, 6.0, 7.0), n_detector=16, mode=mode))
    if offsets:
        g = replace(g, off_detector=(2.5 * g.d_detector[0], -1.2 * g.d_detector[1]),
                    off_origin=(1.5 * g.d_voxel[0], -1.0 * g.d_voxel[1], 0.5 * g.d_voxel[2]))
    return g


def trilinear(volume: torch.Tensor, g):
    """The trilinear interpolant of ``volume`` [nx, ny, nz] through its voxel centres (0 beyond them, fading over a voxel)."""
    axes = g.voxel_axes(dtype=torch.float64)
    c0 = torch.tensor([a[0] for a in axes], dtype=torch.float64)
    c1 = torch.tensor([a[-1] for a in axes], dtype=torch.float64)
    v = volume.permute(2, 1, 0)[None, None]

    def field(points):
        grid = (2 * (points - c0) / (c1 - c0) - 1).reshape(1, 1, 1, -1, 3)
        return F.grid_sample(v, grid, mode="bilinear", padding_mode="zeros", align_corners=True).reshape(-1)
    return field


@pytest.mark.parametrize("mode", ["cone", "parallel"])
@pytest.mark.parametrize("offsets", [False, True])
def test_voxel_planes_integrate_the_trilinear_volume_to_its_joseph_projection(mode, offsets):
    g = geometry(mode, offsets)
    x = torch.as_tensor(np.random.default_rng(3).random(g.n_voxel))
    origins, directions = g.rays(ANGLES, dtype=torch.float64)
    o, d = origins.reshape(-1, 3), directions.reshape(-1, 3)
    lo, hi = (torch.tensor(b, dtype=torch.float64) for b in box_of(g))
    R = len(o)
    ray, t, length = voxel_plane_samples(o, d, torch.full((R,), -1e3, dtype=torch.float64), torch.full((R,), 1e3, dtype=torch.float64),
                                         lo, hi, torch.tensor(g.n_voxel))
    assert torch.all(ray[1:] >= ray[:-1])  # rays in order
    same = ray[1:] == ray[:-1]
    assert torch.all((t[1:] - t[:-1])[same].abs() > 0)  # one sample per plane
    mu = trilinear(x, g)(o[ray] + t[:, None] * d[ray])
    _, line = integrate_samples(mu, ray, (length / g.scale)[ray], R)
    joseph = forward(x.numpy(), g, ANGLES).reshape(-1)
    assert np.abs(joseph).max() > 0.01
    np.testing.assert_allclose(line.numpy(), joseph, rtol=1e-9, atol=1e-12)


def test_voxel_planes_keep_only_the_planes_between_near_and_far():
    g = geometry("cone", False)
    o, d = (a.reshape(-1, 3) for a in g.rays(ANGLES[:1], dtype=torch.float64))
    lo, hi = (torch.tensor(b, dtype=torch.float64) for b in box_of(g))
    R = len(o)
    full = voxel_plane_samples(o, d, torch.full((R,), -1e3, dtype=torch.float64), torch.full((R,), 1e3, dtype=torch.float64),
                               lo, hi, torch.tensor(g.n_voxel))
    t_mid = full[1].median()
    near, far = torch.full((R,), float(t_mid) - 1e-3, dtype=torch.float64), torch.full((R,), 1e3, dtype=torch.float64)
    ray, t, _ = voxel_plane_samples(o, d, near, far, lo, hi, torch.tensor(g.n_voxel))
    assert torch.all(t >= near[ray]) and 0 < len(t) < len(full[1])
    empty = voxel_plane_samples(o, d, far, far, lo, hi, torch.tensor(g.n_voxel))
    assert empty[0].numel() == 0
    intensity, line = integrate_samples(torch.zeros(0, dtype=torch.float64), empty[0], torch.zeros(0, dtype=torch.float64), R)
    assert torch.all(line == 0) and torch.all(intensity == 1)


def test_model_with_voxel_planes_renders_what_the_classical_projector_gives():
    """A k-neas model whose query is a trilinear volume renders its Joseph projection; the grid is in the state_dict."""
    g = geometry("cone", True)
    cfg = presets.resolve(replace(methods.k_neas.config, preset="tiny"))
    model = replace(cfg.model, quadrature="voxel-planes").setup(scale=g.scale)
    o, d = (a.reshape(-1, 3).float() for a in g.rays(ANGLES, dtype=torch.float64))
    with pytest.raises(ConfigError, match="set_voxel_grid"):
        model.render(o, d, 0.0, 100.0)
    model.set_voxel_grid(g.n_voxel, *box_of(g))
    x = torch.as_tensor(np.random.default_rng(4).random(g.n_voxel))
    field = trilinear(x, g)
    model.query = lambda pts: {"mu": field(pts.double()).float()}
    model.eval()
    out = model.render(o, d, 0.0, 100.0)
    np.testing.assert_allclose(out.line_integral.numpy(), forward(x.numpy(), g, ANGLES).reshape(-1), rtol=2e-5, atol=1e-6)
    state = model.state_dict()
    assert state["voxel_count"].tolist() == list(g.n_voxel)
    with pytest.raises(ConfigError, match="bins"):
        cfg.model.setup(scale=g.scale).set_voxel_grid(g.n_voxel, *box_of(g))
