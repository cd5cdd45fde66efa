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


def set_visual_hull(model, scene, label: str = "model") -> None:
    """Give ``model`` its empty-space grid: the visual hull of the scene's training views
    (``occupancy.visual_hull``; air = at or below the noise-aware air threshold)."""
    from ..datamanagers.ct import noise_air_threshold
    from ..occupancy import box_of, visual_hull

    threshold, _ = noise_air_threshold(np.asarray(scene.train.projections))
    occupied = visual_hull(scene.geometry, scene.train.angles, scene.train.projections,
                           resolution=int(model.config.occupancy_resolution), air_threshold=threshold)
    model.set_occupancy(occupied, *box_of(scene.geometry))
    say(f"{label}: empty space: the visual hull of the {len(scene.train)} training views keeps "
        f"{100 * float(occupied.float().mean()):.1f} % of the volume box ({occupied.shape[0]}^3 cells)")


def train_stage(config, scene, run_dir: Path, *, epochs: int, device, bounds, label: str, tb=None,
                warm: Optional[WarmStartVolume] = None, deadline: Optional[float] = None) -> Trainer:
    """Build the stage's Trainer, resume it if it has checkpoints, else warm-start it from
    ``warm`` when given (``trainer.warm_start_steps`` steps), keep ``warm`` as a prior when
    ``trainer.warm_start_anchor`` > 0 (resumed runs too), and train it, shortened where the run's
    time budget (``deadline``, ``time.perf_counter`` seconds; None: none) needs it (``Trainer.train``)."""
    trainer = Trainer(config, scene, run_dir, epochs=epochs, device=device, bounds=bounds, label=label, console=console,
                      tb=tb, tb_prefix=f"{label}/")
    path = trainer.resume()
    if path is None and trainer.model.occupancy is not None:
        set_visual_hull(trainer.model, scene, label)
    if path is not None:
        state = "complete" if trainer.complete else f"step {trainer.step}/{trainer.total_steps}"
        say(f"{label}: resuming from {path} ({state})")
    elif warm is not None and int(config.trainer.warm_start_steps or 0) > 0:
        steps = int(config.trainer.warm_start_steps)
        what = warm.what.upper()
        where = ("; the field queried only at those inside the visual hull, --trainer.fit-outside labels queries every one"
                 if str(config.trainer.fit_outside) == "skip" and trainer.model.occupancy is not None else "")
        say(f"{label}: warm start: fitting the model to the {what} reconstruction for {steps} steps "
            f"({config.trainer.warm_start_points:,} voxel centres each{where}; --trainer.warm-start none trains from the "
            "initialisation, as the paper)")
        seconds = trainer.warm_start(warm.volume, steps, int(config.trainer.warm_start_points), what=what,
                                     occupancy_weight=float(config.trainer.warm_start_occupancy))
        say(f"{label}: warm start done in {seconds:.1f} s")
    anchor = float(config.trainer.warm_start_anchor or 0.0)
    if warm is not None and anchor > 0:
        occupancy = float(config.trainer.anchor_occupancy)
        edges = float(config.trainer.anchor_edge_contrast or 0.0)
        region = str(config.trainer.anchor_region)
        trainer.set_anchor(warm.volume, anchor, int(config.trainer.anchor_points), occupancy_weight=occupancy, edge_contrast=edges,
                           region=region, outside=str(config.trainer.anchor_outside))
        labels, hints = "", ["--trainer.warm-start-anchor 0 trains on the projections alone"]
        a = trainer.anchor
        where = (f" drawn in the visual hull ({len(a.points):,} voxels, weight {a.weight:.3g} for their share)"
                 if a is not None and region == "hull" and trainer.model.occupancy is not None else "")
        if a is not None and a.outside is not None:
            where = (f" (the field queried only at those inside the visual hull, {1 - float(a.outside.float().mean()):.1%} of the "
                     "box; outside it the volume is 0 whatever the field)")
            hints.insert(0, "--trainer.anchor-outside labels queries every draw")
        if edges > 0:
            labels = f", its values held less at its sharp edges (half at a step of {edges:g} of its range per voxel)"
            hints.insert(0, "--trainer.anchor-edge-contrast 0 holds every voxel alike")
        if occupancy > 0 and trainer.model.has_surfaces:
            labels += f", and its labels away from its edges, weight {occupancy:g} inside it"
            hints.insert(0, "--trainer.anchor-occupancy 0 keeps its values only")
        say(f"{label}: anchor: the {warm.what.upper()} volume kept as a prior, weight {anchor:g}, "
            f"{config.trainer.anchor_points:,} voxel centres per step{where}{labels} ({'; '.join(hints)})")
    say(f"{label}: {trainer.epochs} epochs x {trainer.steps_per_epoch} steps, {trainer.model.num_parameters():,} parameters")
    t = config.trainer
    trainer.train(deadline=deadline, passes=bool(t.correction_passes and t.correction_iterations and trainer.model.has_surfaces))
    return trainer
