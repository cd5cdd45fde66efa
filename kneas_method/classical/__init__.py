"""Classical CT reconstruction (SPEC §7): plain functions of (projections, geometry, angles).

* :mod:`.projector`: the matched Joseph pair ``forward`` (A) / ``back`` (Aᵀ, its exact
  adjoint), the reusable :class:`Projector`, and the voxel-driven
  :class:`VoxelBackprojector` (unmatched; what ``backprojector="auto"`` picks when detector pixels
  at the isocentre are at least a voxel wide).
  The data simulator and the evaluation of volumes project with it too.
* :mod:`.fdk`: Feldkamp-Davis-Kress filtered back-projection.
* :mod:`.iterative`: ``sart``, ``os_sart``, ``cgls``, ``asd_pocs`` (TIGRE-style functions
  returning ``[nx, ny, nz]`` float32 data units).
* :mod:`.options` / :mod:`.reconstruct`: :class:`ReconstructionOptions` and
  :func:`reconstruct`, the one entry the pipelines use (``kneas-train fdk|sart|...`` and the
  neural methods' bounds volume / warm start).
"""

from .iterative import (
    ALGORITHMS,
    asd_pocs,
    cgls,
    choose_backprojector,
    interleaved_subsets,
    os_sart,
    pixels_per_voxel,
    sart,
    spread_order,
    total_variation,
    tv_gradient,
    view_order,
)
from .projector import Projector, VoxelBackprojector, back, forward

__all__ = [
    "Projector",
    "VoxelBackprojector",
    "forward",
    "back",
    "sart",
    "os_sart",
    "cgls",
    "asd_pocs",
    "choose_backprojector",
    "pixels_per_voxel",
    "spread_order",
    "view_order",
    "interleaved_subsets",
    "total_variation",
    "tv_gradient",
    "ALGORITHMS",
]
