"""NeRF-style frequency (positional) encoding.

``x [P, D]`` -> ``[x, sin(2^0 pi x), cos(2^0 pi x), ..., sin(2^(F-1) pi x), cos(2^(F-1) pi x)]``,
each block ``D`` wide, frequency-major (the NeRF ordering). ``n_output_dims = D*include_input + 2*D*F``;
for 3-D points and the default F = 6: 3 + 36 = 39. Inputs are used as given (model units,
normally in ``[-1, 1]``); no clamping.
"""

from __future__ import annotations

import dataclasses
import math
from typing import ClassVar

import torch
from torch import nn

from ..config import InstantiateConfig
from ..errors import ConfigError, KneasError


@dataclasses.dataclass
class FrequencyEncodingConfig(InstantiateConfig):
    """Sin/cos encoding at angular frequencies ``2^k * pi``, ``k = 0 .. num_frequencies-1``.

    Attributes:
        num_frequencies: F, number of octaves.
        include_input: prepend the raw input.
        in_dims: D, input width (3 for points).
    """

    _target: ClassVar = "kneas_method.fields.frequency:FrequencyEncoding"

    num_frequencies: int = 6
    include_input: bool = True
    in_dims: int = 3

    @property
    def n_output_dims(self) -> int:
        return self.in_dims * (int(self.include_input) + 2 * self.num_frequencies)

    def validate(self) -> None:
        if self.num_frequencies < 0:
            raise ConfigError(f"frequency encoding num_frequencies must be >= 0, got {self.num_frequencies}")
        if self.in_dims < 1:
            raise ConfigError(f"frequency encoding in_dims must be >= 1, got {self.in_dims}")
        if self.n_output_dims == 0:
            raise ConfigError("frequency encoding with num_frequencies=0 and include_input=false outputs nothing; "
                              "set num_frequencies >= 1 or include_input=true")


class FrequencyEncoding(nn.Module):
    """Frequency encoding module; call ``x [P, D] -> [P, n_output_dims]`` (dtype of ``x``)."""

    def __init__(self, config: FrequencyEncodingConfig):
        super().__init__()
        config.validate()
        self.config = config
        self.in_dims = config.in_dims
        self.include_input = config.include_input
        self.n_output_dims = config.n_output_dims
        freqs = math.pi * 2.0 ** torch.arange(config.num_frequencies, dtype=torch.float64)
        self.register_buffer("freqs", freqs, persistent=False)  # [F] angular frequencies (float64; cast per call)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``x [P, D]`` -> ``[P, D*include_input + 2*D*F]``."""
        if x.dim() != 2 or x.shape[-1] != self.in_dims:
            raise KneasError(f"frequency encoding expects input of shape [P, {self.in_dims}], got {tuple(x.shape)}")
        parts = [x] if self.include_input else []
        if self.freqs.numel():
            ang = x[:, None, :] * self.freqs.to(x.dtype)[None, :, None]  # [P, F, D]
            parts.append(torch.stack([torch.sin(ang), torch.cos(ang)], 2).reshape(x.shape[0], -1))  # [P, F*2*D]
        return torch.cat(parts, -1)
