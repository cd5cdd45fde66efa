"""The pipeline of a classical run (``kneas-train fdk ...``): reconstruct -> evaluate -> report.

Writes ``volume.npy`` (data units) to the run folder; ``kneas-eval`` and ``kneas-export``
read it back.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..atomic import atomic_write
from ..classical.reconstruct import reconstruct
from ..console import console, say
from . import report
from .evaluate import evaluate_volume_stage
from .figures import run_figures
from .progress import stage_progress


class ClassicalPipeline:
    """``ClassicalPipeline(config, scene=, run_dir=, device=).run() -> exit code``."""

    def __init__(self, config, *, scene, run_dir: Path, device, started: float = 0.0):
        self.config, self.scene, self.run_dir, self.device = config, scene, Path(run_dir), device

    def run(self) -> int:
        config, scene = self.config, self.scene
        say(f"{config.algorithm}: reconstructing from {len(scene.train)} views")
        with stage_progress(console, unit="iterations") as progress:
            task = progress.add_task(config.algorithm, total=None, info="")
            rec = reconstruct(config.algorithm, scene, config.reconstruction, device=self.device,
                              progress=lambda i, n, r: progress.update(task, completed=i, total=n, info=f"residual {r:.3e}"))
        volume = np.asarray(rec.volume, dtype=np.float32)
        atomic_write(self.run_dir / "volume.npy", lambda fh: np.save(fh, volume))
        evaluation = evaluate_volume_stage(volume, scene, console)
        run_figures(self.run_dir, scene, evaluation.projections, evaluation.volume, f"{config.method}, {scene.name}")
        return report.finish(self.run_dir, report.classical_metrics(config, scene, rec, evaluation, self.device))
