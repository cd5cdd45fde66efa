"""The warm start (not in the paper): before projection training, the fresh model is fitted to the
classical start's volume at the voxel centres, so training begins from that volume instead of the
initialisation."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..config import at_least
from ..errors import KneasError
from .base import RunState, Stage, StageConfig
from .volume_fit import fit_whole_volume

WARM_START_SEED_OFFSET = 104729  # the warm start's draws: the run's seed plus this


def warm_start(trainer, volume: np.ndarray, steps: int, points_per_step: int, what: str = "FDK",
               occupancy_weight: float = 0.0) -> float:
    """Fit the trainer's fresh model to an attenuation ``volume`` (data units, the scene's voxel
    grid; negative values clipped to 0) before projection training: ``steps`` Adam steps at the
    trainer's learning rate, each on ``points_per_step`` random voxel centres, loss = MSE of ``mu`` +
    ``occupancy_weight`` x the per-material occupancy cross-entropy (``CTModel.volume_loss_dict``) +
    the model's eikonal term. Seeded from the run's seed; leaves the training optimiser, sampler and
    RNG states untouched. The losses go into the trainer's history (``warm_start_*``). Returns the
    wall time in seconds."""
    if trainer.step != 0:
        raise KneasError(f"the warm start runs before training, but the {trainer.label} stage is at step {trainer.step}")
    started = time.perf_counter()
    values = fit_whole_volume(trainer, volume, "warm-start", steps, points_per_step, occupancy_weight, WARM_START_SEED_OFFSET,
                              f"{trainer.label} warm start", f"fit to the {what} volume",
                              f"check the {what} volume or use --skip-stages warm-start")
    for k, v in values.items():
        trainer.record(f"warm_start_{k}", v)
    return time.perf_counter() - started


@dataclass
class WarmStartConfig(StageConfig):
    """Fit the fresh model to the classical start's volume before projection training.

    Attributes:
        steps: Adam steps of the fit.
        points: voxel centres per step.
        occupancy: weight of the per-material occupancy cross-entropy (0 = the MSE of ``mu`` only).
    """

    _target = "kneas_method.stages.warm_start:WarmStart"
    name = "warm-start"
    phase = "before-training"
    needs = ("classical-start",)
    steps: int = field(default=300, metadata=at_least(0, whole=True))
    points: int = field(default=16384, metadata=at_least(1, whole=True))
    occupancy: float = field(default=0.01, metadata=at_least(0))

    def describe(self) -> str:
        return f"warm start: the fresh model fitted to the classical start for {self.steps} steps"


class WarmStart(Stage):
    def run(self, state: RunState) -> None:
        trainer, c = state.trainer, self.config
        if state.resumed or c.steps <= 0 or state.start is None:
            return
        volume, algorithm = state.start
        what = algorithm.upper()
        where = ("; the field queried only at those inside the visual hull" if trainer.model.occupancy is not None else "")
        state.say(f"{trainer.label}: warm start: fitting the model to the {what} reconstruction for {c.steps} steps "
                  f"({c.points:,} voxel centres each{where}; --skip-stages warm-start trains from the initialisation, as the paper)")
        seconds = warm_start(trainer, volume, int(c.steps), int(c.points), what=what, occupancy_weight=float(c.occupancy))
        state.records[self.name] = {"steps": int(c.steps), "seconds": float(seconds)}
        state.say(f"{trainer.label}: warm start done in {seconds:.1f} s")
