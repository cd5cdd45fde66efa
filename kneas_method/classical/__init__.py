"""Classical CT reconstruction (SPEC §7).

* :mod:`.projector`: the matched Joseph pair ``forward`` (A) / ``back`` (Aᵀ, its exact
  adjoint), the reusable :class:`Projector`, and the voxel-driven
  :class:`VoxelBackprojector` (unmatched).
"""

from .projector import Projector, VoxelBackprojector, back, forward

__all__ = ["Projector", "VoxelBackprojector", "forward", "back"]
