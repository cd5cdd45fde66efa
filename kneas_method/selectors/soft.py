"""Soft sequential selector (K-NeAS, any K >= 1).

With materials ordered by ascending attenuation (index 0 = lowest),
``w_i = Omega(d_i) · Π_{j > i} (1 − Omega(d_j))`` and ``mu = Σ_i mu_bar_i · w_i``.
The weights are non-negative and sum to ``1 − Π_i (1 − Omega(d_i)) <= 1``
(the remainder is air). For K = 1 this is NeAS-1M's ``mu = mu_bar · Omega(d)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..errors import ConfigError
from .base import Selector, SelectorConfig


def sequential_weights(occupancies: torch.Tensor) -> torch.Tensor:
    """``w_i = o_i · Π_{j>i} (1 − o_j)`` for occupancies [..., K] -> [..., K]."""
    free = 1.0 - occupancies
    # suffix products Π_{j>i} free_j: reverse exclusive cumulative product
    rev = torch.flip(free, dims=[-1])
    excl = torch.cumprod(torch.cat([torch.ones_like(rev[..., :1]), rev[..., :-1]], dim=-1), dim=-1)
    return occupancies * torch.flip(excl, dims=[-1])


@dataclass
class SoftSelectorConfig(SelectorConfig):
    _target = "kneas_method.selectors.soft:SoftSelector"


class SoftSelector(Selector):
    """Differentiable sequential occupancy filter (paper Eq. 2-3)."""

    def __init__(self, config: SoftSelectorConfig, *, num_materials: int):
        if num_materials < 1:
            raise ConfigError(f"the soft selector needs K >= 1 materials, got {num_materials}")
        super().__init__(config, num_materials=num_materials)

    def weights(self, occupancies, distances):
        return sequential_weights(occupancies)
