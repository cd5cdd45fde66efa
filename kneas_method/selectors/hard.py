"""Hard selector (NeAS-2M, K = 2 only).

``mu = mu_bar_2 · Omega(d_2)`` where ``d_2 < 0`` (inside the inner surface),
else ``mu_bar_1 · Omega(d_1)``. Weights are ``(Omega(d_1)·[d_2 >= 0], Omega(d_2)·[d_2 < 0])``:
differentiable in ``d`` and ``s`` except across the switch ``d_2 = 0``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..errors import ConfigError
from .base import Selector, SelectorConfig


@dataclass
class HardSelectorConfig(SelectorConfig):
    _target = "kneas_method.selectors.hard:HardSelector"


class HardSelector(Selector):
    def __init__(self, config: HardSelectorConfig, *, num_materials: int):
        if num_materials != 2:
            raise ConfigError(
                f"the hard selector (NeAS-2M) works only with K = 2 materials, got K = {num_materials}; "
                "use --num-materials 2 or the soft selector (model.selector 'soft') for other K"
            )
        super().__init__(config, num_materials=num_materials)

    def weights(self, occupancies, distances):
        inner = (distances[..., 1] < 0).to(occupancies.dtype)
        return torch.stack([occupancies[..., 0] * (1.0 - inner), occupancies[..., 1] * inner], dim=-1)
