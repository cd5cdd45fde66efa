"""The fast training path computes what the straightforward (reference) one does.

Exact parts (equal within float32 round-off): the vectorised hash grid vs the
per-level loop; the forward-mode K distance gradients vs K separate
double-backward passes; the batched autograd K gradients; and a whole
``CTModel.loss_dict`` + backward, fast vs the straightforward model
(``benchmarks/naive.py``, the oracles kept outside the package). Approximate part:
the finite-difference eikonal vs the exact one on the model's own SDF.
"""

import dataclasses

import pytest
import torch

from kneas_method import methods, presets
from kneas_method.fields.hash_grid import HashGridConfig, HashGridEncoding
from kneas_method.fields.sdf_field import SDFField, SDFFieldConfig
from kneas_method.losses.eikonal import EikonalLoss, EikonalLossConfig

from benchmarks.naive import ReferenceHashGrid, eikonal_k_loop, hash_grid_loop, make_reference


def grid(force_hash=False, levels=5):
    torch.manual_seed(0)
    # base 4, scale 2, 2^10 entries: levels 0-1 dense, the rest hashed (unless force_hash)
    enc = HashGridEncoding(HashGridConfig(num_levels=levels, log2_hashmap_size=10, base_resolution=4, init_scale=1.0,
                                          implementation="torch"), force_hash=force_hash)
    return enc


def pts(n=300, spread=1.2, seed=1):
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(n, 3, generator=g) * 2 - 1) * spread  # some outside [-1, 1]^3


def table_grad(enc, fn, x):
    enc.table.grad = None
    y = fn(x)
    w = torch.linspace(-1, 1, y.shape[-1])
    (y * w).sum().backward()
    return y.detach(), enc.table.grad.clone()


@pytest.mark.parametrize("force_hash", [False, True])
def test_vectorised_grid_equals_per_level_loop(force_hash):
    enc = grid(force_hash)
    x = pts()
    y_fast, g_fast = table_grad(enc, enc.encode, x)
    y_ref, g_ref = table_grad(enc, lambda pts_: hash_grid_loop(enc, pts_), x)
    assert torch.allclose(y_fast, y_ref, atol=1e-6)
    assert torch.allclose(g_fast, g_ref, atol=1e-5)
    assert torch.allclose(ReferenceHashGrid(enc)(x), y_ref)


def test_grid_jacobian_equals_autograd_including_clamped_points():
    enc = grid()
    x = pts(200)
    feats, jac = enc.encode_with_jacobian(x)
    assert torch.allclose(feats, enc.encode(x), atol=1e-7)
    xr = x.clone().requires_grad_(True)
    out = enc.encode(xr)
    rows = [torch.autograd.grad(out[:, j].sum(), xr, retain_graph=True)[0] for j in range(out.shape[1])]
    auto = torch.stack(rows, -1)  # [P, 3, E]
    assert jac.shape == auto.shape
    assert torch.allclose(jac, auto, rtol=1e-5, atol=1e-4)
    outside = (x.abs() > 1).any(-1)
    assert outside.any() and (jac[outside].abs().amax(-1)[x[outside].abs() > 1] == 0).all()


def sdf(K=3, bound=1.0):
    enc = grid()
    torch.manual_seed(2)
    return SDFField(SDFFieldConfig(bound=bound), encoding=enc, num_materials=K)


def k_backward_grads(field, x):
    return eikonal_k_loop(field.distances, x)


@pytest.mark.parametrize("bound", [1.0, 1.3])
def test_forward_mode_k_gradients_equal_k_backward_passes_and_train_the_same(bound):
    field = sdf(bound=bound)
    x = pts(300, spread=1.5)
    d, f, g_fast = field.forward_with_gradients(x)
    plain = field.get_outputs(x)
    d_ref, f_ref = plain.distances, plain.features
    assert torch.equal(d, d_ref) and torch.equal(f, f_ref)
    g_ref = k_backward_grads(field, x)
    assert torch.allclose(g_fast, g_ref, rtol=1e-5, atol=1e-4)
    mask = (x.abs() <= bound).all(-1)
    params = list(field.parameters())
    grads = []
    for g in (g_fast, g_ref):
        loss = EikonalLoss.penalty(g, mask)
        grads.append(torch.autograd.grad(loss, params, retain_graph=True, allow_unused=True, materialize_grads=True))
    for a, b in zip(*grads):
        assert torch.allclose(a, b, rtol=1e-4, atol=1e-6)


def test_batched_autograd_equals_k_loop():
    field = sdf()
    x = pts(100, spread=0.9)
    loss = EikonalLossConfig(mode="autograd").setup()
    batched = loss.gradients(field.distances, x)
    looped = eikonal_k_loop(field.distances, x)
    assert torch.allclose(batched, looped, rtol=1e-5, atol=1e-5)


def test_masked_penalty_matches_boolean_indexing():
    g = torch.randn(50, 3, 3)
    mask = torch.rand(50) > 0.4
    norm = g[mask].norm(dim=-1)
    assert EikonalLoss.penalty(g, mask).item() == pytest.approx(((norm - 1) ** 2).mean().item(), rel=1e-6)
    assert EikonalLoss.penalty(g, torch.zeros(50, dtype=torch.bool)).item() == 0.0


def test_fd_eikonal_approximates_exact_on_the_models_own_sdf():
    field = sdf()  # finest level: 64 cells over [-1, 1]
    with torch.no_grad():  # a smoother field (|grad d| ~ 1, as training makes it), so the ReLUs rarely switch within +-h
        field.encoding.table.mul_(0.02)
    h = 1e-3
    # points well inside a cell on every level, so +-h stays on one trilinear piece
    x = pts(2000, spread=0.9, seed=5)
    res = torch.tensor(field.encoding.layout.resolutions, dtype=torch.float32)
    frac = (((x + 1) / 2)[:, None, :] * res[None, :, None]) % 1.0
    margin = h / 2 * res[None, :, None] * 2
    keep = ((frac > margin) & (frac < 1 - margin)).all(-1).all(-1)
    x = x[keep]
    assert len(x) > 20
    exact = field.forward_with_gradients(x)[2]
    fd = EikonalLossConfig(mode="finite-difference", fd_step=h).setup().gradients(field.distances, x)
    # the ReLU may switch between the probes at a few points: compare robustly
    err = (fd - exact).norm(dim=-1) / exact.norm(dim=-1).clamp_min(1e-3)
    assert err.median() < 1e-2
    assert EikonalLoss.penalty(fd).item() == pytest.approx(EikonalLoss.penalty(exact).item(), rel=0.05)


def model_pair(fraction=1.0, K=3):
    cfg = presets.resolve(dataclasses.replace(methods.k_neas.config, preset="tiny", num_materials=K))
    mc = dataclasses.replace(cfg.model, eikonal_fraction=fraction)
    torch.manual_seed(0)
    fast = mc.setup(scale=2.0)
    ref = make_reference(mc.setup(scale=2.0))
    ref.load_state_dict(fast.state_dict())
    with torch.no_grad():  # a non-trivial table (the default init is ~1e-4)
        fast.field.encoding.table.uniform_(-0.5, 0.5)
        ref.field.encoding.table.copy_(fast.field.encoding.table)
    assert fast.fused_eikonal and not ref.fused_eikonal
    return fast, ref


def batch(n=24, seed=0):
    g = torch.Generator().manual_seed(seed)
    origins = torch.randn(n, 3, generator=g)
    origins = 3.0 * origins / origins.norm(dim=-1, keepdim=True)
    directions = -origins / 3.0 + 0.2 * torch.randn(n, 3, generator=g)
    is_air = torch.zeros(n, dtype=torch.bool)
    is_air[-4:] = True
    return {"origins": origins, "directions": directions, "projections": torch.rand(n, generator=g) * is_air.logical_not(),
            "is_air": is_air, "near": 2.0, "far": 4.0}


@pytest.mark.parametrize("fraction", [1.0, 0.5])
def test_model_fast_and_reference_give_same_losses_and_gradients(fraction):
    fast, ref = model_pair(fraction)
    b = batch()
    out = {}
    for name, m in (("fast", fast), ("ref", ref)):
        g = torch.Generator().manual_seed(7)
        losses = m.loss_dict(b, 0.0, generator=g)
        m.zero_grad()
        losses["total"].backward()
        out[name] = ({k: v.item() for k, v in losses.items()}, {n: p.grad for n, p in m.named_parameters()})
    (lf, gf), (lr, gr) = out["fast"], out["ref"]
    assert set(lf) == {"intensity", "floater", "eikonal", "total"} and lf["eikonal"] > 0
    for k in lf:
        assert lf[k] == pytest.approx(lr[k], rel=1e-5, abs=1e-8), k
    for n in gf:
        a, r = gf[n], gr[n]
        if r is None:
            assert a is None or a.abs().max() == 0, n
            continue
        assert torch.allclose(a, r, rtol=1e-4, atol=1e-6 * max(1.0, r.abs().max().item())), n
