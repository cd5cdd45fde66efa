"""Settings of a classical reconstruction (SPEC §7), shared by the classical methods
(``kneas-train fdk|sart|os-sart|cgls|asd-pocs ...``) and by the neural methods that start
from a classical volume (the classical start, ``--stages.classical-start.algorithm``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, Optional

from ..config import at_least

Algorithm = Literal["fdk", "sart", "os-sart", "cgls", "asd-pocs"]
ALGORITHMS: tuple[str, ...] = Algorithm.__args__
FdkFilter = Literal["ram-lak", "shepp-logan", "cosine", "hann"]
Backprojector = Literal["auto", "voxel", "matched"]


@dataclass
class ReconstructionOptions:
    """Settings of the classical reconstructions.

    Attributes:
        filter: FDK ramp-filter window.
        iterations: iterations of the iterative methods (None: the algorithm's default:
            sart 5, os-sart 10, cgls 30, asd-pocs 10).
        relaxation: SART-family relaxation λ in (0, 2] (None: sart 0.5, os-sart / asd-pocs 1.0).
        subsets: OS-SART subsets (ASD-POCS: None = one view per update, as SART).
        positivity: clamp the volume at 0 after every SART-family update (ASD-POCS always does).
        backprojector: the iterative methods' back-projector: ``auto`` (from the geometry: voxel-driven
            when detector pixels at the isocentre are at least a voxel wide, else matched), ``voxel``
            (voxel-driven, as RTK's defaults) or ``matched`` (the projector's exact adjoint).
        tv_steps: ASD-POCS total-variation descent steps per iteration.
        tv_alpha: ASD-POCS first TV step as a fraction of the first data step (the TV weight).
    """

    filter: FdkFilter = "ram-lak"
    iterations: Optional[int] = field(default=None, metadata=at_least(1, whole=True))
    relaxation: Optional[float] = field(default=None, metadata=at_least(0, strict=True))
    subsets: Optional[int] = field(default=None, metadata=at_least(1, whole=True))
    positivity: bool = True
    backprojector: Backprojector = "auto"
    tv_steps: int = field(default=20, metadata=at_least(0, whole=True))
    tv_alpha: float = field(default=0.01, metadata=at_least(0))
