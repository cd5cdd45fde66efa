"""One entry for every classical reconstruction: ``reconstruct(algorithm, scene, options)``."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

from ..errors import ConfigError
from .options import ALGORITHMS, ReconstructionOptions

# Iterations when ReconstructionOptions.iterations is None (SART 5: RTK's usual setting and the
# reference; CGLS 30 as RTK's usual, see benchmarks/classical.py).
DEFAULT_ITERATIONS = {"sart": 5, "os-sart": 10, "cgls": 30, "asd-pocs": 10}
DEFAULT_RELAXATION = {"sart": 0.5, "os-sart": 1.0, "asd-pocs": 1.0}
DEFAULT_SUBSETS = 10  # OS-SART


@dataclass
class Reconstruction:
    """A classical volume: ``volume [nx, ny, nz]`` float32 (data units, 1/m), the wall time and
    what was run (``settings``, JSON-able)."""

    volume: np.ndarray
    seconds: float
    settings: dict


def _given(value, default):
    """``value``, or ``default`` where it is None (0 is a value the algorithm refuses, not "the default")."""
    return default if value is None else value


def algorithm_settings(algorithm: str, options: ReconstructionOptions, n_views: int) -> dict:
    """The settings ``algorithm`` runs with (``options`` with the defaults filled), JSON-able."""
    o = options
    if algorithm == "fdk":
        return {"filter": o.filter}
    settings = {"iterations": _given(o.iterations, DEFAULT_ITERATIONS[algorithm]), "backprojector": o.backprojector}
    if algorithm == "cgls":
        return settings
    settings["relaxation"] = _given(o.relaxation, DEFAULT_RELAXATION[algorithm])
    if algorithm in ("sart", "os-sart"):
        settings["positivity"] = o.positivity
    if algorithm == "os-sart":
        settings["subsets"] = _given(o.subsets, min(DEFAULT_SUBSETS, n_views))
    if algorithm == "asd-pocs":
        settings.update(subsets=o.subsets, tv_steps=o.tv_steps, tv_alpha=o.tv_alpha)
    return settings


def reconstruct(algorithm: str, scene, options: Optional[ReconstructionOptions] = None, *, device="cpu",
                progress: Optional[Callable[[int, int, float], None]] = None,
                iterates: Optional[Callable[[int, "torch.Tensor"], None]] = None, init=None) -> Reconstruction:
    """Reconstruct ``scene``'s training views with ``algorithm`` (one of :data:`ALGORITHMS`).

    ``progress(iteration, total, residual)`` is called by the iterative methods after each iteration
    (``residual``: relative data residual ‖Ax − b‖ / ‖b‖), and ``iterates(iteration, x)`` with the
    current volume tensor (read-only; FDK has no iterations and calls neither). ``init``: the iterative
    methods' start volume [nx, ny, nz] (data units; None: zeros); FDK takes none."""
    options = options or ReconstructionOptions()
    if algorithm not in ALGORITHMS:
        raise ConfigError(f"classical algorithm {algorithm!r} is not known; use one of {', '.join(ALGORITHMS)}")
    if algorithm == "fdk" and init is not None:
        raise ConfigError("FDK is not iterative, so it takes no start volume; leave init out for fdk")
    settings = algorithm_settings(algorithm, options, len(scene.train))
    if "backprojector" in settings:  # record the one "auto" picks for this geometry
        from .iterative import choose_backprojector

        settings["backprojector"] = choose_backprojector(settings["backprojector"], scene.geometry)
    t0 = time.perf_counter()
    if algorithm == "fdk":
        from .fdk import fdk_reconstruct

        volume = fdk_reconstruct(scene, filter=options.filter, device=device)
    else:
        from . import iterative

        s = dict(settings)
        if algorithm == "asd-pocs":
            s.update(n_tv=s.pop("tv_steps"), alpha=s.pop("tv_alpha"))
        function = iterative.ALGORITHMS[algorithm]
        volume = function(scene.train.projections, scene.geometry, scene.train.angles, device=device, progress=progress,
                          iterates=iterates, init=init, **s)
    started = {} if init is None else {"init": "a given volume"}
    return Reconstruction(np.asarray(volume, dtype=np.float32), time.perf_counter() - t0,
                          {"algorithm": algorithm, **settings, "views": len(scene.train), **started})
