"""The classical start: a classical reconstruction of a neural run's training views, which the
bounds, the warm start and the anchor then use (``--stages.classical-start.algorithm``).

Computed once per run and kept in the run folder as ``<algorithm>_volume.npy`` (data
units) with ``<algorithm>_volume.json`` (settings, seconds), so a resumed run reuses it.

Where the object is wider than the detector's field of view (``data.truncation.FittingBox.wider_than_view``)
the start is run further (:func:`start_options`): a neural run keeps the start's values where the
views say little (outside the field of view), and ASD-POCS run on spreads less into the air there.
On fewer views than 50 it is run further too, to the single-view updates its count makes on 50.

:func:`start_fit` says whether the start's projections already fit the training views to their noise
(a noisy scan), which the later stages' choices follow.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from ..atomic import atomic_write
from ..classical.options import Algorithm, ReconstructionOptions
from ..classical.reconstruct import Reconstruction, algorithm_settings, reconstruct
from ..console import say
from ..engine.progress import stage_progress
from ..engine.run_dir import read_json, write_json
from ..errors import KneasError
from .base import RunState, Stage, StageConfig


# Iterations of a neural run's classical start where the object is wider than the field of view and
# --reconstruction.iterations is not given: ASD-POCS spreads less into the air outside the field of
# view when run further; the other algorithms keep their defaults.
WIDE_START_ITERATIONS = {"asd-pocs": 40}
# A start given no count makes at least the single-view updates its default count makes on this many
# views (the benchmarks' 50): on 5 or 10 views the default count stops ASD-POCS far short of where it
# goes on to (built-in chest, 5 views: 25.48 dB after 10 iterations, 26.94 after 100), while each
# iteration costs a tenth of one on 50 views. On 50 views or more the default count is kept.
VIEW_UPDATE_VIEWS = 50
VIEW_UPDATE_ALGORITHMS = ("sart", "asd-pocs")  # one view per update; OS-SART's subsets and CGLS use many


def start_options(algorithm: str, options: ReconstructionOptions, wider_than_view: bool, n_views: int = VIEW_UPDATE_VIEWS
                  ) -> ReconstructionOptions:
    """The options a neural run's ``algorithm`` start runs with on ``n_views`` training views: ``options``
    where a count is given; else the most of the algorithm's default count, :data:`WIDE_START_ITERATIONS`
    where the object is wider than the field of view, and the count that makes the default's single-view
    updates on :data:`VIEW_UPDATE_VIEWS` views (``ceil(default x 50 / n_views)``)."""
    if options.iterations is not None or algorithm == "fdk":
        return options
    from ..classical.reconstruct import DEFAULT_ITERATIONS

    default = DEFAULT_ITERATIONS[algorithm]
    count = default
    if wider_than_view and algorithm in WIDE_START_ITERATIONS:
        count = max(count, WIDE_START_ITERATIONS[algorithm])
    if algorithm in VIEW_UPDATE_ALGORITHMS and options.subsets is None and n_views >= 1:
        count = max(count, math.ceil(default * VIEW_UPDATE_VIEWS / n_views))
    return options if count == default else dataclasses.replace(options, iterations=count)


def start_fit(state: RunState) -> Optional[dict]:
    """How the classical start's projections fit the training views: their residual's mean square, the
    noise variance the band-correction passes estimate, and whether the first is within the passes'
    ``noise_factor`` times the second (``band_correction.at_noise``, the test the passes stop at: a noisy
    scan). Computed once a run and kept in ``records["classical-start"]["fit"]``; None without a start."""
    if state.start is None:
        return None
    record = state.records.setdefault("classical-start", {})
    if "fit" not in record:
        from .band_correction import NOISE_FACTOR, volume_at_noise

        correction = state.config.stages.correction
        factor = NOISE_FACTOR if correction is None else float(correction.noise_factor)
        level, mean_square, sigma2 = volume_at_noise(state.start[0], state.views(), state.projector(), factor)
        record["fit"] = {"mean_square": float(mean_square), "noise_variance": float(sigma2), "at_noise": bool(level)}
        state.say(f"classical start: the {state.start[1].upper()} volume's residual {mean_square:.3g} (mean square) is "
                  + (f"at the data's noise ({sigma2:.3g}): the views hold nothing more it could fit" if level
                     else f"above the data's noise ({sigma2:.3g})"))
    return record["fit"]


def classical_volume(algorithm: str, options: ReconstructionOptions, scene, run_dir: Path, device) -> Reconstruction:
    """The run's ``algorithm`` reconstruction of its training views with ``options`` (cached in
    ``run_dir``; a cached one with another iteration count is computed again)."""
    from ..console import console

    path, info_path = Path(run_dir) / f"{algorithm}_volume.npy", Path(run_dir) / f"{algorithm}_volume.json"
    wanted = algorithm_settings(algorithm, options, len(scene.train)).get("iterations")
    if path.is_file() and info_path.is_file():
        try:
            volume = np.load(path, allow_pickle=False)
            info = read_json(info_path, f"{algorithm} volume info")
            if tuple(volume.shape) == tuple(scene.geometry.n_voxel) and dict(info.get("settings", {})).get("iterations") == wanted:
                return Reconstruction(volume, float(info.get("seconds", 0.0)), dict(info.get("settings", {})))
        except (OSError, ValueError, KneasError):
            pass
    count = f" ({wanted} iterations)" if wanted else ""
    say(f"{algorithm}: reconstructing {len(scene.train)} training views for the classical start{count}")
    with stage_progress(console, unit="iterations") as progress:
        task = progress.add_task(algorithm, total=None, info="")

        def report(i, total, residual):
            progress.update(task, completed=i, total=total, info=f"residual {residual:.3e}")

        rec = reconstruct(algorithm, scene, options, device=device, progress=report)
    volume = np.asarray(rec.volume, dtype=np.float32)
    atomic_write(path, lambda fh: np.save(fh, volume))
    write_json(info_path, {"seconds": rec.seconds, "settings": rec.settings})
    return rec


@dataclass
class ClassicalStartConfig(StageConfig):
    """The classical start (not in the paper): reconstruct the training views with ``algorithm``
    (settings: the run's ``--reconstruction.*``) before the bounds; the automatic bounds are then
    estimated on this volume instead of a trained NeAS-1M prior, and the warm start and the anchor
    use it.

    Attributes:
        algorithm: the classical method (ASD-POCS: the one made for few views).
    """

    _target = "kneas_method.stages.classical_start:ClassicalStart"
    name = "classical-start"
    phase = "start"
    algorithm: Algorithm = "asd-pocs"

    def describe(self) -> str:
        return f"classical start: an {self.algorithm.upper()} reconstruction of the training views (the bounds, the warm start and the anchor use it)"


class ClassicalStart(Stage):
    def run(self, state: RunState) -> None:
        algorithm = self.config.algorithm
        options = start_options(algorithm, state.config.reconstruction, state.fitting_wider_than_view, len(state.scene.train))
        rec = classical_volume(algorithm, options, state.scene, state.run_dir, state.device)
        state.start = (np.asarray(rec.volume), algorithm)
        state.classical_seconds += rec.seconds
        state.records[self.name] = {"algorithm": algorithm, "seconds": float(rec.seconds), "settings": rec.settings}
