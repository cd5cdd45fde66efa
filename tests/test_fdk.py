"""FDK / FBP on an analytic ball: exact projections from Geometry.rays (chord lengths)."""

import math

import numpy as np
import pytest
import torch

from kneas_method.data.scene import Scene, Views
from kneas_method.errors import ConfigError, KneasError
from kneas_method.classical.fdk import angular_widths, column_presence, fdk_reconstruct, ramp_filter, redundancy_weights
from kneas_method.evaluation.metrics import psnr3d
from kneas_method.geometry import Geometry

CENTRE = (0.25, -0.15, 0.2)  # model units; a different value on every axis catches swapped/flipped axes
RADIUS = 0.3
MU = 0.8  # data units (1/m)


def make_geometry(mode="cone", n_voxel=(32, 28, 24), n_det=(48, 40)):
    vox = 4.0  # mm
    if mode == "cone":
        d_det = 128.0 * 1.5 * 1.25 / 48  # covers the magnified volume
    else:
        d_det = 128.0 * 1.25 / 48
    return Geometry.from_mm(mode=mode, DSD=1500.0, DSO=1000.0, nDetector=n_det, dDetector=(d_det, d_det),
                            nVoxel=n_voxel, dVoxel=(vox, vox, vox))


def ball_projections(g, angles):
    """Exact line integrals [N, nV, nU] of a ball of MU (1/m): chord length (m) x MU."""
    o, d = g.rays(torch.as_tensor(angles), dtype=torch.float64)
    dn = d / d.norm(dim=-1, keepdim=True)
    w = torch.tensor(CENTRE, dtype=torch.float64) - o
    t = (w * dn).sum(-1)
    dist2 = (w * w).sum(-1) - t * t
    chord_model = 2 * torch.sqrt(torch.clamp(RADIUS**2 - dist2, min=0))
    return (chord_model / g.scale * MU).numpy().astype(np.float32)


def ball_volume(g, ss=3):
    """True volume [nx, ny, nz] with partial-volume (supersampled) edges, data units."""
    x = g.voxel_centres(dtype=torch.float64)
    dv = torch.tensor(g.d_voxel, dtype=torch.float64)
    offs = (torch.arange(ss, dtype=torch.float64) + 0.5) / ss - 0.5
    acc = torch.zeros(x.shape[:3], dtype=torch.float64)
    c = torch.tensor(CENTRE, dtype=torch.float64)
    for a in offs:
        for b in offs:
            for e in offs:
                acc += ((x + torch.stack([a, b, e]) * dv - c).norm(dim=-1) <= RADIUS).double()
    return (acc / ss**3 * MU).numpy()


def check_ball(g, rec, tol):
    x = g.voxel_centres(dtype=torch.float64).numpy()
    r = np.linalg.norm(x - np.array(CENTRE), axis=-1)
    core, outside = r < 0.5 * RADIUS, r > 1.4 * RADIUS
    assert rec.shape == tuple(g.n_voxel) and rec.dtype == np.float32
    assert abs(rec[core].mean() / MU - 1) < tol, rec[core].mean()
    assert abs(rec[outside].mean()) < 0.01 * MU
    # the ball is where it should be, on every axis (thresholded centroid)
    m = rec > 0.5 * MU
    centroid = x[m].mean(0)
    assert np.allclose(centroid, CENTRE, atol=0.5 * max(g.d_voxel)), centroid
    gt = ball_volume(g)
    p, p0 = psnr3d(rec, gt), psnr3d(np.zeros_like(gt), gt)
    assert p > p0 + 15, (p, p0)
    return p


def test_cone_full_scan_scale_and_orientation():
    g = make_geometry()
    angles = np.linspace(0, 2 * math.pi, 90, endpoint=False) + 0.1
    rec = fdk_reconstruct(g, angles, ball_projections(g, angles))
    check_ball(g, rec, tol=0.03)


def test_cone_half_scan_naf_protocol():
    # NAF scenes: 180 degrees, less than a short scan; the centre stays well-scaled
    g = make_geometry()
    angles = np.linspace(0, math.pi, 90, endpoint=False)
    proj = ball_projections(g, angles)
    rec = fdk_reconstruct(g, angles, proj)
    check_ball(g, rec, tol=0.05)
    # without redundancy weighting (plain 1/2 factor) the scale is off by about 2x
    plain = fdk_reconstruct(g, angles, proj, redundancy=False, filter="hann")
    x = g.voxel_centres(dtype=torch.float64).numpy()
    core = np.linalg.norm(x - np.array(CENTRE), axis=-1) < 0.5 * RADIUS
    assert plain[core].mean() < 0.6 * MU


def test_cone_short_scan_and_scene_input():
    g = make_geometry(n_voxel=(24, 24, 24), n_det=(40, 40))
    u = (g.n_detector[0] / 2) * g.d_detector[0]
    span = math.pi + 2 * math.atan(u / g.dsd)
    angles = np.linspace(0, span, 60, endpoint=False) - 1.0
    views = Views(angles, ball_projections(g, angles))
    scene = Scene(name="ball", geometry=g, train=views, val=views.subset(slice(0, 2)))
    rec = fdk_reconstruct(scene, filter="shepp-logan")
    check_ball(g, rec, tol=0.04)


def test_parallel_beam_fbp():
    g = make_geometry("parallel", n_voxel=(24, 24, 24), n_det=(40, 40))
    angles = np.linspace(0, math.pi, 60, endpoint=False)
    rec = fdk_reconstruct(g, angles, torch.as_tensor(ball_projections(g, angles)))
    check_ball(g, rec, tol=0.03)


def test_redundancy_weights_pairs_sum_to_one():
    rng = np.random.default_rng(0)
    gmax = 0.12
    for arc in (math.pi, math.pi + 2 * gmax, 1.5 * math.pi):
        beta = rng.uniform(0, arc, 400)
        gam = rng.uniform(-gmax, gmax, 400)
        w = np.array([redundancy_weights([b], [g], gmax, arc=(0.0, arc))[0, 0] for b, g in zip(beta, gam)])
        conj = beta + math.pi - 2 * gam
        conj_in = np.mod(conj, 2 * math.pi) < arc
        wc = np.array([redundancy_weights([b], [-g], gmax, arc=(0.0, arc))[0, 0] for b, g in zip(conj, gam)])
        assert np.allclose(w[conj_in] + wc[conj_in], 1.0)
        assert np.allclose(w[~conj_in], 1.0)  # measured once: counts once
        assert np.all((w >= 0) & (w <= 1))
    full = redundancy_weights(np.linspace(0, 2 * math.pi, 36, endpoint=False), np.linspace(-gmax, gmax, 5), gmax)
    assert np.allclose(full, 0.5)


def test_angular_widths():
    a = np.linspace(0, math.pi, 10, endpoint=False)
    w, start, arc = angular_widths(a[::-1])
    assert np.allclose(w, math.pi / 10) and math.isclose(arc, math.pi) and math.isclose(start, -math.pi / 20)
    with pytest.raises(KneasError, match="same angle"):
        angular_widths([0.0, 0.0, 1.0])


def test_ramp_filter_matches_direct_convolution():
    rng = np.random.default_rng(1)
    row = torch.tensor(rng.uniform(0, 1, (3, 17)), dtype=torch.float64)
    pitch = 0.7
    k = np.arange(-16, 17)
    h = np.zeros(len(k))
    h[k == 0] = 1 / (4 * pitch**2)
    odd = np.abs(k) % 2 == 1
    h[odd] = -1 / (np.pi**2 * k[odd].astype(float) ** 2 * pitch**2)
    direct = np.stack([pitch * np.convolve(r, h)[16:16 + 17] for r in row.numpy()])
    assert np.allclose(ramp_filter(row, pitch).numpy(), direct, atol=1e-10)


def test_errors():
    g = make_geometry(n_voxel=(8, 8, 8), n_det=(16, 16))
    a = np.linspace(0, math.pi, 4, endpoint=False)
    with pytest.raises(ConfigError, match="filter"):
        fdk_reconstruct(g, a, np.zeros((4, 16, 16), np.float32), filter="butterworth")
    with pytest.raises(KneasError, match="nV, nU"):
        fdk_reconstruct(g, a, np.zeros((4, 16, 15), np.float32))
    with pytest.raises(KneasError, match="angles and projections"):
        fdk_reconstruct(g)


def test_detector_and_volume_offsets():
    g = Geometry.from_mm(mode="cone", DSD=1500.0, DSO=1000.0, nDetector=(56, 48), dDetector=(5.0, 5.0),
                         nVoxel=(32, 28, 24), dVoxel=(4.0, 4.0, 4.0), offDetector=(12.0, -9.0), offOrigin=(6.0, -4.0, 3.0))
    angles = np.linspace(0, 2 * math.pi, 60, endpoint=False)
    check_ball(g, fdk_reconstruct(g, angles, ball_projections(g, angles)), tol=0.03)


def test_column_presence_shares_the_lines_seen_on_both_sides_of_the_centre():
    lo, hi = -0.03, 0.17
    g = np.linspace(lo, -lo, 41)
    assert np.allclose(column_presence(g, (lo, hi)) + column_presence(-g, (lo, hi)), 1.0)  # Wang's weights
    assert column_presence(np.array([lo - 1e-3, hi + 1e-3]), (lo, hi)).tolist() == [0.0, 0.0]  # off the detector
    assert column_presence(np.array([0.1]), (0.02, 0.17)).tolist() == [1.0]  # not crossing the centre: no taper
    angles = np.linspace(0, 2 * math.pi, 36, endpoint=False)
    w = redundancy_weights(angles, np.array([-0.02, 0.0, 0.02, 0.05, 0.16]), hi, fan=(lo, hi))
    assert np.allclose(w[:, 1], 0.5) and np.allclose(w[:, 0] + w[:, 2], 1.0)  # seen from both sides
    assert np.allclose(w[:, 3:], 1.0)  # its conjugate falls off the detector: counts once


@pytest.mark.parametrize("columns,past_centre", [(100, 20), (90, 10)])
def test_an_offset_half_fan_detector_reconstructs_as_a_centred_one(columns, past_centre):
    from dataclasses import replace

    from kneas_method.classical.projector import forward

    g = Geometry.from_mm(mode="cone", DSD=1200.0, DSO=750.0, nDetector=(160, 24), dDetector=(2.0, 2.0), nVoxel=(64, 64, 8),
                         dVoxel=(2.0, 2.0, 2.0))
    x = np.arange(64) - 31.5
    r = np.hypot(*np.meshgrid(x, x, indexing="ij"))
    vol = np.repeat(np.where(r < 28, 0.5, 0.0)[..., None], 8, 2).astype(np.float32)
    angles = np.linspace(0, 2 * math.pi, 120, endpoint=False)
    du = g.d_detector[0]
    half = replace(g, n_detector=(columns, 24), off_detector=((columns / 2 - past_centre) * du, 0.0))  # one side and a little more
    rec = fdk_reconstruct(half, angles, forward(vol, half, angles))[:, :, 4]
    for r0 in range(0, 24, 4):  # every ring at the right level, inside the part seen from both sides and beyond it
        ring = (r >= r0) & (r < r0 + 4)
        assert abs(rec[ring].mean() / 0.5 - 1.0) < 0.01, (r0, rec[ring].mean())
