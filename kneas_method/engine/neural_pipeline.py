"""The pipeline of a neural run: its procedure's stages around the core (bounds, training), then the
evaluation and the report.

Every stage up to the trained model works on the box the views are fitted on
(``data.truncation.fitting_scene``: the scene's own, or longer along the axis where the object goes
on beyond it, in the same model units); the evaluation and the report on the scene's.

1. ``start`` stages (``kneas_method.stages``): the classical start.
2. **bounds** (fields with surfaces): ``bounds_stage.estimate_bounds`` on the classical start's volume
   or a NeAS-1M prior -> ``BoundsResult``, kept as ``bounds.json`` (reused on resume); K is written
   back into ``config.json``.
3. **the Trainer**: resumed from the newest checkpoint, or fresh (with the visual hull when the model
   has an occupancy grid); ``before-training`` stages (time budget, warm start, anchor); training.
4. ``after-training`` stages: band correction, smoothing, materials refit.
5. **evaluation**: ``evaluate_model_stage`` on all held-out views and the voxel centres.
6. **report**: figures, ``metrics.json`` (with the procedure and every stage's record) and the summary.
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
from ..stages import RunState
from . import report
from .bounds_stage import BoundsResult, at_noise_k_rule, estimate_bounds
from .evaluate import evaluate_model_stage
from .figures import run_figures
from .loss_scale import LOSS_SCALE_TOP, loss_scale
from .run_dir import read_json, save_run_config, write_json
from .trainer import StageInterrupted, Trainer


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


def build_stages(config) -> list:
    """The run's stages (``presets.stage_configs``), built, in the order their phases and the
    procedure give."""
    from ..presets import stage_configs
    from ..stages import PHASES

    configs = stage_configs(config)
    return [cfg.setup() for phase in PHASES for cfg in configs if type(cfg).phase == phase]


class NeuralPipeline:
    """``NeuralPipeline(config, scene=, run_dir=, device=, started=).run() -> exit code``."""

    def __init__(self, config, *, scene, run_dir: Path, device, started: float = 0.0, fitting: Optional[FittingBox] = None):
        self.config, self.scene, self.run_dir, self.device = config, scene, Path(run_dir), device
        self.fitting = fitting or FittingBox(scene)
        self.started = started or time.perf_counter()

    def bounds(self, state: RunState) -> Optional[BoundsResult]:
        """The bounds of a surface model (``bounds.json``, reused on resume); None without surfaces."""
        from ..stages.materials_refit import refit_bounds

        config = state.config
        if not field_has_surfaces(config.model):
            return None
        path = self.run_dir / "bounds.json"
        if path.is_file():
            result = refit_bounds(BoundsResult.from_json(read_json(path, "bounds file")), self.run_dir, config.method)
            say(f"bounds: already estimated for this run ({path}; K = {result.K})")
        else:
            automatic = config.bounds is None and config.model.alphas is None and config.bounds_source == "auto"
            at_noise = False
            if automatic and state.start is not None and at_noise_k_rule(config) is not None:
                from ..stages.classical_start import start_fit

                fit = start_fit(state)
                at_noise = bool(fit is not None and fit["at_noise"])
            result = estimate_bounds(config, state.scene, self.run_dir, self.device, start=state.start if automatic else None,
                                     loss_scale=state.loss_scale, start_at_noise=at_noise)
            write_json(path, result.to_json())
        if config.model.selector == "hard" and result.K != 2:
            raise ConfigError(f"method {config.method!r} uses the hard selector (2 materials) but the bounds have K = {result.K}; give 2-material bounds")
        return result

    def trainer(self, state: RunState, tb) -> Trainer:
        """The run's Trainer: resumed from its newest checkpoint, or fresh (with the visual hull)."""
        from .visual_hull import set_visual_hull

        config, bounds = state.config, state.bounds
        trainer = Trainer(config, state.scene, self.run_dir, epochs=config.trainer.epochs, device=self.device,
                          bounds=None if bounds is None else (bounds.alphas, bounds.betas), label="model", console=console,
                          tb=tb, tb_prefix="model/", loss_scale=state.loss_scale, records=state.records)
        path = trainer.resume()
        state.resumed = path is not None
        if path is None and trainer.model.occupancy is not None:
            set_visual_hull(trainer.model, state.scene, "model", say=say)
        if path is not None:
            say(f"model: resuming from {path} ({'complete' if trainer.complete else f'step {trainer.step}/{trainer.total_steps}'})")
        return trainer

    def run(self) -> int:
        run_dir, scene, device = self.run_dir, self.scene, self.device
        fit = self.fitting.scene  # the views are fitted on its box; the model is scored on the scene's
        stages = build_stages(self.config)
        state = RunState(config=self.config, scene=fit, run_dir=run_dir, device=device, started=self.started,
                         loss_scale=loss_scale(fit), say=say, fitting_wider_than_view=self.fitting.wider_than_view)
        if state.loss_scale != 1.0:
            say(f"losses measured in units of {state.loss_scale:.4g} /m, the 99.5th percentile of the scan's FDK volume, which is "
                f"above NAF's normalised {LOSS_SCALE_TOP:g} /m, so that they weigh as on NAF's scale; the volume and the bounds stay in /m")
        tb = tensorboard_writer(run_dir)
        where = "at the start"
        try:
            for stage in (s for s in stages if s.config.phase == "start"):
                where = f"during the {stage.name} stage"
                stage.run(state)
                if state.start is not None:
                    state.score(stage.name, state.start[0])
            where = "while the bounds were estimated"
            state.bounds = self.bounds(state)
            if state.bounds is not None:  # the K actually trained (and, from the peaks rule, where material 1's labels start)
                b = state.bounds
                model = dataclasses.replace(state.config.model, num_materials=b.K)
                if model.first_label_threshold is None and b.details.get("first_label_threshold") is not None:
                    model = dataclasses.replace(model, first_label_threshold=float(b.details["first_label_threshold"]))
                state.config = dataclasses.replace(state.config, num_materials=b.K, model=model)
                save_run_config(run_dir, state.config)
            where = "before training"
            trainer = state.trainer = self.trainer(state, tb)
            for stage in (s for s in stages if s.config.phase == "before-training"):
                where = f"during the {stage.name} stage"
                stage.run(state)
                if stage.name == "warm-start" and not state.resumed:
                    state.score(stage.name)
                    state.forget_volume()  # training moves the field everywhere
            say(f"model: {trainer.epochs} epochs x {trainer.steps_per_epoch} steps, {trainer.model.num_parameters():,} parameters")
            trainer.train(loss_terms=state.loss_terms, step_hooks=state.step_hooks)
            state.config = trainer.config  # the epochs it trained, where the budget shortened them (config.json says so too)
            state.forget_volume()
            state.score("training")
        except StageInterrupted as exc:
            return _interrupted(run_dir, f"[yellow]interrupted at step {exc.step}[/]: checkpoint {exc.checkpoint or 'no checkpoint (none written yet)'}")
        except KeyboardInterrupt:
            return _interrupted(run_dir, f"[yellow]interrupted[/] {where}")
        finally:
            if tb is not None:
                tb.flush()
        for stage in (s for s in stages if s.config.phase == "after-training"):
            try:
                stage.run(state)
                state.score(stage.name)
            except KeyboardInterrupt:
                return _interrupted(run_dir, f"[yellow]interrupted during the {stage.name} stage[/]; training is complete "
                                    f"(checkpoint {trainer.last_checkpoint})")
        config = state.config
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
        metrics = report.neural_metrics(config, scene, trainer, state.bounds, evaluation, device, stages=[s.name for s in stages],
                                        records=state.records, session_wall_time_s=time.perf_counter() - self.started)
        return report.finish(run_dir, report.with_fitting_box(metrics, self.fitting))
