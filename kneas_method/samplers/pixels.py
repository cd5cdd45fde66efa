"""Per-projection object / air pixel sampler (SPEC §3).

For each training view the sampler precomputes the flat indices of its object
pixels (``p > air_threshold``) and air pixels (``p <= air_threshold``). With the
default threshold 0 and noise-free data this is SPEC §1's ``p > 0`` / ``p == 0``;
for noisy data the datamanager passes a threshold above the noise in air
(:func:`kneas_method.datamanagers.ct.noise_air_threshold`). A draw for one view takes up to
``num_object`` object pixels and up to ``num_air`` air pixels, each without
replacement (a view with fewer pixels than asked gives all it has).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..config import InstantiateConfig


@dataclass
class ObjectAirPixelSamplerConfig(InstantiateConfig):
    """Attributes: num_object (512), num_air (128) pixels per draw."""

    _target = "kneas_method.samplers.pixels:ObjectAirPixelSampler"
    num_object: int = 512
    num_air: int = 128


class ObjectAirPixelSampler:
    """``sample(view, generator) -> (object_pixels [M, 2], air_pixels [A, 2])`` as ``(j, i)`` = (row, column), int64, CPU.

    Args:
        projections: [N, nV, nU] line integrals (numpy or tensor) of the training views.
        air_threshold: line integrals at or below it are air, above it object (default 0).
    """

    def __init__(self, config: ObjectAirPixelSamplerConfig, *, projections, air_threshold: float = 0.0):
        self.config = config
        self.air_threshold = float(air_threshold)
        p = torch.as_tensor(np.asarray(projections))
        self.n_u = int(p.shape[-1])
        flat = p.reshape(p.shape[0], -1)
        self.object_index = [torch.nonzero(row > self.air_threshold, as_tuple=False)[:, 0] for row in flat]
        self.air_index = [torch.nonzero(row <= self.air_threshold, as_tuple=False)[:, 0] for row in flat]

    def _draw(self, index: torch.Tensor, n: int, generator: torch.Generator) -> torch.Tensor:
        if n <= 0 or len(index) == 0:
            chosen = index[:0]
        elif n >= len(index):
            chosen = index[torch.randperm(len(index), generator=generator)]
        else:
            chosen = index[torch.randperm(len(index), generator=generator)[:n]]
        return torch.stack([chosen // self.n_u, chosen % self.n_u], dim=-1)

    def sample(self, view: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        obj = self._draw(self.object_index[view], self.config.num_object, generator)
        air = self._draw(self.air_index[view], self.config.num_air, generator)
        return obj, air
