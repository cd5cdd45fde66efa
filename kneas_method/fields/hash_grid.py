"""Multi-resolution hash grid encoding (SPEC §2): pure torch (default) and tiny-cuda-nn.

Layout (the paper's "hash" configuration, ``HashGridConfig()`` defaults)
-----------------------------------------------------------------------
Level ``l`` (0-based) has resolution ``R_l = ceil(base_resolution * per_level_scale**l)``
cells per axis, i.e. ``R_l + 1`` vertices per axis. Its dense grid needs
``(R_l + 1)**3`` entries, rounded up to a multiple of 8; if that fits in
``2**log2_hashmap_size`` entries the level is stored **densely** with that many
entries and vertex ``(x, y, z)`` lives at ``x + y*(R+1) + z*(R+1)**2``. Finer levels
are **hashed** into ``2**log2_hashmap_size`` entries::

    index = ((x*1) & M) ^ ((y*2654435761) & M) ^ ((z*805459861) & M)  (mod table size),
    M = 2**32 - 1  (uint32 semantics; products taken in int64)

For the paper config (14 levels, 2 features, 2^19, base 16, scale 2) the entry
counts are 4920, 35944, 274632, then 524288 x 11: 6,082,664 entries, 12,165,328
parameters. All levels share one parameter tensor ``table [n_entries, F]``; level
``l`` owns rows ``level_offsets[l] : level_offsets[l] + level_sizes[l]``.

Lookup: a point ``x`` in model units ``[-1, 1]^3`` maps to ``p = clamp((x + 1)/2, 0, 1)``;
on level ``l`` its grid coordinate is ``p * R_l`` and the output is the trilinear
interpolation of the 8 surrounding vertices' features. Output features are
level-major: ``out[:, l*F + f]`` (the same order tiny-cuda-nn uses).

The torch implementation is vectorised over levels (a handful of batched
tensor ops, one gather, three lerps; no Python loop over levels) and uses
only differentiable torch ops, so it is twice differentiable: the eikonal loss
can take ``grad(out, x, create_graph=True)`` and back-propagate through it to
both the table and ``x``. Measured on one CPU thread, 16,384 points, paper
config: forward ~0.1 s, forward+backward ~0.25 s, forward + ``grad(create_graph)``
+ backward ~0.3 s (a per-level Python loop: ~0.77 s / ~0.89 s, mostly from
zero-filling the 48 MB table gradient once per level).

:meth:`HashGridEncoding.encode_with_jacobian` returns the features and their exact spatial
Jacobian from the same gather (forward mode): the SDF field uses it to get all K distance
gradients for the eikonal term with a first-order backward only (no double backward).
The straightforward per-level loop is kept outside the package, as the test oracle and the
benchmark reference (``benchmarks/naive.py``; ``benchmarks/step.py --reference``).

tiny-cuda-nn
------------
``implementation="tcnn"`` wraps ``tinycudann.Encoding`` (imported only there).
It is accepted only if tiny-cuda-nn's parameter count equals the layout above;
note that current tiny-cuda-nn releases treat ``base_resolution`` as the number
of *vertices* (level resolution ``16 * 2**l`` vertices, coordinate
``p * (16 * 2**l - 1) + 0.5``), giving 12,132,352 parameters for the paper config,
so they are refused with a :class:`ConfigError` naming both counts.
``implementation="auto"`` uses tiny-cuda-nn only when it is installed, CUDA is
available (and the target device, if given, is CUDA) and its layout matches;
otherwise it uses the torch implementation.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from typing import ClassVar, Sequence

import torch
from torch import nn

from ..config import InstantiateConfig
from ..errors import ConfigError, KneasError

#: Spatial-hash primes per axis (instant-ngp / tiny-cuda-nn "CoherentPrime").
HASH_PRIMES: tuple[int, int, int] = (1, 2654435761, 805459861)
_UINT32_MASK = 0xFFFFFFFF
IMPLEMENTATIONS = ("auto", "torch", "tcnn")
TCNN_INSTALL_HINT = (
    "pip install ninja git+https://github.com/NVlabs/tiny-cuda-nn/#subdirectory=bindings/torch "
    "(needs a CUDA toolkit), or use implementation='torch'"
)


@dataclasses.dataclass
class HashGridConfig(InstantiateConfig):
    """Multi-resolution hash grid encoding; defaults are the paper's (SPEC §2).

    Attributes:
        num_levels: number of resolution levels L.
        features_per_level: features F stored per vertex and level.
        log2_hashmap_size: log2 of the maximum entries per level (table size T).
        base_resolution: cells per axis of level 0.
        per_level_scale: resolution growth factor between levels (>= 1).
        implementation: ``"auto"`` (tiny-cuda-nn when usable, else torch),
            ``"torch"`` or ``"tcnn"``.
        init_scale: table entries are initialised uniform in ``[-init_scale, init_scale]``.
    """

    _target: ClassVar = "kneas_method.fields.hash_grid:HashGridEncoding"

    num_levels: int = 14
    features_per_level: int = 2
    log2_hashmap_size: int = 19
    base_resolution: int = 16
    per_level_scale: float = 2.0
    implementation: str = "auto"
    init_scale: float = 1e-4

    @property
    def n_output_dims(self) -> int:
        return self.num_levels * self.features_per_level

    def validate(self) -> None:
        """Raise :class:`ConfigError` (one line) for an invalid setting."""
        checks = (
            (self.num_levels >= 1, f"hash grid num_levels must be >= 1, got {self.num_levels}"),
            (self.features_per_level >= 1, f"hash grid features_per_level must be >= 1, got {self.features_per_level}"),
            (1 <= self.log2_hashmap_size <= 30, f"hash grid log2_hashmap_size must be in 1..30, got {self.log2_hashmap_size}"),
            (self.base_resolution >= 1, f"hash grid base_resolution must be >= 1, got {self.base_resolution}"),
            (self.per_level_scale >= 1.0, f"hash grid per_level_scale must be >= 1.0, got {self.per_level_scale}"),
            (self.init_scale >= 0.0, f"hash grid init_scale must be >= 0, got {self.init_scale}"),
            (self.implementation in IMPLEMENTATIONS,
             f"hash grid implementation must be one of {list(IMPLEMENTATIONS)}, got {self.implementation!r}"),
        )
        for ok, message in checks:
            if not ok:
                raise ConfigError(message)
        finest = math.ceil(self.base_resolution * self.per_level_scale ** (self.num_levels - 1))
        if finest > 2**20:
            raise ConfigError(
                f"hash grid finest resolution {finest} exceeds 2^20 cells per axis; "
                "lower num_levels, base_resolution or per_level_scale"
            )

    def setup(self, device: torch.device | str | None = None, **kwargs) -> nn.Module:
        """Build the encoding module (see the module docstring for ``"auto"``).

        Args:
            device: where the module will run, if known; ``"auto"`` never picks
                tiny-cuda-nn for a non-CUDA device.
        """
        self.validate()
        impl = self.implementation
        if impl == "torch":
            return HashGridEncoding(self, **kwargs)
        if impl == "tcnn":
            return TcnnHashGridEncoding(self, **kwargs)
        # auto
        if not _tcnn_usable(device):
            return HashGridEncoding(self, **kwargs)
        try:
            return TcnnHashGridEncoding(self, **kwargs)
        except ConfigError as exc:
            warnings.warn(f"using the torch hash grid instead of tiny-cuda-nn: {exc}", stacklevel=2)
            return HashGridEncoding(self, **kwargs)


def _tcnn_usable(device: torch.device | str | None) -> bool:
    if device is not None and torch.device(device).type != "cuda":
        return False
    if not torch.cuda.is_available():
        return False
    try:
        import tinycudann  # noqa: F401
    except Exception:  # ImportError, or a broken CUDA build raising at import
        return False
    return True


@dataclasses.dataclass(frozen=True)
class HashGridLayout:
    """Per-level table layout of a hash grid (all lists have one entry per level).

    Attributes:
        resolutions: ``R_l``, cells per axis (``R_l + 1`` vertices).
        sizes: table entries of the level.
        offsets: first table row of the level.
        hashed: whether the level is hashed (else dense).
        features_per_level: F.
    """

    resolutions: tuple[int, ...]
    sizes: tuple[int, ...]
    offsets: tuple[int, ...]
    hashed: tuple[bool, ...]
    features_per_level: int

    @property
    def n_entries(self) -> int:
        return self.offsets[-1] + self.sizes[-1]

    @property
    def n_params(self) -> int:
        return self.n_entries * self.features_per_level

    @property
    def n_dense(self) -> int:
        """Number of dense levels (they are always the first levels)."""
        return sum(1 for h in self.hashed if not h)


def hash_grid_layout(config: HashGridConfig, force_hash: bool = False) -> HashGridLayout:
    """The SPEC §2 table layout for ``config``.

    Args:
        force_hash: hash every level into ``2**log2_hashmap_size`` entries, even
            levels whose dense grid would fit (a testing / comparison aid).
    """
    config.validate()
    table_size = 2**config.log2_hashmap_size
    resolutions, sizes, offsets, hashed = [], [], [], []
    offset = 0
    for level in range(config.num_levels):
        res = math.ceil(config.base_resolution * config.per_level_scale**level)
        dense = -(-((res + 1) ** 3) // 8) * 8  # (R+1)^3 rounded up to a multiple of 8
        is_hashed = force_hash or dense > table_size
        size = table_size if is_hashed else dense
        resolutions.append(res)
        sizes.append(size)
        offsets.append(offset)
        hashed.append(is_hashed)
        offset += size
    # Resolutions never decrease (per_level_scale >= 1), so dense levels are a prefix.
    n_dense = sum(1 for h in hashed if not h)
    assert all(not h for h in hashed[:n_dense]) and all(hashed[n_dense:])
    return HashGridLayout(tuple(resolutions), tuple(sizes), tuple(offsets), tuple(hashed), config.features_per_level)


def spatial_hash(coords: torch.Tensor, table_size: int | torch.Tensor) -> torch.Tensor:
    """Hash integer vertex coordinates ``coords [..., 3]`` (int64) -> table indices ``[...]``.

    ``((x*1) & M) ^ ((y*2654435761) & M) ^ ((z*805459861) & M) mod table_size``, M = 2^32 - 1.
    """
    primes = torch.tensor(HASH_PRIMES, dtype=torch.int64, device=coords.device)
    h = (coords.to(torch.int64) * primes) & _UINT32_MASK
    return (h[..., 0] ^ h[..., 1] ^ h[..., 2]) % table_size


class HashGridEncoding(nn.Module):
    """Pure-torch multi-resolution hash grid (SPEC §2), vectorised across levels.

    Attributes:
        table: ``nn.Parameter [n_entries, F]``, all levels' features.
        layout: :class:`HashGridLayout`.
        n_output_dims: ``L * F`` (28 for the paper config).
        implementation: ``"torch"``.

    Call: ``x [P, 3]`` in model units ``[-1, 1]^3`` (clamped) -> ``[P, L*F]`` in the
    table's dtype (float32 by default); ``[..., 3] -> [..., L*F]`` also works.
    """

    implementation = "torch"

    def __init__(self, config: HashGridConfig, force_hash: bool = False):
        super().__init__()
        self.config = config
        self.layout = hash_grid_layout(config, force_hash=force_hash)
        if self.layout.n_entries >= 2**31:  # before the table is allocated
            raise ConfigError(f"the hash grid's table would have {self.layout.n_entries:,} rows, more than an int32 index holds; "
                              "lower log2_hashmap_size or num_levels")
        self.n_levels = config.num_levels
        self.n_features = config.features_per_level
        self.n_output_dims = self.n_levels * self.n_features
        lay = self.layout
        self.table = nn.Parameter(torch.empty(lay.n_entries, self.n_features, dtype=torch.float32))
        with torch.no_grad():
            self.table.uniform_(-config.init_scale, config.init_scale)

        nd = lay.n_dense
        self._n_dense = nd
        res = torch.tensor(lay.resolutions, dtype=torch.int64)
        self.register_buffer("_resolutions", res, persistent=False)  # [L]
        # Indices are computed in int32 (half the memory traffic of int64; the table has < 2^31 rows).
        self.register_buffer("_offsets", torch.tensor(lay.offsets, dtype=torch.int32), persistent=False)  # [L]
        # Dense levels: per-axis strides (1, R+1, (R+1)^2) [nd, 3], and each of the 8 corners' row
        # offset from the cell's low corner [nd, 8] (corner c = 4*dx + 2*dy + dz)
        r1 = res[:nd] + 1
        strides = torch.stack([torch.ones_like(r1), r1, r1 * r1], -1)
        self.register_buffer("_dense_strides", strides.to(torch.int32), persistent=False)
        bits = torch.tensor([[(c >> 2) & 1, (c >> 1) & 1, c & 1] for c in range(8)], dtype=torch.int64)  # [8, 3]
        self.register_buffer("_dense_corners", (strides[:, None, :] * bits[None]).sum(-1).to(torch.int32), persistent=False)
        # Hashed levels: index masks T - 1 [nh] (T = 2**log2_hashmap_size, a power of two), and the
        # primes as int32: a product wraps modulo 2^32 in int32 as in uint32, so its low log2(T) bits,
        # all the mask keeps, are the reference hash's
        assert all(size & (size - 1) == 0 for size in lay.sizes[nd:])
        self.register_buffer("_hash_masks", torch.tensor(lay.sizes[nd:], dtype=torch.int32) - 1, persistent=False)
        primes = [p - 2**32 if p >= 2**31 else p for p in HASH_PRIMES]
        self.register_buffer("_primes", torch.tensor(primes, dtype=torch.int32), persistent=False)

    # -- layout helpers -------------------------------------------------------
    def level_table(self, level: int) -> torch.Tensor:
        """The rows of ``table`` owned by ``level``: a view ``[level_sizes[level], F]``."""
        o, s = self.layout.offsets[level], self.layout.sizes[level]
        return self.table[o : o + s]

    def extra_repr(self) -> str:
        lay = self.layout
        return (f"levels={self.n_levels}, features={self.n_features}, dense_levels={lay.n_dense}, "
                f"resolutions={lay.resolutions[0]}..{lay.resolutions[-1]}, params={lay.n_params}")

    # -- forward ----------------------------------------------------------------
    def corners(self, x: torch.Tensor, dtype: torch.dtype | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Table rows of the 8 cell corners and the position inside the cell, on every level.

        Args:
            x: ``[P, 3]`` points in model units (clamped to ``[-1, 1]^3``).
            dtype: float dtype of ``frac`` (default: the table's).

        Returns:
            ``index [P, L, 8]`` (int64 rows of ``table``; corner ``c = 4*dx + 2*dy + dz``) and
            ``frac [P, L, 3]`` in ``[0, 1]`` (differentiable w.r.t. ``x``).
        """
        _check_points(x)
        dtype = self.table.dtype if dtype is None else dtype
        p = ((x.to(dtype) + 1.0) * 0.5).clamp(0.0, 1.0)  # [P, 3]
        res = self._resolutions.to(dtype)  # [L]
        pos = p[:, None, :] * res[None, :, None]  # [P, L, 3] grid coordinates
        cell = torch.minimum(torch.floor(pos.detach()), (res - 1.0)[None, :, None])  # [P, L, 3]
        frac = pos - cell  # [P, L, 3]
        lo = cell.to(torch.int32)  # the cell's low corner

        parts = []
        nd = self._n_dense
        if nd > 0:
            row = (lo[:, :nd] * self._dense_strides).sum(-1, dtype=torch.int32) + self._offsets[:nd]  # [P, nd]
            parts.append(row[:, :, None] + self._dense_corners)  # [P, nd, 8]
        if nd < self.n_levels:
            # Hashed level sizes are powers of two dividing 2^32, so masking every axis term to
            # the low log2(T) bits equals the reference "& 0xFFFFFFFF, XOR, mod T" (and is cheaper);
            # the high corner's term is the low one's plus the prime, modulo T.
            mask = self._hash_masks[None, :, None]
            t0 = (lo[:, nd:] * self._primes) & mask  # [P, nh, 3]
            t = torch.stack([t0, (t0 + self._primes) & mask], -1)  # [P, nh, 3, 2]
            idx = t[:, :, 0, :, None, None] ^ t[:, :, 1, None, :, None] ^ t[:, :, 2, None, None, :]
            parts.append(idx.flatten(2) + self._offsets[nd:, None])  # [P, nh, 8]
        index = parts[0] if len(parts) == 1 else torch.cat(parts, 1)
        return index.long(), frac  # int64 for the gather: index_select's backward is 8x slower with int32 on a CPU

    def encode(self, x: torch.Tensor, table: torch.Tensor | None = None) -> torch.Tensor:
        """Encode ``x [P, 3]`` with ``table [n_entries, F]`` (default ``self.table``) -> ``[P, L*F]``.

        Trilinear interpolation as three successive lerps (x, then y, then z): mathematically
        the weighted sum of the 8 corners, but measurably cheaper to differentiate twice on CPU
        than forming the 8 weights.
        """
        table = self.table if table is None else table
        _check_points(x)
        lead = x.shape[:-1]
        x = x.reshape(-1, 3)
        index, frac = self.corners(x, table.dtype)
        P, L, F = x.shape[0], self.n_levels, self.n_features
        # unbind rather than slicing: its backward is one stack instead of a zero-fill per slice
        f0, f1 = table.index_select(0, index.reshape(-1)).view(P, L, 2, 4 * F).unbind(2)  # [P, L, (dy, dz, F)]
        fx, fy, fz = frac[..., None].unbind(2)  # [P, L, 1]
        a0, a1 = (f0 + fx * (f1 - f0)).view(P, L, 2, 2 * F).unbind(2)  # [P, L, (dz, F)]
        b0, b1 = (a0 + fy * (a1 - a0)).view(P, L, 2, F).unbind(2)  # [P, L, F]
        out = b0 + fz * (b1 - b0)  # [P, L, F]
        return out.reshape(*lead, L * F)

    def encode_with_jacobian(self, x: torch.Tensor, table: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Features and their exact spatial Jacobian from one gather (forward mode).

        Args:
            x: ``[P, 3]`` points in ``[-1, 1]^3`` (clamped).

        Returns:
            ``features [P, L*F]`` (equal to :meth:`encode`) and ``jacobian [P, 3, L*F]``,
            ``jacobian[p, i, j] = d features_j / d x_i`` (tangent-major, ready for a GEMM): the derivative of the three lerps with respect to the
            cell position times ``R_l / 2`` (zero on an axis where ``x`` lies outside
            ``[-1, 1]``, as autograd's clamp gives). Both are built from differentiable
            torch ops on the gathered corner features, so a loss on the Jacobian (the
            eikonal term) back-propagates to ``table`` with a *first-order* backward,
            the same values autograd's double backward gives.
        """
        table = self.table if table is None else table
        _check_points(x)
        P, L, F = x.shape[0], self.n_levels, self.n_features
        index, frac = self.corners(x, table.dtype)
        # unbind (not slicing) throughout: its backward is one stack, where each slice's
        # backward would zero-fill and copy a full-size gradient
        f0, f1 = table.index_select(0, index.reshape(-1)).view(P, L, 2, 4 * F).unbind(2)  # [P, L, (dy, dz, F)] at dx = 0, 1
        fx, fy, fz = frac[..., None].unbind(2)  # [P, L, 1] each
        dxa = f1 - f0  # d a / d fx
        a0, a1 = (f0 + fx * dxa).view(P, L, 2, 2 * F).unbind(2)  # [P, L, (dz, F)] at dy = 0, 1
        dxa0, dxa1 = dxa.view(P, L, 2, 2 * F).unbind(2)
        dyb = a1 - a0  # d b / d fy
        b0, b1 = (a0 + fy * dyb).view(P, L, 2, F).unbind(2)  # [P, L, F] at dz = 0, 1
        dxb0, dxb1 = (dxa0 + fy * (dxa1 - dxa0)).view(P, L, 2, F).unbind(2)
        dyb0, dyb1 = dyb.view(P, L, 2, F).unbind(2)
        dzo = b1 - b0
        out = b0 + fz * dzo
        dxo = dxb0 + fz * (dxb1 - dxb0)
        dyo = dyb0 + fz * (dyb1 - dyb0)
        # d frac / d x = R_l / 2 where -1 <= x <= 1 (clamp passes the gradient at its ends, like autograd)
        inside = ((x >= -1.0) & (x <= 1.0)).to(table.dtype)  # [P, 3]
        scale = self._resolutions.to(table.dtype)[None, :, None] * 0.5 * inside[:, None, :]  # [P, L, 3]
        scale = scale.transpose(1, 2)[:, :, :, None]  # [P, 3, L, 1]
        jac = torch.stack([dxo, dyo, dzo], 1) * scale  # [P, 3, L, F]
        return out.reshape(P, L * F), jac.reshape(P, 3, L * F)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``x [P, 3]`` in ``[-1, 1]^3`` (model units) -> features ``[P, L*F]``.

        Extra leading dimensions are allowed: ``[..., 3] -> [..., L*F]``.
        """
        return self.encode(x)


def _check_points(x: torch.Tensor) -> None:
    if x.dim() < 1 or x.shape[-1] != 3:
        raise KneasError(f"hash grid expects points of shape [P, 3], got {tuple(x.shape)}; pass 3-D points")


class TcnnHashGridEncoding(nn.Module):
    """The same encoding through ``tinycudann.Encoding`` (CUDA only).

    Attributes:
        encoding: the ``tinycudann.Encoding``; its ``params [n_params]`` hold the
            table in the torch layout's order (level-major, then entry, then feature).
        layout: :class:`HashGridLayout` (the torch layout it was checked against).
        n_output_dims: ``L * F``.
        implementation: ``"tcnn"``.

    Call: ``x [P, 3]`` (CUDA) in ``[-1, 1]^3`` -> ``[P, L*F]`` float32.

    Raises:
        KneasError: tiny-cuda-nn is not installed or CUDA is not available.
        ConfigError: tiny-cuda-nn's parameter count differs from the SPEC layout.
    """

    implementation = "tcnn"

    def __init__(self, config: HashGridConfig, dtype: torch.dtype | None = None, seed: int = 1337):
        super().__init__()
        try:
            import tinycudann as tcnn
        except ImportError:
            raise KneasError(
                f"hash grid implementation 'tcnn' needs the optional package 'tinycudann', which is not installed; "
                f"install it with: {TCNN_INSTALL_HINT}"
            ) from None
        if not torch.cuda.is_available():
            raise KneasError("hash grid implementation 'tcnn' needs a CUDA GPU and none is available; "
                             "use implementation='torch' or 'auto'")
        config.validate()
        self.config = config
        self.layout = hash_grid_layout(config)
        self.n_levels = config.num_levels
        self.n_features = config.features_per_level
        self.n_output_dims = self.n_levels * self.n_features
        encoding_config = tcnn_encoding_config(config)
        try:
            self.encoding = tcnn.Encoding(3, encoding_config, seed=seed, dtype=dtype)
        except TypeError:  # older bindings without ``dtype``
            self.encoding = tcnn.Encoding(3, encoding_config, seed=seed)
        got = self.encoding.params.numel()
        if got != self.layout.n_params:
            raise ConfigError(
                f"tiny-cuda-nn's hash grid has {got} parameters but the SPEC layout has {self.layout.n_params} "
                "(this tinycudann version sizes dense levels differently); use implementation='torch'"
            )
        with torch.no_grad():
            self.encoding.params.uniform_(-config.init_scale, config.init_scale)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``x [P, 3]`` in ``[-1, 1]^3`` (model units) -> ``[P, L*F]`` float32."""
        _check_points(x)
        lead = x.shape[:-1]
        p = ((x.reshape(-1, 3).float() + 1.0) * 0.5).clamp(0.0, 1.0).contiguous()
        return self.encoding(p).float().reshape(*lead, self.n_output_dims)

    def load_table(self, table: torch.Tensor) -> None:
        """Copy a torch-layout ``table [n_entries, F]`` into tiny-cuda-nn's params."""
        if tuple(table.shape) != (self.layout.n_entries, self.n_features):
            raise ConfigError(f"table of shape {tuple(table.shape)} does not fit this hash grid "
                              f"([{self.layout.n_entries}, {self.n_features}])")
        with torch.no_grad():
            self.encoding.params.copy_(table.detach().reshape(-1).to(self.encoding.params))

    def table(self) -> torch.Tensor:
        """tiny-cuda-nn's params as a torch-layout table ``[n_entries, F]`` (a detached copy)."""
        return self.encoding.params.detach().reshape(self.layout.n_entries, self.n_features).clone()


def tcnn_encoding_config(config: HashGridConfig) -> dict:
    """The ``tinycudann.Encoding`` config dict for ``config``."""
    return {
        "otype": "HashGrid",
        "n_levels": config.num_levels,
        "n_features_per_level": config.features_per_level,
        "log2_hashmap_size": config.log2_hashmap_size,
        "base_resolution": config.base_resolution,
        "per_level_scale": config.per_level_scale,
    }


def copy_torch_to_tcnn(src: HashGridEncoding, dst: TcnnHashGridEncoding) -> None:
    """Copy the torch encoding's table into the tiny-cuda-nn encoding (layouts must match)."""
    _check_same_layout(src, dst)
    dst.load_table(src.table)


def copy_tcnn_to_torch(src: TcnnHashGridEncoding, dst: HashGridEncoding) -> None:
    """Copy the tiny-cuda-nn encoding's params into the torch encoding's table."""
    _check_same_layout(src, dst)
    with torch.no_grad():
        dst.table.copy_(src.table().to(dst.table))


def _check_same_layout(a: nn.Module, b: nn.Module) -> None:
    if a.layout != b.layout:
        raise ConfigError(f"hash grid layouts differ ({a.layout.n_params} vs {b.layout.n_params} parameters); "
                          "build both from the same HashGridConfig")


__all__: Sequence[str] = (
    "HASH_PRIMES", "HashGridConfig", "HashGridLayout", "HashGridEncoding", "TcnnHashGridEncoding",
    "hash_grid_layout", "spatial_hash", "tcnn_encoding_config", "copy_torch_to_tcnn", "copy_tcnn_to_torch",
)
