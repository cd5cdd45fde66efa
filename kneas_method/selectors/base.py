"""Selector protocol: combine K materials into one attenuation per point.

``selector(distances [P, K], mu_bar [P, K], boundary) -> (mu [P], weights [P, K])``
where ``distances`` are signed distances (model units, negative inside),
``mu_bar`` raw per-material attenuations (data units, materials ordered by
ascending attenuation), ``boundary`` the surface boundary function
``Omega(d) -> occupancy`` (``fields.sdf_field.SurfaceBoundary``), ``mu = Σ_k
weights_k · mu_bar_k`` (data units) and ``weights`` the per-material memberships.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from ..config import InstantiateConfig


@dataclass
class SelectorConfig(InstantiateConfig):
    """Base selector config; ``setup(num_materials=K)`` builds the selector."""


class Selector(nn.Module):
    def __init__(self, config: SelectorConfig, *, num_materials: int):
        super().__init__()
        self.config = config
        self.num_materials = int(num_materials)

    def weights(self, occupancies: torch.Tensor, distances: torch.Tensor) -> torch.Tensor:
        """Per-material weights [P, K] from occupancies ``Omega(d)`` [P, K] and distances [P, K]."""
        raise NotImplementedError

    def forward(self, distances: torch.Tensor, mu_bar: torch.Tensor, boundary: nn.Module) -> tuple[torch.Tensor, torch.Tensor]:
        w = self.weights(boundary(distances), distances)
        return (w * mu_bar).sum(-1), w
