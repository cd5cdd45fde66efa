"""The straightforward implementations, kept outside the package as test oracles and as the
speed benchmark's reference (the nerfacc way: the naive version lives beside the tests).

* :func:`hash_grid_loop`: the hash grid as a Python loop over levels (per level: the 8
  corner rows, one ``index_select``, the trilinear weights). Same values as
  ``HashGridEncoding.encode``; its backward zero-fills a table-sized gradient per level.
* :func:`eikonal_k_loop`: the K distance gradients as K separate double-backward passes.
* :func:`make_reference`: turns a built ``CTModel`` into the straightforward one (loop or
  vectorised grid without forward-mode Jacobian, K-loop eikonal), sharing its parameters.

Used by ``tests/test_speed_equivalence.py`` and ``benchmarks/step.py --reference``.
"""

from __future__ import annotations

import torch
from torch import nn

from kneas_method.fields.hash_grid import HashGridEncoding, spatial_hash
from kneas_method.losses.eikonal import EikonalLoss


def hash_grid_loop(enc: HashGridEncoding, x: torch.Tensor) -> torch.Tensor:
    """``x [P, 3]`` in ``[-1, 1]^3`` (clamped) -> ``[P, L*F]``, one level at a time."""
    lead = x.shape[:-1]
    x = x.reshape(-1, 3)
    p = ((x.to(enc.table.dtype) + 1.0) * 0.5).clamp(0.0, 1.0)
    bits = torch.tensor([[(c >> 2) & 1, (c >> 1) & 1, c & 1] for c in range(8)], dtype=torch.int64, device=x.device)  # [8, 3]
    outs = []
    for level in range(enc.n_levels):
        res = enc.layout.resolutions[level]
        pos = p * res
        cell = torch.clamp(torch.floor(pos.detach()), max=res - 1)
        frac = pos - cell  # [P, 3]
        vert = cell.to(torch.int64)[:, None, :] + bits  # [P, 8, 3]
        if enc.layout.hashed[level]:
            idx = spatial_hash(vert, enc.layout.sizes[level])
        else:
            r1 = res + 1
            idx = vert[..., 0] + vert[..., 1] * r1 + vert[..., 2] * r1 * r1  # [P, 8]
        w3 = torch.where(bits.bool(), frac[:, None, :], 1.0 - frac[:, None, :])  # [P, 8, 3]
        w = w3[..., 0] * w3[..., 1] * w3[..., 2]  # [P, 8] trilinear weights
        feats = enc.level_table(level).index_select(0, idx.reshape(-1)).view(-1, 8, enc.n_features)
        outs.append((w[..., None] * feats).sum(1))  # [P, F]
    return torch.cat(outs, -1).reshape(*lead, enc.n_output_dims)


class ReferenceHashGrid(nn.Module):
    """A torch hash grid seen without its forward-mode Jacobian; ``loop=True`` also encodes
    level by level (:func:`hash_grid_loop`). Holds the wrapped grid's ``table`` Parameter
    under the same name, so state dicts and parameter names are unchanged."""

    implementation = "torch"

    def __init__(self, enc: HashGridEncoding, loop: bool = True):
        super().__init__()
        self.table = enc.table
        self._grid = [enc]  # not a submodule: its table is already registered above
        self.loop = loop
        self.layout, self.n_levels, self.n_features, self.n_output_dims = enc.layout, enc.n_levels, enc.n_features, enc.n_output_dims

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        enc = self._grid[0]
        return hash_grid_loop(enc, x) if self.loop else enc.encode(x)


def eikonal_k_loop(distance_fn, points: torch.Tensor, distances: torch.Tensor | None = None) -> torch.Tensor:
    """Spatial gradients ``[P, K, 3]`` of the distances by K separate double-backward passes."""
    if distances is None or not points.requires_grad:
        points = points.detach().requires_grad_(True)
        with torch.enable_grad():
            distances = distance_fn(points)
    grads = [torch.autograd.grad(distances[:, k].sum(), points, create_graph=True, retain_graph=True)[0]
             for k in range(distances.shape[-1])]
    return torch.stack(grads, dim=1)


class ReferenceEikonalLoss(EikonalLoss):
    """The eikonal loss with :func:`eikonal_k_loop` for the exact gradients."""

    def gradients(self, distance_fn, points, distances=None):
        if self.config.mode != "autograd":
            return super().gradients(distance_fn, points, distances)
        return eikonal_k_loop(distance_fn, points, distances)


def make_reference(model, grid: str = "loop"):
    """Make a built ``CTModel`` (torch hash grid) compute the straightforward way, in place:
    ``grid="loop"`` (per-level loop) or ``"vectorised"`` (the vectorised grid, but no
    forward-mode Jacobian); the eikonal by K double backwards. Returns the model."""
    enc = model.field.encoding
    if not isinstance(enc, HashGridEncoding):
        raise TypeError(f"make_reference needs the torch hash grid, got {type(enc).__name__}")
    model.field.encoding = ReferenceHashGrid(enc, loop=(grid == "loop"))
    if model.eikonal is not None:
        model.eikonal = ReferenceEikonalLoss(model.eikonal.config, default_step=model.eikonal.step)
    assert not model.fused_eikonal
    return model
