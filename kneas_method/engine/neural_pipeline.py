"""The pipeline of a neural run: (bounds) -> (warm start) -> training -> evaluation -> report.

Stages (each returns a typed result). Every stage up to the trained model works on the box the views
are fitted on (``data.truncation.fitting_scene``: the scene's own, or longer along the axis where the
object goes on beyond it, in the same model units); the evaluation and the report on the scene's.

1. **bounds** (fields with surfaces): ``bounds_stage.estimate_bounds`` -> ``BoundsResult``,
   kept as ``bounds.json`` (reused on resume); K (BIC, the file, or ``--num-materials``)
   is written back into ``config.json``.
2. **classical volume** (``--bounds-volume fdk`` or ``--trainer.warm-start fdk``):
   ``classical_volume`` reconstructs the training views once, cached in the run folder.
3. **training**: ``train_stage`` (resume from the newest checkpoint, or warm start, then
   ``Trainer.train``).
4. **correction** (surface models, ``trainer.correction_passes`` > 0): ``correct_stage``, passes of
   the band correction of the trained model against the training views (``kneas_method.correction``),
   each written into the model, as many as the run's time budget leaves room for
   (``trainer.time_budget``, ``engine.budget``: training gives way first, then the passes); the
   checkpoint is rewritten with them.
   **materials** (bounds from the peaks rule's fallback: a noisy start): ``materials_stage`` fits
   the mixtures again to the trained volume and, where they find more materials, refits the model
   with them (``bounds.json``, ``config.json`` and the checkpoint follow).
5. **evaluation**: ``evaluate_model_stage`` on all held-out views and the voxel centres.
6. **report**: figures, ``metrics.json`` and the summary block (``report``).
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Optional

from ..console import EXIT_INTERRUPTED, console, say
from ..data.truncation import FittingBox
from ..errors import ConfigError
from ..model import field_has_surfaces
from . import report
from .bounds_stage import BoundsResult, estimate_bounds
from .budget import run_budget
from .classical_volume import classical_volume, start_options
from .correction_stage import correct_stage
from .evaluate import evaluate_model_stage
from .figures import run_figures
from .materials_stage import materials_stage, refit_bounds
from .run_dir import read_json, save_run_config, write_json
from .train_stage import WarmStartVolume, train_stage
from .trainer import StageInterrupted


def tensorboard_writer(run_dir: Path):
    """A SummaryWriter in ``run_dir/tensorboard`` when tensorboard is installed, else None."""
    try:
        from torch.utils.tensorboard import SummaryWriter  # needs the tensorboard package
    except Exception:
        return None
    try:
        return SummaryWriter(str(run_dir / "tensorboard"))
    except Exception:
        return None


def _interrupted(run_dir: Path, message: str) -> int:
    say(message)
    say(f"resume with: kneas-train --resume {run_dir}")
    return EXIT_INTERRUPTED


class NeuralPipeline:
    """``NeuralPipeline(config, scene=, run_dir=, device=, started=).run() -> exit code``."""

    def __init__(self, config, *, scene, run_dir: Path, device, started: float = 0.0, fitting: Optional[FittingBox] = None):
        self.config, self.scene, self.run_dir, self.device = config, scene, Path(run_dir), device
        self.fitting = fitting or FittingBox(scene)
        self.started = started or time.perf_counter()
        self.classical_seconds = 0.0
        self._classical: dict = {}

    # ----------------------------------------------------------------- stages
    def classical(self, algorithm: str):
        """The run's classical reconstruction by ``algorithm``, computed once."""
        if algorithm not in self._classical:
            options = start_options(algorithm, self.config.reconstruction, self.fitting.wider_than_view)
            rec = classical_volume(algorithm, options, self.fitting.scene, self.run_dir, self.device)
            self._classical[algorithm] = rec
            self.classical_seconds += rec.seconds
        return self._classical[algorithm]

    def bounds(self) -> Optional[BoundsResult]:
        """The bounds of a surface model (``bounds.json``, reused on resume); None without surfaces."""
        config = self.config
        if not field_has_surfaces(config.model):
            return None
        path = self.run_dir / "bounds.json"
        if path.is_file():
            result = refit_bounds(BoundsResult.from_json(read_json(path, "bounds file")), self.run_dir, config.method)
            say(f"bounds: already estimated for this run ({path}; K = {result.K})")
            if result.details.get("volume") not in (None, "prior"):
                self.classical(result.details["volume"])  # its time is part of the run's
        else:
            volume = None
            if config.bounds_volume != "prior" and config.bounds is None and config.model.alphas is None and config.bounds_source == "auto":
                volume = self.classical(config.bounds_volume).volume
            result = estimate_bounds(config, self.fitting.scene, self.run_dir, self.device, volume=volume)
            write_json(path, result.to_json())
        if config.model.selector == "hard" and result.K != 2:
            raise ConfigError(f"method {config.method!r} uses the hard selector (2 materials) but the bounds have K = {result.K}; give 2-material bounds")
        return result

    def warm_start(self) -> Optional[WarmStartVolume]:
        what = self.config.trainer.warm_start
        if what == "none":
            return None
        return WarmStartVolume(self.classical(what).volume, what)

    # -------------------------------------------------------------------- run
    def run(self) -> int:
        run_dir, scene, device = self.run_dir, self.scene, self.device
        fit = self.fitting.scene  # the views are fitted on its box; the model is scored on the scene's
        tb = tensorboard_writer(run_dir)
        stage = "while the bounds were estimated"
        try:
            bounds = self.bounds()
            config = self.config
            if bounds is not None:  # the K actually trained (and, from the peaks rule, where material 1's labels start)
                model = dataclasses.replace(config.model, num_materials=bounds.K)
                if model.first_label_threshold is None and bounds.details.get("first_label_threshold") is not None:
                    model = dataclasses.replace(model, first_label_threshold=float(bounds.details["first_label_threshold"]))
                config = dataclasses.replace(config, num_materials=bounds.K, model=model)
                save_run_config(run_dir, config)
            stage = "before training (the warm start)"
            warm = self.warm_start()
            budget = run_budget(config.trainer.time_budget, fit.geometry.n_voxel)
            trainer = train_stage(config, fit, run_dir, epochs=config.trainer.epochs, device=device,
                                  bounds=None if bounds is None else (bounds.alphas, bounds.betas), label="model", tb=tb, warm=warm,
                                  deadline=None if budget is None else self.started + budget)
            config = trainer.config  # the epochs it trained, where the budget shortened them (config.json says so too)
        except StageInterrupted as exc:
            return _interrupted(run_dir, f"[yellow]interrupted at step {exc.step}[/]: checkpoint {exc.checkpoint or 'no checkpoint (none written yet)'}")
        except KeyboardInterrupt:
            return _interrupted(run_dir, f"[yellow]interrupted[/] {stage}")
        finally:
            if tb is not None:
                tb.flush()
        try:
            correction = correct_stage(trainer, fit, config, device, run_started=self.started)
        except KeyboardInterrupt:
            return _interrupted(run_dir, f"[yellow]interrupted during the correction[/]; training is complete (checkpoint {trainer.last_checkpoint})")
        try:
            config, bounds = materials_stage(trainer, fit, config, bounds, run_dir)
        except KeyboardInterrupt:
            return _interrupted(run_dir, f"[yellow]interrupted while the materials were found again[/]; training and the correction are "
                                f"complete (checkpoint {trainer.last_checkpoint})")
        try:
            evaluation = evaluate_model_stage(trainer.model, scene, config, device, console, fitting=self.fitting)
        except KeyboardInterrupt:
            return _interrupted(run_dir, f"[yellow]interrupted during the evaluation[/]; training is complete (checkpoint {trainer.last_checkpoint})")
        if tb is not None:
            for k in ("psnr2d", "ssim2d", "psnr3d", "ssim3d"):
                if k in evaluation.metrics:
                    tb.add_scalar(f"eval/{k}", evaluation.metrics[k], trainer.step)
            tb.close()
        run_figures(run_dir, scene, evaluation.projections, evaluation.volume, f"{config.method}, {scene.name}", trainer)
        used = [k for k in self._classical]
        metrics = report.neural_metrics(config, scene, trainer, bounds, evaluation, device, classical_time_s=self.classical_seconds,
                                        classical_volume=used[0] if len(used) == 1 else (used or None),
                                        session_wall_time_s=time.perf_counter() - self.started, correction=correction)
        return report.finish(run_dir, report.with_fitting_box(metrics, self.fitting))
