"""Attenuation networks (SPEC §2): feature ``f`` [P, 8] -> raw attenuations ``mu_bar`` [P, K].

Every network ends in ``alpha_k * sigmoid(.) + beta_k`` per material ``k``, so
``mu_bar_k`` lies in ``(beta_k, beta_k + alpha_k)``. The bounds are buffers in
**data units** (1/m, what a NAF volume stores), saved in the ``state_dict`` and
set with :meth:`AttenuationNetwork.set_bounds` (e.g. from the GMM of SPEC §4).

- ``single`` (NeAS-1M, K = 1): Linear(8 -> 64), ReLU, Linear(64 -> 1).
- ``shared`` (K-NeAS): body Linear(8 -> 64), ReLU; per material a head
  Linear(64 -> 64), ReLU, Linear(64 -> 1).
- ``independent`` (NeAS-2M, ablations): per material Linear(8 -> 64), ReLU,
  Linear(64 -> 64), ReLU, Linear(64 -> 1).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import torch
from torch import nn

from ..config import InstantiateConfig
from ..errors import ConfigError

WIDE_ALPHA = 3.4  # NeAS defaults, data units (1/m)
WIDE_BETA = 0.1


def default_bounds(num_materials: int) -> tuple[list[float], list[float]]:
    """Placeholder bounds (data units): the NeAS wide bounds for K = 1; for K > 1
    the same range ``[0.1, 3.5]`` split into K equal, ascending intervals."""
    if num_materials == 1:
        return [WIDE_ALPHA], [WIDE_BETA]
    width = WIDE_ALPHA / num_materials
    return [width] * num_materials, [WIDE_BETA + k * width for k in range(num_materials)]


@dataclass
class AttenuationConfig(InstantiateConfig):
    """Common settings. ``hidden_dim``: layer width (paper: 64)."""

    hidden_dim: int = 64


class AttenuationNetwork(nn.Module):
    """Base: ``forward(features [P, F]) -> mu_bar [P, K]`` (data units), bounded."""

    def __init__(self, config: AttenuationConfig, *, feature_dim: int, num_materials: int):
        super().__init__()
        if num_materials < 1:
            raise ConfigError(f"num_materials is {num_materials}; the attenuation network needs K >= 1")
        self.config = config
        self.num_materials = int(num_materials)
        alphas, betas = default_bounds(self.num_materials)
        self.register_buffer("alphas", torch.tensor(alphas, dtype=torch.float32))
        self.register_buffer("betas", torch.tensor(betas, dtype=torch.float32))

    def set_bounds(self, alphas: Sequence[float], betas: Sequence[float]) -> None:
        """Set ``alpha_k, beta_k`` (data units, length K each, ``alpha_k > 0``)."""
        a = torch.as_tensor(alphas, dtype=torch.float32).reshape(-1)
        b = torch.as_tensor(betas, dtype=torch.float32).reshape(-1)
        if len(a) != self.num_materials or len(b) != self.num_materials:
            raise ConfigError(
                f"got {len(a)} alphas and {len(b)} betas for a {self.num_materials}-material model; give exactly {self.num_materials} of each"
            )
        if not bool(torch.all(a > 0)) or not bool(torch.all(torch.isfinite(a) & torch.isfinite(b))):
            raise ConfigError(f"attenuation bounds must be finite with alpha > 0, got alphas={a.tolist()} betas={b.tolist()}")
        self.alphas.copy_(a.to(self.alphas.device))
        self.betas.copy_(b.to(self.betas.device))

    def raw(self, features: torch.Tensor) -> torch.Tensor:
        """Unbounded logits [P, K]."""
        raise NotImplementedError

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        return self.alphas * torch.sigmoid(self.raw(features)) + self.betas


def _mlp(sizes: Sequence[int]) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i in range(len(sizes) - 1):
        layers.append(nn.Linear(sizes[i], sizes[i + 1]))
        if i < len(sizes) - 2:
            layers.append(nn.ReLU())
    return nn.Sequential(*layers)


@dataclass
class SingleAttenuationConfig(AttenuationConfig):
    _target = "kneas_method.fields.attenuation:SingleAttenuation"


class SingleAttenuation(AttenuationNetwork):
    """NeAS-1M: Linear(F -> 64), ReLU, Linear(64 -> 1). Only K = 1."""

    def __init__(self, config, *, feature_dim: int, num_materials: int):
        if num_materials != 1:
            raise ConfigError(
                f"the 'single' attenuation network has one material but K = {num_materials}; use attenuation 'shared' or 'independent' for K > 1"
            )
        super().__init__(config, feature_dim=feature_dim, num_materials=1)
        self.net = _mlp([feature_dim, config.hidden_dim, 1])

    def raw(self, features):
        return self.net(features)


@dataclass
class SharedAttenuationConfig(AttenuationConfig):
    _target = "kneas_method.fields.attenuation:SharedAttenuation"


class SharedAttenuation(AttenuationNetwork):
    """K-NeAS: shared body Linear(F -> 64), ReLU; K heads Linear(64 -> 64), ReLU, Linear(64 -> 1)."""

    def __init__(self, config, *, feature_dim: int, num_materials: int):
        super().__init__(config, feature_dim=feature_dim, num_materials=num_materials)
        h = config.hidden_dim
        self.body = nn.Sequential(nn.Linear(feature_dim, h), nn.ReLU())
        self.heads = nn.ModuleList(_mlp([h, h, 1]) for _ in range(self.num_materials))

    def raw(self, features):
        z = self.body(features)
        return torch.cat([head(z) for head in self.heads], dim=-1)


@dataclass
class IndependentAttenuationConfig(AttenuationConfig):
    _target = "kneas_method.fields.attenuation:IndependentAttenuation"


class IndependentAttenuation(AttenuationNetwork):
    """NeAS-2M / ablations: per material Linear(F -> 64), ReLU, Linear(64 -> 64), ReLU, Linear(64 -> 1)."""

    def __init__(self, config, *, feature_dim: int, num_materials: int):
        super().__init__(config, feature_dim=feature_dim, num_materials=num_materials)
        h = config.hidden_dim
        self.nets = nn.ModuleList(_mlp([feature_dim, h, h, 1]) for _ in range(self.num_materials))

    def raw(self, features):
        return torch.cat([net(features) for net in self.nets], dim=-1)
