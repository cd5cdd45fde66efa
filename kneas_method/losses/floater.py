"""Floater loss (paper §2.2.4, SPEC §3): MSE of air-ray intensity against 1.

Applied only while training progress (fraction of epochs done, in [0, 1]) is
below ``fraction`` (0.2: the first 20 % of epochs).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..config import InstantiateConfig


@dataclass
class FloaterLossConfig(InstantiateConfig):
    """Attributes: fraction of training (by epochs) during which the loss is on."""

    _target = "kneas_method.losses.floater:FloaterLoss"
    fraction: float = 0.2


class FloaterLoss:
    """``loss(intensity_air [A]) -> scalar``: ``mean((I − 1)^2)``; ``active(progress)`` gives the schedule."""

    def __init__(self, config: FloaterLossConfig):
        self.config = config

    def active(self, progress: float) -> bool:
        """True while ``progress`` (epochs done / total epochs, in [0, 1]) < fraction."""
        return float(progress) < self.config.fraction

    def __call__(self, intensity_air: torch.Tensor) -> torch.Tensor:
        if intensity_air.numel() == 0:
            return intensity_air.sum() * 0.0
        return torch.mean((intensity_air - 1.0) ** 2)
