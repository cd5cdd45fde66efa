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
        trace = IterationTrace(config.algorithm, scene, self.fitting) if config.trace else None
        say(f"{config.algorithm}: reconstructing from {len(scene.train)} views"
            + (", every iteration scored against the true volume" if trace else ""))
        with stage_progress(console, unit="iterations") as progress:
            task = progress.add_task(config.algorithm, total=None, info="")
            rec = reconstruct(config.algorithm, self.fitting.scene, config.reconstruction, device=self.device,
                              progress=lambda i, n, r: progress.update(task, completed=i, total=n, info=f"residual {r:.3e}"),
                              iterates=trace.score if trace else None)
        fitted = np.asarray(rec.volume, dtype=np.float32)
        volume = np.ascontiguousarray(self.fitting.crop(fitted))
        atomic_write(self.run_dir / "volume.npy", lambda fh: np.save(fh, volume))
        if self.fitting.slices:  # the held-out views see the longer box: kneas-eval projects it again
            atomic_write(self.run_dir / FITTED_VOLUME, lambda fh: np.save(fh, fitted))
        evaluation = evaluate_volume_stage(volume, scene, console,
                                           fitted=(self.fitting.scene.geometry, fitted) if self.fitting.slices else None)
        run_figures(self.run_dir, scene, evaluation.projections, evaluation.volume, f"{config.method}, {scene.name}")
        metrics = report.classical_metrics(config, scene, rec, evaluation, self.device)
        if trace:
            metrics["trace"] = trace.result(volume)
            best = metrics["trace"]["best"]
            say(f"{config.algorithm}: best count {best['iterations']} of {len(metrics['trace']['psnr3d'])}: "
                f"psnr3d {best['psnr3d']:.2f}, ssim3d {best['ssim3d']:.4f}")
        return report.finish(self.run_dir, report.with_fitting_box(metrics, self.fitting))


class IterationTrace:
    """The psnr3d of the volume after every iteration, and the best count (``--trace``).

    The iterate is scored as the run would return it at that count (on the scene's box; ASD-POCS's
    and CGLS's clamped at 0, as they are on return); only the best one is kept, for its ssim3d.
    """

    CLAMPED = ("asd-pocs", "cgls")

    def __init__(self, algorithm: str, scene, fitting: FittingBox):
        from ..errors import ConfigError

        if scene.image is None:
            raise ConfigError(f"--trace scores every iteration against the true volume, and scene {scene.name} has none; drop --trace")
        if algorithm == "fdk":
            raise ConfigError("--trace is for the iterative methods (sart, os-sart, cgls, asd-pocs); fdk has no iterations")
        self.algorithm, self.truth, self.fitting = algorithm, np.asarray(scene.image, dtype=np.float32), fitting
        self.psnr: list[float] = []
        self.best: Optional[tuple[int, float, np.ndarray]] = None

    def score(self, iteration: int, x) -> None:
        from ..evaluation.metrics import psnr3d

        x = x.clamp(min=0.0) if self.algorithm in self.CLAMPED else x
        v = np.ascontiguousarray(self.fitting.crop(x.detach().cpu().numpy()))
        p = psnr3d(v, self.truth)
        self.psnr.append(round(float(p), 4))
        if self.best is None or p > self.best[1]:
            self.best = (iteration, float(p), v.astype(np.float32, copy=True))

    def result(self, final: np.ndarray) -> dict:
        from ..evaluation.metrics import psnr3d, ssim3d

        if self.best is None:  # no iteration ran
            self.best = (0, float(psnr3d(final, self.truth)), final)
        count, p, v = self.best
        return {"psnr3d": self.psnr, "best": {"iterations": int(count), "psnr3d": round(p, 4), "ssim3d": round(float(ssim3d(v, self.truth)), 4)}}
