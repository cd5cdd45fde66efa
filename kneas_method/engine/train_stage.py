"""One training stage of a neural run: build the Trainer, resume or warm-start it, train it."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from ..console import console, say
from .trainer import Trainer


@dataclass
class WarmStartVolume:
    """A volume to fit the fresh model to before projection training: ``volume [nx, ny, nz]``
    (data units) and what it is (``fdk``, ...)."""

    volume: np.ndarray
    what: str


def train_stage(config, scene, run_dir: Path, *, epochs: int, device, bounds, label: str, tb=None,
                warm: Optional[WarmStartVolume] = None) -> Trainer:
    """Build the stage's Trainer, resume it if it has checkpoints, else warm-start it from
    ``warm`` when given (``trainer.warm_start_steps`` steps), and train it."""
    trainer = Trainer(config, scene, run_dir, epochs=epochs, device=device, bounds=bounds, label=label, console=console,
                      tb=tb, tb_prefix=f"{label}/")
    path = trainer.resume()
    if path is not None:
        state = "complete" if trainer.complete else f"step {trainer.step}/{trainer.total_steps}"
        say(f"{label}: resuming from {path} ({state})")
    elif warm is not None and int(config.trainer.warm_start_steps or 0) > 0:
        steps = int(config.trainer.warm_start_steps)
        what = warm.what.upper()
        say(f"{label}: warm start: fitting the model to the {what} reconstruction for {steps} steps "
            f"({config.trainer.warm_start_points:,} voxel centres each; --trainer.warm-start none trains from the initialisation, as the paper)")
        seconds = trainer.warm_start(warm.volume, steps, int(config.trainer.warm_start_points), what=what,
                                     occupancy_weight=float(config.trainer.warm_start_occupancy))
        say(f"{label}: warm start done in {seconds:.1f} s")
    say(f"{label}: {trainer.epochs} epochs x {trainer.steps_per_epoch} steps, {trainer.model.num_parameters():,} parameters")
    trainer.train()
    return trainer
