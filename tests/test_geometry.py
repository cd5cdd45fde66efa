import math

import numpy as np
import torch

from kneas_method.geometry import Geometry


def make(mode="cone", **kw):
    args = dict(mode=mode, DSD=1500.0, DSO=1000.0, nDetector=(64, 48), dDetector=(4.0, 4.0),
                nVoxel=(32, 32, 32), dVoxel=(4.0, 4.0, 4.0))
    args.update(kw)
    return Geometry.from_mm(**args)


def test_scale_puts_volume_in_unit_sphere():
    g = make()
    half_diag_m = 0.5 * math.sqrt(3) * 0.128
    assert math.isclose(g.scale, 1 / half_diag_m)
    corner = torch.tensor(g.volume_half_size, dtype=torch.float64)
    assert math.isclose(float(corner.norm()), 1.0, rel_tol=1e-9)
    assert math.isclose(g.dso, 1.0 * g.scale)  # 1000 mm = 1 m
    assert math.isclose(g.mm_per_unit * g.scale, 1000.0)


def test_round_trip_mm():
    g = make(offOrigin=(1.0, 2.0, 3.0), offDetector=(0.5, -0.5))
    back = g.to_mm()
    g2 = Geometry.from_mm(**{k: back[k] for k in ("mode", "DSD", "DSO", "nDetector", "dDetector", "nVoxel", "dVoxel", "offOrigin", "offDetector")})
    assert g2 == g or all(np.allclose(np.asarray(getattr(g, f)), np.asarray(getattr(g2, f))) for f in ("dsd", "dso", "d_detector", "d_voxel", "off_origin", "scale"))


def test_central_ray_at_angle_zero_points_to_origin():
    g = make(nDetector=(2, 2))
    o, d = g.rays([0.0])
    assert o.shape == (1, 2, 2, 3) and d.shape == (1, 2, 2, 3)
    assert torch.allclose(o[0, 0, 0], torch.tensor([g.dso, 0.0, 0.0]))
    # mean of the four central pixels' directions is the central axis (-1, 0, 0)
    assert torch.allclose(d[0].reshape(-1, 3).mean(0), torch.tensor([-1.0, 0.0, 0.0]), atol=1e-6)
    # u (column) runs along +y, v (row) along -z at theta = 0
    assert d[0, 0, 1, 1] > d[0, 0, 0, 1]
    assert d[0, 1, 0, 2] < d[0, 0, 0, 2]


def test_rays_follow_spec_formula():
    g = make()
    theta = 0.7
    o, d = g.rays([theta])
    j, i = 5, 9
    (nu, nv), (du, dv) = g.n_detector, g.d_detector
    u = (i + 0.5 - nu / 2) * du
    v = (j + 0.5 - nv / 2) * dv
    c, s = math.cos(theta), math.sin(theta)
    rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    rz90 = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]])
    rxm90 = np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]])
    expected = rz @ rz90 @ rxm90 @ np.array([u / g.dsd, v / g.dsd, 1.0])
    assert np.allclose(d[0, j, i].numpy(), expected, atol=1e-6)
    assert np.allclose(o[0, j, i].numpy(), [g.dso * c, g.dso * s, 0], atol=1e-6)


def test_selected_pixels_match_full_grid():
    g = make()
    o, d = g.rays([0.1, 2.0])
    pix = torch.tensor([[[3, 4], [10, 0]], [[0, 0], [47, 63]]])
    o2, d2 = g.rays([0.1, 2.0], pixels=pix)
    for n in range(2):
        for m in range(2):
            j, i = pix[n, m]
            assert torch.allclose(d2[n, m], d[n, j, i]) and torch.allclose(o2[n, m], o[n, j, i])


def test_parallel_beam():
    g = make(mode="parallel", dDetector=(1.0, 1.0))
    o, d = g.rays([0.0])
    assert torch.allclose(d[0, 3, 3], torch.tensor([-1.0, 0.0, 0.0]))
    assert torch.allclose(o[0, 0, 0, 0], torch.tensor(g.dso))


def test_near_far_covers_volume():
    g = make()
    near, far = g.near_far
    r = math.hypot(*g.volume_half_size[:2])
    assert math.isclose(near, g.dso - r - 0.005) and math.isclose(far, g.dso + r + 0.005)
    # every voxel centre lies within [near, far] along the central ray
    assert near < g.dso - g.volume_half_size[0] and far > g.dso + g.volume_half_size[0]


def test_voxel_centres():
    g = make(nVoxel=(4, 2, 3), offOrigin=(4.0, 0.0, 0.0))
    c = g.voxel_centres(dtype=torch.float64)
    assert c.shape == (4, 2, 3, 3)
    dx = g.d_voxel[0]
    assert math.isclose(float(c[1, 0, 0, 0] - c[0, 0, 0, 0]), dx, rel_tol=1e-9)
    assert math.isclose(float(c[:, 0, 0, 0].mean()), g.off_origin[0], rel_tol=1e-9)
    assert math.isclose(float(c[0, 0, 0, 1]), -g.d_voxel[1] / 2, rel_tol=1e-9)
