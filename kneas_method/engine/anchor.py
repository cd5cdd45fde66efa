"""The warm-start volume kept as a prior during projection training (``Trainer.set_anchor``).

:class:`Anchor` holds what :meth:`Trainer.anchor_loss` draws from every step; :func:`label_interior`
says where that volume's labels can be trusted and :func:`edge_trust` how much each of its values is.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np
import torch
from scipy import ndimage

# labels are kept only this many voxels away from any other label (a 5^3 neighbourhood):
# measured on the ASD-POCS volumes of seven scenes against the truth, the labels there are
# wrong at 0 to 199 voxels in a million (at the edges themselves, blur: tens of thousands)
LABEL_MARGIN_VOXELS = 2


def label_interior(volume: np.ndarray, thresholds: Sequence[float], margin: int = LABEL_MARGIN_VOXELS) -> np.ndarray:
    """Voxels whose label is the label of every voxel within ``margin`` voxels (a cube).

    A voxel's label is how many of ``thresholds`` (ascending) its value exceeds. A
    reconstruction's labels are wrong mostly where its edges are blurred; away from any
    edge they agree with the truth's.

    Args:
        volume: ``[X, Y, Z]`` attenuation.
        thresholds: ``[K]`` ascending label thresholds, same units.
        margin: half the cube's side, voxels (0: every voxel).

    Returns:
        ``[X, Y, Z]`` bool.
    """
    labels = np.digitize(np.asarray(volume), np.asarray(thresholds, dtype=np.float64)).astype(np.int16)
    size = 2 * int(margin) + 1
    return ndimage.maximum_filter(labels, size=size, mode="nearest") == ndimage.minimum_filter(labels, size=size, mode="nearest")


def edge_trust(volume: np.ndarray, contrast: float) -> np.ndarray:
    """How much each voxel's value of a reconstruction is trusted: ``1 / (1 + (g / g0)^2)``.

    ``g`` is the voxel's central-difference gradient magnitude (``correction.gradient_magnitude``) and ``g0 = contrast x``
    the volume's 99.5th percentile, so the weight is 1 where the volume is flat and 1/2 where its
    values change by ``contrast`` of its range per voxel. A sparse-view reconstruction's error
    grows with its gradient (at the edges it blurs and shifts), and this weighs it as a Gaussian
    prior whose spread grows with that gradient; faint edges, where the projections say little,
    keep most of their weight.

    Args:
        volume: ``[X, Y, Z]`` attenuation (negative values count as 0).
        contrast: ``> 0``, a fraction of the volume's 99.5th percentile.

    Returns:
        ``[X, Y, Z]`` float32 in ``(0, 1]``.
    """
    v = np.clip(np.asarray(volume, dtype=np.float32), 0.0, None)
    g0 = float(contrast) * float(np.percentile(v, 99.5))
    if not g0 > 0:
        return np.ones(v.shape, dtype=np.float32)
    from ..correction import gradient_magnitude

    g = gradient_magnitude(torch.from_numpy(v)).numpy()
    return (1.0 / (1.0 + (g / g0) ** 2)).astype(np.float32)


@dataclass(frozen=True)
class Anchor:
    """A prior volume on the scene's voxel grid, as :meth:`Trainer.anchor_loss` uses it.

    Attributes:
        points: ``[V, 3]`` voxel centres, model units.
        targets: ``[V]`` the volume's values there, data units (negative values clipped to 0).
        weight: the prior's weight in the loss.
        points_per_step: voxel centres drawn each step.
        occupancy_weight: weight, inside the prior, of its labels (``CTModel.occupancy_loss``); 0 = none.
        label_mask: ``[V]`` bool, the voxels whose labels count (:func:`label_interior`);
            ``None`` when ``occupancy_weight`` is 0.
        value_weights: ``[V]`` each voxel's weight in the MSE (:func:`edge_trust`); ``None`` = 1 everywhere.
        outside: ``[V]`` bool, the voxels outside the model's occupancy grid, which the anchor
            leaves out of its field query (``anchor_outside`` ``skip``); ``None`` = query every draw.
    """

    points: torch.Tensor
    targets: torch.Tensor
    weight: float
    points_per_step: int
    occupancy_weight: float = 0.0
    label_mask: Optional[torch.Tensor] = None
    value_weights: Optional[torch.Tensor] = None
    outside: Optional[torch.Tensor] = None
