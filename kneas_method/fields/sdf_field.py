"""SDF field (SPEC §2): encoding -> Linear(F -> 64), ReLU, Linear(64 -> K + 8).

The network maps a point to ``K`` signed distances ``d_1..d_K`` (model units,
negative inside a material's surface) and a feature vector ``f`` (8-dim by
default) that the attenuation networks read. :class:`SurfaceBoundary` is the
surface boundary function ``Omega(d, s) = sigmoid(-s d)`` with one learnable
sharpness ``s`` (initialised at 20), shared by all materials.
"""

from __future__ import annotations

import math

from dataclasses import dataclass

import torch
from torch import nn

from ..errors import ConfigError

from .base import Field, FieldConfig, FieldOutputs, encode_points


@dataclass
class SDFFieldConfig(FieldConfig):
    """SDF network on top of an encoding.

    Attributes:
        hidden_dim: width of the single hidden layer (paper: 64).
        feature_dim: size of the feature vector ``f`` (paper: 8).
        bound: see :class:`~kneas_method.fields.base.FieldConfig`.
        distance_bias: initial bias of the distance outputs (model units). The
            default 0.1 starts every material "outside" (``Omega < 0.5``), i.e. an
            empty volume: most of a CT volume is air, and a field that starts
            half-full puts haze where no object ray constrains it.
    """

    _target = "kneas_method.fields.sdf_field:SDFField"
    has_surfaces = True
    hidden_dim: int = 64
    feature_dim: int = 8
    distance_bias: float = 0.1


class SDFField(Field):
    """Encoding + SDF MLP: ``get_outputs(points [P, 3])`` gives ``distances [P, K]`` and ``features [P, feature_dim]``."""

    def __init__(self, config: SDFFieldConfig, *, encoding: nn.Module, num_materials: int):
        super().__init__(config)
        if not isinstance(num_materials, int) or isinstance(num_materials, bool) or num_materials < 1:
            raise ConfigError(f"num_materials is {num_materials!r}; a surface field needs a whole number K >= 1 (--num-materials)")
        self.encoding = encoding
        self.num_materials = self.num_distances = int(num_materials)
        self.feature_dim = config.feature_dim
        self.mlp = nn.Sequential(
            nn.Linear(encoding.n_output_dims, config.hidden_dim),
            nn.ReLU(),
            nn.Linear(config.hidden_dim, self.num_materials + config.feature_dim),
        )
        if config.distance_bias:
            with torch.no_grad():
                self.mlp[-1].bias[: self.num_materials] += config.distance_bias

    def get_outputs(self, points: torch.Tensor, with_gradients: bool = False) -> FieldOutputs:
        if with_gradients:
            distances, features, grads = self.forward_with_gradients(points)
            return FieldOutputs(distances=distances, features=features, distance_gradients=grads)
        out = self.mlp(encode_points(self.encoding, points, self.bound))
        return FieldOutputs(distances=out[:, : self.num_materials], features=out[:, self.num_materials :])

    @property
    def supports_gradients(self) -> bool:
        """True when :meth:`forward_with_gradients` works: the encoding gives its
        Jacobian (the torch hash grid) and the MLP is Linear/ReLU only."""
        return (callable(getattr(self.encoding, "encode_with_jacobian", None))
                and all(isinstance(m, (nn.Linear, nn.ReLU)) for m in self.mlp))

    def forward_with_gradients(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Distances, features and the spatial gradients of all K distances in one pass.

        Forward-mode differentiation with 3 tangents carried alongside the values
        (the encoding's Jacobian from the same gather, then ``W·J`` and the ReLU mask
        per layer): ``grads`` equals ``torch.autograd.grad(distances[:, k].sum(), points,
        create_graph=True)`` for every k, and stays differentiable with respect to the
        parameters, so the eikonal term needs one first-order backward instead of K
        double backwards.

        Args:
            points: ``[P, 3]`` model units.

        Returns:
            ``distances [P, K]`` (model units), ``features [P, feature_dim]``,
            ``grads [P, K, 3]`` (d distance / d point, unit-free).
        """
        bound = self.bound
        x = points / bound
        inside = ((x >= -1.0) & (x <= 1.0)).to(points.dtype)  # clamp passes the gradient inside, ends included
        h, jac = self.encoding.encode_with_jacobian(x.clamp(-1.0, 1.0))  # [P, E], [P, 3, E]
        h = h.float()
        P = h.shape[0]
        t = jac.float().reshape(P * 3, -1)  # tangents [P*3, E]
        K = self.num_materials
        last = len(self.mlp) - 1
        for i, m in enumerate(self.mlp):
            if isinstance(m, nn.Linear):
                h = m(h)
                t = t @ (m.weight[:K] if i == last else m.weight).t()  # only the K distances need tangents
            else:  # ReLU
                mask = h > 0
                h = torch.relu(h)
                t = (t.view(P, 3, -1) * mask[:, None, :]).view(P * 3, -1)
        grads = t.view(P, 3, K).transpose(1, 2) * (inside / bound)[:, None, :]  # [P, K, 3]
        return h[:, :K], h[:, K:], grads


class SurfaceBoundary(nn.Module):
    """``Omega(d, s) = sigmoid(-s * d)``: occupancy in (0, 1) from a signed distance.

    One learnable scalar sets the sharpness ``s`` (1/model unit), initialised at
    ``s_init``. It is stored as ``log_s`` with ``s = exp(LOG_SCALE * log_s)`` (the
    NeuS parametrisation of its inverse standard deviation), so an optimiser step
    changes ``s`` by a relative amount: boundaries can sharpen from 20 to a few
    hundred within a short schedule instead of creeping by ``lr`` per step.
    """

    LOG_SCALE = 10.0

    def __init__(self, s_init: float = 20.0):
        super().__init__()
        if s_init <= 0:
            raise ConfigError(f"model.s_init must be a positive sharpness (1/model unit), got {s_init}")
        self.log_s = nn.Parameter(torch.tensor(math.log(float(s_init)) / self.LOG_SCALE))

    @property
    def s(self) -> torch.Tensor:
        """The sharpness ``s`` (a 0-d tensor, differentiable)."""
        return torch.exp(self.LOG_SCALE * self.log_s)

    def forward(self, distances: torch.Tensor) -> torch.Tensor:
        """distances [..., K] -> occupancies [..., K]."""
        return torch.sigmoid(-self.s * distances)
