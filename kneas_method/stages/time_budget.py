"""The time budget (``--stages.time-budget.seconds``): the whole run within a number of seconds, and
small pure rules for what gives way.

A neural run's budget counts from the command's start (``engine.pipeline.train``). Training gives way
first, then the band-correction passes; the classical start and the evaluation never do. A budget
that binds makes the result depend on the machine's speed, and the run says so.

What training leaves for the stages after it follows the scan. The passes stop at the data's noise, so
where the classical start's projections already fit the training views to their noise (a noisy scan)
they are not expected to run, and training leaves the time of the smoothing's and the materials
refit's fits instead; elsewhere it leaves the passes their share.

* :func:`run_budget`: the seconds a run on a given grid may take.
* :func:`kept_after_training`: the seconds training leaves for the stages after it.
* :func:`training_steps`: after ``TIMED_STEPS`` steps, how many training steps leave that time before
  the budget runs out (training's last thousand steps are worth far less than the passes).
* :func:`pass_fits`: whether one more pass is expected to end in the time left.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Optional, Sequence

from ..config import at_least
from .base import RunState, Stage, StageConfig
from .classical_start import start_fit

# Seconds of a run's time budget kept for what follows the passes: the smoothing (a projection and
# SURE; on a noisy scan its fit), the materials refit's mixtures, the evaluation and the report (about
# 10 s on a clean 128^3 scan on 2 cores; a noisy scan's passes end at its noise long before any budget).
TIME_RESERVE_S = 30.0
# The budget is for a volume of this many voxels or fewer; a larger one gets it in proportion to its voxels
# (the classical start, the passes and the evaluation grow with them).
BUDGET_VOXELS = 128 ** 3
# What the training rule keeps for the passes, as a share of the whole training's time (12 passes took
# 0.56-0.87 of it on the built-in and larger-detector scenes on 2 cores).
PASSES_SHARE = 0.9
# Steps timed before training's length is checked against the budget, and the least share of its
# steps training is cut to (where even that does not fit, the passes give way as well).
TIMED_STEPS = 100
MIN_STEPS_SHARE = 0.25
# The smoothing's seconds besides its fit: the model's volume, the filters SURE compares and their
# projections (5-25 s on a noisy 128^3 scan on 2 cores).
SMOOTHING_CHOICE_S = 25.0


def run_budget(time_budget: Optional[float], n_voxel) -> Optional[float]:
    """Seconds a run on a grid of ``n_voxel`` (nx, ny, nz) voxels may take under a budget of
    ``time_budget`` seconds (None or 0: no budget): the budget, times the grid's voxels over
    ``BUDGET_VOXELS`` where it has more."""
    if not time_budget:
        return None
    return float(time_budget) * max(1.0, math.prod(int(n) for n in n_voxel) / BUDGET_VOXELS)


def kept_after_training(seconds_per_step: float, total: int, *, passes: bool, fit_steps: int = 0,
                        seconds: float = 0.0) -> float:
    """Seconds training leaves for the stages after it: ``PASSES_SHARE`` x the whole training's time
    (``total`` steps at ``seconds_per_step``) where band-correction passes are expected to run (``passes``),
    and ``fit_steps`` more steps at that rate plus ``seconds`` for the later stages' fits and mixtures."""
    return ((PASSES_SHARE * int(total) if passes else 0.0) + int(fit_steps)) * float(seconds_per_step) + float(seconds)


def training_steps(left: float, step: int, total: int, seconds_per_step: float, steps_per_epoch: int, kept: float) -> int:
    """The training steps (whole epochs of ``steps_per_epoch``) that end with ``kept`` seconds left
    (:func:`kept_after_training`).

    ``left``: seconds until the budget runs out, less ``TIME_RESERVE_S``; ``step`` of ``total`` steps
    run, at ``seconds_per_step``. Returns ``total`` where everything fits, else the most whole epochs
    that do, at least ``MIN_STEPS_SHARE`` of ``total`` and the epoch under way.
    """
    fit = step + (left - float(kept)) / max(float(seconds_per_step), 1e-9)
    if fit >= total:
        return int(total)
    least = max(math.ceil(MIN_STEPS_SHARE * total / steps_per_epoch), math.ceil(step / steps_per_epoch), 1)
    return int(min(total, max(int(fit // steps_per_epoch), least) * steps_per_epoch))


def pass_fits(left: float, seconds: Sequence[float], refreshed: Sequence[bool], refresh: bool) -> bool:
    """Whether a band-correction pass is expected to end within ``left`` seconds.

    ``seconds`` [n] and ``refreshed`` [n]: what each earlier pass took and whether it computed the
    discretisation error afresh (the dearest part of a pass); ``refresh``: whether this one will. Its
    cost is taken as the longest earlier pass of its kind, or of either kind where none is; the first
    pass needs only some time left.
    """
    if left <= 0:
        return False
    same = [s for s, r in zip(seconds, refreshed) if bool(r) == bool(refresh)]
    known = same or list(seconds)
    return not known or max(known) <= left


def after_training(state: RunState) -> dict:
    """What training is to leave for the stages after it in ``state``'s run, as the keyword arguments of
    :func:`kept_after_training` (less the step's time): whether the correction passes are expected to
    run, and the later stages' fit steps and other seconds where they are not."""
    stages, model = state.config.stages, state.trainer.model
    passes = stages.correction is not None and model.has_surfaces
    fit = start_fit(state) if model.has_surfaces else None
    if fit is None or not fit["at_noise"]:
        return {"passes": passes}
    state.say("time budget: the start fits the views to their noise, where the correction passes stop: training leaves "
              "time for the fits after them instead")
    from .materials_refit import refits

    fit_steps, seconds = 0, 0.0
    if stages.smoothing is not None:
        fit_steps, seconds = int(stages.smoothing.steps), SMOOTHING_CHOICE_S
    if stages.materials_refit is not None and refits(state.bounds):
        # the refit fits the bounds' mixtures again (as long as they took), and where it finds more materials, a fresh
        # model for its steps
        fit_steps += int(stages.materials_refit.steps)
        seconds += float(state.bounds.details.get("fit_time_s", 0.0))
    return {"passes": False, "fit_steps": fit_steps, "seconds": round(seconds, 1)}


@dataclass
class TimeBudgetConfig(StageConfig):
    """The whole run within ``seconds``, from the command's start. Training gives way first: after
    ``TIMED_STEPS`` steps, where the rest of them and the stages after them would not end
    ``TIME_RESERVE_S`` before the budget runs out, training is cut to the whole epochs that do (a
    quarter of them at least; ``config.json`` says so). The stages after training are taken as the
    band-correction passes (``PASSES_SHARE`` x the whole training's time), or where the classical
    start already fits the views to the data's noise (where the passes stop), as the smoothing's and
    the materials refit's fits. Then the passes: one not expected to end ``TIME_RESERVE_S`` before it
    is not started.
    The budget is for a grid of 128^3 voxels or fewer; a larger grid gets it in proportion.

    Attributes:
        seconds: the budget (10 minutes on 2 CPU cores: the cpu preset's goal).
    """

    _target = "kneas_method.stages.time_budget:TimeBudget"
    name = "time-budget"
    phase = "before-training"
    seconds: float = field(default=600.0, metadata=at_least(0, strict=True))

    def describe(self) -> str:
        return f"time budget: the whole run within {self.seconds:g} s (training gives way first, then the correction passes)"


class TimeBudget(Stage):
    """Sets the run's deadline, and a step hook that shortens training where the budget needs it."""

    def run(self, state: RunState) -> None:
        budget = run_budget(self.config.seconds, state.scene.geometry.n_voxel)
        state.deadline = state.started + budget
        state.records.setdefault(self.name, {"time_budget_s": round(budget, 1), "training": None})
        trainer = state.trainer
        if trainer.step >= trainer.total_steps:
            return  # a resumed run past its training: the passes check the deadline themselves
        plan = state.records[self.name].get("after_training")
        if plan is None:
            plan = state.records[self.name]["after_training"] = after_training(state)
        check_at = trainer.step + TIMED_STEPS

        def shorten_if_needed(trainer) -> None:
            if trainer.step != check_at:
                return
            now = time.perf_counter()
            per_step = (now - trainer.train_started_at) / TIMED_STEPS
            kept = kept_after_training(per_step, trainer.total_steps, **plan)
            fits = training_steps(state.deadline - TIME_RESERVE_S - now, trainer.step, trainer.total_steps, per_step,
                                  trainer.steps_per_epoch, kept)
            if fits < trainer.total_steps:
                planned = trainer.epochs
                trainer.shorten(fits)
                state.records[self.name]["training"] = {"epochs_planned": planned, "epochs": trainer.epochs,
                                                        "seconds_per_step": round(float(per_step), 5),
                                                        "seconds_left": round(float(state.deadline - now), 1),
                                                        "seconds_kept": round(float(kept), 1)}
                after = ("leave the band-correction passes their time" if plan["passes"] else
                         "leave the smoothing and the materials refit their time" if plan.get("fit_steps") else
                         "end within it")
                trainer.say(f"{trainer.label}: the run's time budget (--stages.time-budget.seconds; --skip-stages time-budget for none) "
                            f"has {state.deadline - now:.0f} s left, and a step takes {per_step:.3f} s: {trainer.total_steps} of the "
                            f"{planned * trainer.steps_per_epoch} steps ({trainer.epochs} of {planned} epochs) {after}, "
                            "so training is shortened to them")

        state.step_hooks.append(shorten_if_needed)
