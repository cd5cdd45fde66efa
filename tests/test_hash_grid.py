"""Multi-resolution hash grid (SPEC §2): layout, hashing, interpolation, gradients, tcnn dispatch."""

import sys
import types

import pytest
import torch

from kneas_method.errors import ConfigError, KneasError
from kneas_method.fields import hash_grid as hg
from kneas_method.fields.hash_grid import HashGridConfig, HashGridEncoding, hash_grid_layout, spatial_hash

PRIMES = (1, 2654435761, 805459861)


def ref_hash(x: int, y: int, z: int, size: int) -> int:
    """Independent reference of the SPEC hash with Python ints (uint32 semantics)."""
    m = 0xFFFFFFFF
    return (((x * PRIMES[0]) & m) ^ ((y * PRIMES[1]) & m) ^ ((z * PRIMES[2]) & m)) % size


def vertices(R: int) -> torch.Tensor:
    """All (R+1)^3 integer vertices [(R+1)^3, 3], x fastest (dense storage order)."""
    r = torch.arange(R + 1)
    z, y, x = torch.meshgrid(r, r, r, indexing="ij")
    return torch.stack([x, y, z], -1).reshape(-1, 3)


def interior_points(n: int, resolutions, margin: float = 1e-3, seed: int = 0) -> torch.Tensor:
    """Random points in [-1, 1]^3 whose grid coordinates stay ``margin`` away from cell faces."""
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(20 * n, 3, generator=g, dtype=torch.float64) * 2 - 1
    p = (x + 1) / 2
    ok = torch.ones(len(x), dtype=torch.bool)
    for R in resolutions:
        frac = torch.frac(p * R)
        ok &= ((frac > margin) & (frac < 1 - margin)).all(-1)
    x = x[ok][:n]
    assert len(x) == n
    return x


# -- layout -----------------------------------------------------------------------------------

def test_paper_layout_counts_exact():
    enc = HashGridConfig().setup()
    assert isinstance(enc, HashGridEncoding)
    lay = enc.layout
    assert lay.resolutions == tuple(16 * 2**l for l in range(14))
    assert lay.sizes == (4920, 35944, 274632) + (524288,) * 11
    assert lay.hashed == (False,) * 3 + (True,) * 11
    assert lay.offsets[1] == 4920 and lay.offsets[3] == 4920 + 35944 + 274632
    assert lay.n_params == 12_165_328
    assert sum(p.numel() for p in enc.parameters()) == 12_165_328
    assert enc.table.shape == (6_082_664, 2)
    assert enc.n_output_dims == 28
    assert enc.level_table(3).shape == (524288, 2)
    # uniform +-1e-4 initialisation
    assert enc.table.abs().max() <= 1e-4 and enc.table.abs().max() > 5e-5


def test_invalid_settings_raise_one_line_config_errors():
    for kw in [dict(num_levels=0), dict(features_per_level=0), dict(log2_hashmap_size=40),
               dict(base_resolution=0), dict(per_level_scale=0.5), dict(implementation="cuda"),
               dict(init_scale=-1.0),
               dict(num_levels=2, log2_hashmap_size=30, base_resolution=2048)]:  # 2^31 table rows: past an int32 index
        with pytest.raises(ConfigError) as err:
            HashGridConfig(**kw).setup()
        assert "\n" not in str(err.value)
    enc = HashGridConfig(num_levels=2, log2_hashmap_size=8, base_resolution=2).setup()
    with pytest.raises(KneasError):
        enc(torch.zeros(4, 2))


def test_spatial_hash_matches_reference():
    g = torch.Generator().manual_seed(1)
    coords = torch.randint(0, 200_000, (200, 3), generator=g)
    got = spatial_hash(coords, 2**19)
    want = [ref_hash(*map(int, c), 2**19) for c in coords]
    assert got.tolist() == want
    assert spatial_hash(torch.tensor([1, 1, 1]), 2**19).item() == ref_hash(1, 1, 1, 2**19)


# -- interpolation ----------------------------------------------------------------------------

def test_linear_table_reproduced_exactly_dense_levels():
    """Features set to an affine function of vertex position -> output is that function at p."""
    cfg = HashGridConfig(num_levels=3, features_per_level=2, log2_hashmap_size=12, base_resolution=2,
                         implementation="torch")
    enc = cfg.setup().double()
    lay = enc.layout
    assert not any(lay.hashed)
    a = torch.tensor([[0.7, -1.3, 2.1], [-0.4, 0.9, 0.25]], dtype=torch.float64)  # [F, 3]
    b = torch.tensor([0.3, -0.2], dtype=torch.float64)
    with torch.no_grad():
        enc.table.zero_()
        for l, R in enumerate(lay.resolutions):
            v = vertices(R).double() / R  # p of each vertex, dense order
            enc.level_table(l)[: len(v)] = v @ a.T + b * (l + 1)
    x = torch.rand(500, 3, dtype=torch.float64) * 2 - 1
    x = torch.cat([x, torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0], [1.0, -1.0, 0.0]], dtype=torch.float64)])
    p = (x + 1) / 2
    out = enc(x).view(-1, 3, 2)
    for l in range(3):
        torch.testing.assert_close(out[:, l], p @ a.T + b * (l + 1), rtol=0, atol=1e-12)


def test_dense_and_hashed_paths_agree():
    """One level stored densely vs. the same level hashed, table holding the same vertex values.

    R = 6 (343 vertices) in a 2^19 table: the test first checks the hash is injective on
    these vertices, then writes every vertex's (random) value at its dense row in one
    encoding and at its hashed row in the other. Any disagreement in corner enumeration,
    strides or hashing between the two paths shows up as a different output.
    """
    cfg = HashGridConfig(num_levels=1, features_per_level=2, log2_hashmap_size=19, base_resolution=6,
                         implementation="torch")
    dense = HashGridEncoding(cfg).double()
    hashed = HashGridEncoding(cfg, force_hash=True).double()
    assert dense.layout.hashed == (False,) and hashed.layout.hashed == (True,)
    R, T = 6, 2**19
    v = vertices(R)
    h = [ref_hash(*map(int, c), T) for c in v]
    assert len(set(h)) == len(h)  # no collisions: the comparison is meaningful
    vals = torch.randn(len(v), 2, dtype=torch.float64)
    with torch.no_grad():
        dense.table.fill_(float("nan"))
        hashed.table.fill_(float("nan"))  # any wrong row read would give NaN
        dense_rows = v[:, 0] + v[:, 1] * (R + 1) + v[:, 2] * (R + 1) ** 2
        dense.table[dense_rows] = vals
        hashed.table[torch.tensor(h)] = vals
    x = torch.rand(2000, 3, dtype=torch.float64) * 2 - 1
    x[:3] = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0], [1.0, 0.0, -1.0]])
    yd, yh = dense(x), hashed(x)
    assert torch.isfinite(yd).all() and torch.isfinite(yh).all()
    assert torch.equal(yd, yh)
    # and at a vertex the output is exactly that vertex's value
    vert = torch.tensor([[2, 5, 1]])
    xv = vert.double() / R * 2 - 1
    row = int(vert[0, 0] + vert[0, 1] * 7 + vert[0, 2] * 49)
    torch.testing.assert_close(hashed(xv)[0], vals[row], rtol=0, atol=1e-12)


def test_corner_rows_match_the_reference_hash_at_a_fine_level():
    """A 4096-cell hashed level: vertex coordinates times the primes wrap int32 many times over,
    and every corner's row is still the reference (uint32) hash's."""
    cfg = HashGridConfig(num_levels=1, features_per_level=2, log2_hashmap_size=19, base_resolution=4096,
                         implementation="torch")
    enc = HashGridEncoding(cfg)
    assert enc.layout.hashed == (True,)
    x = torch.rand(200, 3) * 2 - 1
    x[0] = 1.0  # the last cell
    index, _ = enc.corners(x)
    cell = torch.minimum(torch.floor((x + 1.0) * 0.5 * 4096.0), torch.tensor(4095.0)).long()  # the cells, as corners() finds them
    for p in range(len(x)):
        for c in range(8):
            vert = cell[p] + torch.tensor([(c >> 2) & 1, (c >> 1) & 1, c & 1])
            assert int(index[p, 0, c]) == ref_hash(*map(int, vert), 2**19)


def test_each_level_reads_only_its_own_rows():
    """Level l's rows all hold the constant c_l -> output block l is c_l everywhere (offsets)."""
    enc = HashGridConfig(num_levels=4, log2_hashmap_size=8, base_resolution=2, implementation="torch").setup()
    assert enc.layout.hashed == (False, False, True, True)
    consts = torch.tensor([[1.0, -1.0], [2.0, -2.0], [3.0, -3.0], [4.0, -4.0]])
    with torch.no_grad():
        for l in range(4):
            enc.level_table(l)[:] = consts[l]
    y = enc(torch.rand(300, 3) * 2 - 1).view(300, 4, 2)
    torch.testing.assert_close(y, consts.expand(300, 4, 2), rtol=0, atol=1e-6)


def test_output_shape_dtype_and_clamping():
    enc = HashGridConfig().setup()
    x = torch.rand(64, 3) * 2 - 1
    y = enc(x)
    assert y.shape == (64, 28) and y.dtype == torch.float32
    assert enc(x.double()).dtype == torch.float32
    assert enc(torch.zeros(0, 3)).shape == (0, 28)
    torch.testing.assert_close(enc(x.view(4, 16, 3)), y.view(4, 16, 28), rtol=0, atol=0)
    outside = torch.tensor([[1.5, -3.0, 0.2], [-1.01, 2.0, -7.0]])
    inside = torch.tensor([[1.0, -1.0, 0.2], [-1.0, 1.0, -1.0]])
    torch.testing.assert_close(enc(outside), enc(inside), rtol=0, atol=0)


# -- gradients --------------------------------------------------------------------------------

def small_grid():
    # resolutions 2, 4, 8; table 64 -> level 0 dense (27 -> 32 entries), levels 1, 2 hashed
    cfg = HashGridConfig(num_levels=3, features_per_level=2, log2_hashmap_size=6, base_resolution=2,
                         implementation="torch", init_scale=1.0)
    enc = cfg.setup().double()
    assert enc.layout.hashed == (False, True, True)
    return enc


def test_gradcheck_table_and_positions():
    enc = small_grid()
    x = interior_points(12, enc.layout.resolutions).requires_grad_(True)
    table = enc.table.detach().clone().requires_grad_(True)
    fn = lambda t, xx: enc.encode(xx, t)  # noqa: E731
    assert torch.autograd.gradcheck(fn, (table, x), eps=1e-6, atol=1e-6)
    assert torch.autograd.gradgradcheck(fn, (table, x), eps=1e-6, atol=1e-5)


def test_second_order_gradient_reaches_table():
    enc = HashGridConfig(num_levels=4, log2_hashmap_size=10, base_resolution=4, implementation="torch",
                         init_scale=0.1).setup()
    x = (torch.rand(256, 3) * 2 - 1).requires_grad_(True)
    sdf = enc(x) @ torch.linspace(-1, 1, enc.n_output_dims)
    (g,) = torch.autograd.grad(sdf.sum(), x, create_graph=True)
    assert g.shape == (256, 3) and g.abs().sum() > 0
    eikonal = ((g.norm(dim=-1) - 1) ** 2).mean()
    eikonal.backward()
    assert enc.table.grad is not None and torch.isfinite(enc.table.grad).all()
    assert enc.table.grad.abs().sum() > 0
    assert x.grad is not None and x.grad.abs().sum() > 0


# -- implementation dispatch ------------------------------------------------------------------

def test_auto_on_cpu_gives_torch_module(monkeypatch):
    cfg = HashGridConfig(num_levels=2, log2_hashmap_size=8, base_resolution=2)
    assert cfg.implementation == "auto"
    assert type(cfg.setup()) is HashGridEncoding
    # even with tinycudann importable, no CUDA -> torch
    monkeypatch.setitem(sys.modules, "tinycudann", types.ModuleType("tinycudann"))
    assert type(cfg.setup()) is HashGridEncoding
    assert type(cfg.setup(device="cpu")) is HashGridEncoding


def test_tcnn_without_tinycudann_raises_install_hint(monkeypatch):
    monkeypatch.setitem(sys.modules, "tinycudann", None)  # import fails
    with pytest.raises(KneasError) as err:
        HashGridConfig(implementation="tcnn").setup()
    msg = str(err.value)
    assert "\n" not in msg and "tinycudann" in msg and "pip install" in msg


class _FakeEncoding(torch.nn.Module):
    """Stands in for tinycudann.Encoding: only ``params`` matters to the wrapper's checks."""

    n_params = 0

    def __init__(self, n_input_dims, encoding_config, seed=1337, dtype=None):
        super().__init__()
        self.params = torch.nn.Parameter(torch.zeros(type(self).n_params))


def _fake_tcnn(monkeypatch, n_params):
    mod = types.ModuleType("tinycudann")
    mod.Encoding = type("Encoding", (_FakeEncoding,), {"n_params": n_params})
    monkeypatch.setitem(sys.modules, "tinycudann", mod)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)


def test_tcnn_layout_mismatch_is_refused_and_auto_falls_back(monkeypatch):
    cfg = HashGridConfig(num_levels=3, log2_hashmap_size=8, base_resolution=2)
    n = hash_grid_layout(cfg).n_params
    _fake_tcnn(monkeypatch, n - 10)
    with pytest.raises(ConfigError) as err:
        HashGridConfig(num_levels=3, log2_hashmap_size=8, base_resolution=2, implementation="tcnn").setup()
    assert str(n) in str(err.value) and str(n - 10) in str(err.value) and "\n" not in str(err.value)
    with pytest.warns(UserWarning, match="tiny-cuda-nn"):
        enc = cfg.setup()
    assert type(enc) is HashGridEncoding


def test_tcnn_converter_round_trip(monkeypatch):
    cfg = HashGridConfig(num_levels=3, log2_hashmap_size=8, base_resolution=2, implementation="tcnn")
    _fake_tcnn(monkeypatch, hash_grid_layout(cfg).n_params)
    t = cfg.setup()
    assert isinstance(t, hg.TcnnHashGridEncoding) and t.n_output_dims == 6
    src = HashGridConfig(num_levels=3, log2_hashmap_size=8, base_resolution=2, implementation="torch",
                         init_scale=1.0).setup()
    hg.copy_torch_to_tcnn(src, t)
    # tcnn order: level-major, entry, feature == torch table flattened row-major
    assert torch.equal(t.encoding.params.detach(), src.table.detach().reshape(-1))
    back = HashGridConfig(num_levels=3, log2_hashmap_size=8, base_resolution=2, implementation="torch").setup()
    hg.copy_tcnn_to_torch(t, back)
    assert torch.equal(back.table, src.table)
    other = HashGridConfig(num_levels=2, log2_hashmap_size=8, base_resolution=2, implementation="torch").setup()
    with pytest.raises(ConfigError):
        hg.copy_torch_to_tcnn(other, t)
