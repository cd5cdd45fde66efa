"""NAF baseline field (SPEC §2, §6): the same encoding, an MLP to one output, mu >= 0, no SDF.

Architecture (our choice; NAF itself uses a 4x32 MLP with a sigmoid output):
encoding -> Linear(F -> 64), ReLU, Linear(64 -> 64), ReLU, Linear(64 -> 1), then
``softplus`` (default; smooth, unbounded above) or ``relu`` / ``sigmoid``
(the latter caps mu at 1, like NAF on normalised volumes). Output in data units (1/m).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn
from torch.nn import functional as F

from ..errors import ConfigError
from .base import Field, FieldConfig, FieldOutputs, encode_points

_ACTIVATIONS = {"softplus": F.softplus, "relu": F.relu, "sigmoid": torch.sigmoid}


@dataclass
class NAFFieldConfig(FieldConfig):
    """Attributes: hidden_dim (64), num_hidden_layers (2), activation (softplus|relu|sigmoid), bound (1.0, model units)."""

    _target = "kneas_method.fields.naf_field:NAFField"
    hidden_dim: int = 64
    num_hidden_layers: int = 2
    activation: str = "softplus"


class NAFField(Field):
    """``get_outputs(points [P, 3] model units)`` gives ``mu [P]`` (>= 0, in units of ``CTModel.attenuation_unit``, 1 /m on
    NAF-normalised scans, which ``CTModel.query`` multiplies in); no surfaces."""

    def __init__(self, config: NAFFieldConfig, *, encoding: nn.Module, num_materials: int | None = None):
        super().__init__(config)
        if config.activation not in _ACTIVATIONS:
            raise ConfigError(f"NAF field activation {config.activation!r} is unknown; choose one of {sorted(_ACTIVATIONS)}")
        self.encoding = encoding
        sizes = [encoding.n_output_dims] + [config.hidden_dim] * config.num_hidden_layers + [1]
        layers: list[nn.Module] = []
        for i in range(len(sizes) - 1):
            layers.append(nn.Linear(sizes[i], sizes[i + 1]))
            if i < len(sizes) - 2:
                layers.append(nn.ReLU())
        self.mlp = nn.Sequential(*layers)
        self._act = _ACTIVATIONS[config.activation]

    def get_outputs(self, points: torch.Tensor, with_gradients: bool = False) -> FieldOutputs:
        return FieldOutputs(mu=self._act(self.mlp(encode_points(self.encoding, points, self.bound))[:, 0]))
