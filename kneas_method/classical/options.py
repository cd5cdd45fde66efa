"""Settings of a classical reconstruction (SPEC §7), shared by the classical methods
(``kneas-train fdk ...``) and by the neural methods that start from a classical volume
(``--bounds-volume``, ``--trainer.warm-start``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

Algorithm = Literal["fdk"]
ALGORITHMS: tuple[str, ...] = Algorithm.__args__
FdkFilter = Literal["ram-lak", "shepp-logan", "cosine", "hann"]


@dataclass
class ReconstructionOptions:
    """Attributes:
    filter: FDK ramp-filter window.
    """

    filter: FdkFilter = "ram-lak"
