"""The one contract every field follows (nerfstudio's ``Field.get_outputs``).

A field maps points ``[P, 3]`` (model units) to a :class:`FieldOutputs`. Two kinds
exist, told apart by what the outputs hold, never by a field's registered name:

* **surface fields** (``SDFField``, or a plugin's): ``distances [P, K]`` (signed,
  model units, negative inside material k) and ``features [P, F]``, from which the
  model's attenuation network and selector make ``mu``;
* **attenuation fields** (``NAFField``): ``mu [P]`` directly (data units, 1/m).

The config class says which kind it builds (``FieldConfig.has_surfaces``), so the
pipeline can decide "bounds, materials, meshes" before the model exists; the built
module says the same through ``Field.num_distances`` (0 = no surfaces).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Optional

import torch
from torch import nn

from ..config import InstantiateConfig
from ..errors import ConfigError


@dataclass
class FieldOutputs:
    """What a field gives at ``P`` points.

    Attributes:
        mu: ``[P]`` attenuation, data units (1/m); attenuation fields only.
        distances: ``[P, K]`` signed distances, model units; surface fields only.
        features: ``[P, F]`` features for the attenuation network; surface fields only.
        distance_gradients: ``[P, K, 3]`` d distances / d points, when asked for
            (``get_outputs(points, with_gradients=True)``).
    """

    mu: Optional[torch.Tensor] = None
    distances: Optional[torch.Tensor] = None
    features: Optional[torch.Tensor] = None
    distance_gradients: Optional[torch.Tensor] = None


@dataclass
class FieldConfig(InstantiateConfig):
    """Base of every field config (registered under ``kneas.fields``).

    Attributes:
        bound: points are divided by this before encoding (model units; the scene
            fits the unit sphere, so 1.0).
    """

    #: True when the field gives signed distances (surfaces, materials, bounds); False for ``mu`` directly.
    has_surfaces: ClassVar[bool] = False
    bound: float = 1.0


class Field(nn.Module):
    """Base of every field module: ``get_outputs(points [P, 3]) -> FieldOutputs``.

    Args (of subclasses): ``config``, ``encoding`` (an encoding module with
    ``n_output_dims``), ``num_materials`` (K; ignored by attenuation fields).
    """

    #: K signed distance fields (0: an attenuation field, no surfaces)
    num_distances: int = 0
    #: width of ``features`` (0 when the field gives ``mu``)
    feature_dim: int = 0

    def __init__(self, config: FieldConfig):
        super().__init__()
        self.config = config
        self.bound = float(config.bound)

    @property
    def has_surfaces(self) -> bool:
        return self.num_distances > 0

    @property
    def supports_gradients(self) -> bool:
        """True when ``get_outputs(points, with_gradients=True)`` gives exact distance
        gradients in the same pass (forward mode), so the eikonal needs no double backward."""
        return False

    def get_outputs(self, points: torch.Tensor, with_gradients: bool = False) -> FieldOutputs:
        """``points [P, 3]`` (model units) -> :class:`FieldOutputs`."""
        raise NotImplementedError

    def forward(self, points: torch.Tensor) -> FieldOutputs:
        return self.get_outputs(points)

    def distances(self, points: torch.Tensor) -> torch.Tensor:
        """Signed distances only: ``[P, 3] -> [P, K]`` (model units)."""
        out = self.get_outputs(points).distances
        if out is None:
            raise ConfigError(f"{type(self).__name__} gives no signed distances (it has no surfaces)")
        return out


def encode_points(encoding: nn.Module, points: torch.Tensor, bound: float) -> torch.Tensor:
    """Encode points [P, 3] (model units) -> [P, F].

    Points are divided by ``bound`` and clamped to ``[-1, 1]^3``, the encoding's
    domain; outside the box the encoding is constant (so ``d`` has zero spatial
    gradient there: the eikonal term skips such points, see ``losses.eikonal``).
    """
    x = (points / bound).clamp(-1.0, 1.0)
    return encoding(x).float()
