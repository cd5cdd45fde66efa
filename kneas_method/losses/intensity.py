"""Intensity loss (SPEC §3): MSE between rendered and measured intensity on object rays."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..config import InstantiateConfig


@dataclass
class IntensityLossConfig(InstantiateConfig):
    _target = "kneas_method.losses.intensity:IntensityLoss"


class IntensityLoss:
    """``loss(intensity [R], projections [R]) -> scalar``: ``mean((I − exp(−p))^2)``;
    ``p`` is the measured line integral (unit-free), ``I`` the rendered intensity."""

    def __init__(self, config: IntensityLossConfig | None = None):
        self.config = config

    def __call__(self, intensity: torch.Tensor, projections: torch.Tensor) -> torch.Tensor:
        if intensity.numel() == 0:
            return intensity.sum() * 0.0
        return torch.mean((intensity - torch.exp(-projections)) ** 2)
