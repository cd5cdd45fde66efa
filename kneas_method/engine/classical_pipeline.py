"""The pipeline of a classical run (``kneas-train fdk ...``): reconstruct -> evaluate -> report.

The volume is reconstructed on the box the views are fitted on (``data.truncation.fitting_scene``)
and kept on the scene's box. Writes ``volume.npy`` (data units) to the run folder, and where the box
was made longer the whole reconstruction too (``volume_fitted_box.npy``, from which the held-out
views are projected); ``kneas-eval`` and ``kneas-export`` read them back.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

from ..atomic import atomic_write
from ..classical.reconstruct import reconstruct
from ..console import console, say
from ..data.truncation import FittingBox
from . import report
from .evaluate import evaluate_volume_stage
from .figures import run_figures
from .progress import stage_progress

# the volume on the longer box the views were fitted on (``data.truncation.FittingBox``), where there is one
FITTED_VOLUME = "volume_fitted_box.npy"


class ClassicalPipeline:
    """``ClassicalPipeline(config, scene=, run_dir=, device=).run() -> exit code``."""

    def __init__(self, config, *, scene, run_dir: Path, device, started: float = 0.0, fitting: Optional[FittingBox] = None):
        self.config, self.scene, self.run_dir, self.device = config, scene, Path(run_dir), device
        self.fitting = fitting or FittingBox(scene)

    def run(self) -> int:
        config, scene = self.config, self.scene
        say(f"{config.algorithm}: reconstructing from {len(scene.train)} views")
        with stage_progress(console, unit="iterations") as progress:
            task = progress.add_task(config.algorithm, total=None, info="")
            rec = reconstruct(config.algorithm, self.fitting.scene, config.reconstruction, device=self.device,
                              progress=lambda i, n, r: progress.update(task, completed=i, total=n, info=f"residual {r:.3e}"))
        fitted = np.asarray(rec.volume, dtype=np.float32)
        volume = np.ascontiguousarray(self.fitting.crop(fitted))
        atomic_write(self.run_dir / "volume.npy", lambda fh: np.save(fh, volume))
        if self.fitting.slices:  # the held-out views see the longer box: kneas-eval projects it again
            atomic_write(self.run_dir / FITTED_VOLUME, lambda fh: np.save(fh, fitted))
        evaluation = evaluate_volume_stage(volume, scene, console,
                                           fitted=(self.fitting.scene.geometry, fitted) if self.fitting.slices else None)
        run_figures(self.run_dir, scene, evaluation.projections, evaluation.volume, f"{config.method}, {scene.name}")
        return report.finish(self.run_dir, report.with_fitting_box(report.classical_metrics(config, scene, rec, evaluation, self.device),
                                                                       self.fitting))
