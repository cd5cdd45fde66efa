"""One entry for every classical reconstruction: ``reconstruct(algorithm, scene, options)``."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

from ..errors import ConfigError
from .options import ALGORITHMS, ReconstructionOptions


@dataclass
class Reconstruction:
    """A classical volume: ``volume [nx, ny, nz]`` float32 (data units, 1/m), the wall time and
    what was run (``settings``, JSON-able)."""

    volume: np.ndarray
    seconds: float
    settings: dict


def reconstruct(algorithm: str, scene, options: Optional[ReconstructionOptions] = None, *, device="cpu",
                progress: Optional[Callable[[int, int, float], None]] = None) -> Reconstruction:
    """Reconstruct ``scene``'s training views with ``algorithm`` (one of :data:`ALGORITHMS`).

    ``progress(iteration, total, residual)`` is called by the iterative methods."""
    options = options or ReconstructionOptions()
    if algorithm not in ALGORITHMS:
        raise ConfigError(f"classical algorithm {algorithm!r} is not known; use one of {', '.join(ALGORITHMS)}")
    t0 = time.perf_counter()
    from .fdk import fdk_reconstruct

    volume = fdk_reconstruct(scene, filter=options.filter, device=device)
    settings = {"algorithm": "fdk", "filter": options.filter, "views": len(scene.train)}
    return Reconstruction(np.asarray(volume, dtype=np.float32), time.perf_counter() - t0, settings)
