"""One training stage: a model, its datamanager, Adam, the LR schedule, checkpoints (SPEC §3).

:class:`Trainer` trains one :class:`~kneas_method.model.CTModel` for a number of
epochs (one step per training projection) and owns everything a resumed run
needs to continue bit-for-bit where it stopped: model, optimizer and scheduler
state, the datamanager's sampler state, the generator passed to
``model.loss_dict(..., generator=)``, the torch RNG, the step and the loss
history. Checkpoints go to ``<run>/checkpoints/`` (atomic, weights-only; see
:mod:`.checkpoint`).

Interrupts: while a stage runs, the first Ctrl-C (SIGINT) only sets a flag; the
current step finishes, a checkpoint of that consistent state is written and
:class:`StageInterrupted` is raised (the CLI prints where and exits 130). A
second Ctrl-C interrupts at once (the last checkpoint written stays valid).

Bad numbers: a non-finite loss (or gradient) is not applied — the gradients are
zeroed, the step is counted and reported. ``max_bad_steps`` of them in a row
end the stage with a one-line :class:`~kneas_method.errors.KneasError` naming
the last good checkpoint; a checkpoint is never written while a parameter is
non-finite.
"""

from __future__ import annotations

import dataclasses
import signal
import threading
import time
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

import numpy as np
import torch

from ..errors import KneasError
from ..evaluation.metrics import psnr2d
from .checkpoint import load_latest_checkpoint, save_checkpoint
from .optim import adam
from .progress import format_losses, stage_progress


class StageInterrupted(Exception):
    """Ctrl-C during training; ``checkpoint`` is the file written (or the last good one, or None)."""

    def __init__(self, checkpoint: Optional[Path], step: int):
        super().__init__(f"interrupted at step {step}")
        self.checkpoint = checkpoint
        self.step = step


class _DeferredInterrupt:
    """Context manager: the first SIGINT sets ``requested``; a second raises KeyboardInterrupt."""

    def __init__(self):
        self.requested = False
        self._previous = None

    def _handler(self, signum, frame):
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGINT, self._handler)
        return self

    def __exit__(self, *exc):
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)
        return False


def stage_records(extra: dict) -> dict[str, Any]:
    """The stages' records a checkpoint's ``extra`` holds (``extra["stages"]``); a checkpoint written
    before the stages had records of their own kept them under their own keys, read here the same way."""
    records = dict(extra.get("stages") or {})
    if extra.get("warm_start_time_s"):
        records.setdefault("warm-start", {"seconds": float(extra["warm_start_time_s"])})
    if extra.get("correction") is not None:
        records.setdefault("correction", {"passes": extra["correction"], "budget": extra.get("correction_budget"),
                                          "seconds": float(extra.get("correction_time_s", 0.0))})
    if extra.get("denoising") is not None:
        records.setdefault("smoothing", dict(extra["denoising"]))
    if extra.get("materials_refit") is not None:
        records.setdefault("materials-refit", dict(extra["materials_refit"]))
    if extra.get("training_budget") is not None:
        records.setdefault("time-budget", {"training": extra["training_budget"]})
    return records


def _finite_params(model: torch.nn.Module) -> bool:
    return all(bool(torch.isfinite(p).all()) for p in model.parameters())


def _finite_grads(model: torch.nn.Module) -> bool:
    return all(p.grad is None or bool(torch.isfinite(p.grad).all()) for p in model.parameters())


class Trainer:
    """Train one model for ``epochs`` epochs.

    Args:
        config: the resolved TrainConfig of this stage (its ``model``, ``datamanager``,
            ``trainer`` and ``seed`` are used; ``method`` is written into checkpoints).
        scene: the scene with the training views already subsampled.
        run_dir: the stage's run folder (checkpoints go to ``run_dir/checkpoints``).
        epochs: number of epochs of this stage.
        device: torch device.
        bounds: ``(alphas, betas)`` in data units for SDF models, or None (the
            model's own: config values or placeholders).
        label: progress-bar label (``prior``, ``model``).
        console: a rich Console for the progress bar and messages.
        tb: optional TensorBoard ``SummaryWriter``.
        tb_prefix: tag prefix for TensorBoard scalars.
    """

    def __init__(self, config, scene, run_dir, *, epochs: int, device, bounds=None, label: str = "model", console=None,
                 tb=None, tb_prefix: str = "", max_bad_steps: Optional[int] = None, loss_scale: float = 1.0,
                 records: Optional[dict] = None):
        from ..model import CTModel

        self.config = config
        self.scene = scene
        self.run_dir = Path(run_dir)
        self.ckpt_dir = self.run_dir / "checkpoints"
        self.device = torch.device(device)
        self.label = label
        self.console = console
        self.tb = tb
        self.tb_prefix = tb_prefix
        t = config.trainer
        self.max_bad_steps = int(max_bad_steps if max_bad_steps is not None else getattr(t, "max_bad_steps", 5))
        self.epochs = int(epochs)
        if self.epochs < 1:
            raise KneasError(f"the {label} stage has {epochs} epochs; give at least 1 (--trainer.epochs / --trainer.prior-epochs)")
        seed = int(config.seed)
        torch.manual_seed(seed)
        self.model = CTModel(config.model, scale=scene.geometry.scale, device=self.device).to(self.device)
        self.model.loss_scale = float(loss_scale)
        if not self.model.has_surfaces:  # its network's outputs in the same unit (the bounds carry it for the others)
            self.model.attenuation_unit.fill_(self.model.loss_scale)
        if bounds is not None:
            self.model.set_bounds(*bounds)
        elif self.model.has_surfaces and self.model.loss_scale != 1.0:  # NeAS's wide defaults are NAF-scale: in the scan's unit
            alphas, betas = self.model.bounds
            self.model.set_bounds([self.model.loss_scale * a for a in alphas], [self.model.loss_scale * b for b in betas])
        if self.model.quadrature == "voxel-planes":
            from ..occupancy import box_of

            self.model.set_voxel_grid(scene.geometry.n_voxel, *box_of(scene.geometry))
        self.datamanager = config.datamanager.setup(scene=scene, device=self.device, seed=seed)
        self.steps_per_epoch = self.datamanager.steps_per_epoch
        self.total_steps = self.epochs * self.steps_per_epoch
        self._make_optimizer()
        self.generator = torch.Generator(device="cpu")
        self.generator.manual_seed(seed + 7919)
        self.step = 0
        self.history: dict[str, list[list[float]]] = {}
        self.bad_steps: list[int] = []
        self.wall_time_s = 0.0
        self.train_started_at = 0.0  # time.perf_counter() when train() began (a step hook times the steps from it)
        self.last_checkpoint: Optional[Path] = None
        self.complete = False
        # what the procedure's stages did (stages.base.RunState.records): kept in every checkpoint
        self.records: dict[str, Any] = records if records is not None else {}

    def _make_optimizer(self) -> None:
        """A fresh Adam optimiser over the model's parameters and the learning-rate schedule."""
        t = self.config.trainer
        self.optimizer = adam(self.model.parameters(), lr=float(t.lr))
        self.decay_step = int(round(float(t.lr_decay_at) * self.total_steps))
        factor = float(t.lr_decay_factor)
        self.scheduler = torch.optim.lr_scheduler.LambdaLR(self.optimizer, lambda s: factor if s >= self.decay_step else 1.0)

    # ---------------------------------------------------------------- state
    def state(self, complete: bool = False) -> dict[str, Any]:
        return {
            "step": self.step,
            "epoch": self.step // self.steps_per_epoch,
            "method": self.config.method,
            "model": self.model.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "scheduler": self.scheduler.state_dict(),
            "datamanager": self.datamanager.state_dict(),
            "rng": {"torch": torch.get_rng_state(), "loss_generator": self.generator.get_state()},
            "extra": {
                "stage": self.label,
                "complete": bool(complete),
                "total_steps": self.total_steps,
                "history": self.history,
                "bad_steps": list(self.bad_steps),
                "wall_time_s": float(self.wall_time_s),
                "num_materials": int(self.model.num_materials),
                "stages": self.records,
            },
        }

    def load_state(self, state: dict[str, Any]) -> None:
        extra = state.get("extra", {})
        if int(extra.get("total_steps", self.total_steps)) != self.total_steps:
            raise KneasError(f"the checkpoint was written for {extra.get('total_steps')} steps but this stage has {self.total_steps}; "
                             "resume with the run's own config.json unchanged")
        self.model.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.scheduler.load_state_dict(state["scheduler"])
        self.datamanager.load_state_dict(state["datamanager"])
        torch.set_rng_state(state["rng"]["torch"])
        self.generator.set_state(state["rng"]["loss_generator"])
        self.step = int(state["step"])
        self.history = {k: [list(map(float, p)) for p in v] for k, v in extra.get("history", {}).items()}
        self.bad_steps = [int(s) for s in extra.get("bad_steps", [])]
        self.wall_time_s = float(extra.get("wall_time_s", 0.0))
        self.complete = bool(extra.get("complete", False))
        self.records.update(stage_records(extra))

    def resume(self) -> Optional[Path]:
        """Load the newest checkpoint of this stage, if any; returns its path."""
        from .checkpoint import list_checkpoints

        if not list_checkpoints(self.ckpt_dir):
            return None
        state, path, skipped = load_latest_checkpoint(self.ckpt_dir, method=self.config.method)
        for reason in skipped:
            self._print(f"[yellow]skipped damaged checkpoint:[/] {reason}")
        self.load_state(state)
        self.last_checkpoint = path
        return path

    def save(self, complete: bool = False) -> Optional[Path]:
        """Write a checkpoint of the current (consistent) state; never with non-finite parameters."""
        if not _finite_params(self.model):
            self._print(f"[red]not writing a checkpoint at step {self.step}: the model has non-finite parameters[/]; "
                        f"the last good one is {self.last_checkpoint}")
            return None
        try:
            path = save_checkpoint(self.ckpt_dir, self.state(complete))
        except OSError as exc:  # disk full, folder gone or read-only: keep the last good one and say where it is
            raise KneasError(
                f"cannot write a checkpoint at step {self.step} in {self.ckpt_dir} ({exc.strerror or exc}); "
                f"the last good checkpoint is {self.last_checkpoint or 'none (none was written yet)'}; "
                f"free some space, then resume with: kneas-train --resume {self.run_dir}") from None
        self.last_checkpoint = path
        return self.last_checkpoint

    def loss_history(self) -> dict[str, list[tuple[float, float]]]:
        """The recorded loss terms ``{name: [(step, value), ...]}`` (no learning rate or validation)."""
        return {k: [tuple(p) for p in v] for k, v in self.history.items() if k not in ("lr", "val_psnr2d")}

    # -------------------------------------------------------------- helpers
    def say(self, msg: str) -> None:
        """One line on the trainer's console (above a live progress bar)."""
        if self.console is not None:
            self.console.print(msg, soft_wrap=True)

    _print = say

    def record(self, name: str, value: float) -> None:
        """Append ``value`` at the current step to the loss history's ``name`` (and TensorBoard)."""
        self.history.setdefault(name, []).append([float(self.step), float(value)])
        if self.tb is not None:
            self.tb.add_scalar(f"{self.tb_prefix}{name}", value, self.step)

    @torch.no_grad()
    def validate(self) -> float:
        """Mean 2D PSNR over ``trainer.eval_views`` held-out views (all when None), their projections
        made as the final evaluation makes them (``trainer.eval_projections``: rendered through the
        field, or the model's volume projected)."""
        from .evaluate import held_out_projections

        val = self.scene.val
        n = len(val)
        k = self.config.trainer.eval_views
        idx = np.arange(n) if not k or k >= n else np.unique(np.round(np.linspace(0, n - 1, int(k))).astype(int))
        pred = held_out_projections(self.model, self.scene, self.config, self.device, np.asarray(val.angles)[idx])
        return float(np.mean(psnr2d(pred, np.asarray(val.projections)[idx])))

    # ------------------------------------------------------------ schedule
    def shorten(self, total_steps: int) -> None:
        """Train ``total_steps`` (whole epochs) instead of the planned steps, the learning rate's step at
        the same share of them (a time budget that does not hold them); ``config.json`` is rewritten
        with the epochs, so that a resumed run trains the same."""
        from .run_dir import save_run_config

        t = self.config.trainer
        self.epochs = int(total_steps) // self.steps_per_epoch
        self.total_steps = self.epochs * self.steps_per_epoch
        self.decay_step = int(round(float(t.lr_decay_at) * self.total_steps))
        self.config = dataclasses.replace(self.config, trainer=dataclasses.replace(t, epochs=self.epochs))
        save_run_config(self.run_dir, self.config)

    def replace_model(self, model, config) -> None:
        """Train ``model`` (built for ``config``, the run's config with its K) from now on, with a fresh
        optimiser and schedule for its parameters (a stage after training replaced the model; they
        only keep a checkpoint loadable)."""
        self.model, self.config = model, config
        self._make_optimizer()

    # ----------------------------------------------------------------- loop
    def train(self, loss_terms: Optional[dict[str, Callable[[], torch.Tensor]]] = None,
              step_hooks: Sequence[Callable[["Trainer"], None]] = ()) -> None:
        """Run the remaining steps; raise StageInterrupted on Ctrl-C, KneasError on repeated bad steps.

        ``loss_terms``: name -> a function of no arguments whose loss every step adds (a stage's, such as
        the anchor); ``step_hooks``: called with the trainer after every step (a stage's, such as the
        time budget's, which may :meth:`shorten` training)."""
        if self.complete or self.step >= self.total_steps:
            self.complete = True
            return
        loss_terms = dict(loss_terms or {})
        t = self.config.trainer
        eval_every = int(t.eval_every or 0)
        ckpt_every = int(t.checkpoint_every or 0)
        log_every = max(1, int(t.log_every or 1))
        consecutive = 0
        self.model.train()
        progress = stage_progress(self.console)
        started = self.train_started_at = time.perf_counter()
        last_info = ""
        with progress, _DeferredInterrupt() as interrupt:
            task = progress.add_task(self.label, total=self.total_steps, completed=self.step, info="")
            try:
                while self.step < self.total_steps:
                    batch = self.datamanager.next_train()
                    frac = self.step / self.total_steps
                    losses = self.model.loss_dict(batch, frac, generator=self.generator)
                    for name, term in loss_terms.items():
                        losses[name] = term()
                        losses["total"] = losses["total"] + losses[name]
                    total = losses["total"]
                    ok = bool(torch.isfinite(total))
                    self.optimizer.zero_grad(set_to_none=True)
                    if ok:
                        total.backward()
                        ok = _finite_grads(self.model)
                    if ok:
                        self.optimizer.step()
                        consecutive = 0
                    else:
                        self.optimizer.zero_grad(set_to_none=True)
                        consecutive += 1
                        self.bad_steps.append(self.step)
                        progress.console.print(f"[yellow]step {self.step}: non-finite loss or gradient "
                                               f"({format_losses({k: float(v.detach()) for k, v in losses.items()})}); not applied[/]")
                    self.scheduler.step()
                    self.step += 1
                    values = {k: float(v.detach()) for k, v in losses.items()}
                    for k, v in values.items():
                        self.record(k, v)
                    if self.step % log_every == 0 or self.step == self.total_steps:
                        self.record("lr", self.optimizer.param_groups[0]["lr"])
                    if consecutive >= self.max_bad_steps:
                        self.wall_time_s += time.perf_counter() - started
                        started = time.perf_counter()
                        raise KneasError(
                            f"{consecutive} non-finite losses in a row ({self.label} stage, step {self.step}): training stopped; "
                            f"the last good checkpoint is {self.last_checkpoint or 'none (none was written yet)'}; "
                            "lower the learning rate (--trainer.lr) or check the data")
                    if self.step % 5 == 0 or self.step == self.total_steps:
                        last_info = format_losses({k: v for k, v in values.items() if k != "total"})
                    progress.update(task, completed=self.step, info=last_info)
                    planned = self.total_steps
                    for hook in step_hooks:
                        hook(self)
                    if self.total_steps != planned:
                        progress.update(task, total=self.total_steps)
                    epoch_done = self.step % self.steps_per_epoch == 0
                    epoch = self.step // self.steps_per_epoch
                    last = self.step == self.total_steps
                    if epoch_done and eval_every and epoch % eval_every == 0 and not last:
                        p = self.validate()
                        self.record("val_psnr2d", p)
                        progress.console.print(f"{self.label} epoch {epoch}/{self.epochs}: validation PSNR2D {p:.2f} dB "
                                               f"({t.eval_views or 'all'} held-out views)")
                    if last or (epoch_done and ckpt_every and epoch % ckpt_every == 0) or interrupt.requested:
                        self.wall_time_s += time.perf_counter() - started
                        started = time.perf_counter()
                        if self.save(complete=last) is None and last:
                            raise KneasError(
                                f"the model has non-finite parameters at the end of the {self.label} stage (step {self.step}); "
                                f"nothing was marked complete; the last good checkpoint is "
                                f"{self.last_checkpoint or 'none (none was written yet)'}; lower the learning rate (--trainer.lr)")
                    if interrupt.requested and not last:
                        raise StageInterrupted(self.last_checkpoint, self.step)
            except KeyboardInterrupt:  # second Ctrl-C, mid-step: keep the last consistent checkpoint
                raise StageInterrupted(self.last_checkpoint, self.step) from None
        self.complete = True
