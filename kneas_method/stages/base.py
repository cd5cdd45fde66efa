"""The one interface of a procedure's stages: a typed config that builds a :class:`Stage`, and the
:class:`RunState` every stage reads and writes.

A neural run goes through four phases (``engine.neural_pipeline``):

1. ``start``: stages that run before the bounds (the classical start);
2. the bounds (the paper's core: a NeAS-1M prior or the start's volume -> GMM -> bounds) and a fresh
   or resumed :class:`~kneas_method.engine.trainer.Trainer`;
3. ``before-training``: stages that prepare training (the warm start, the anchor's loss term, the
   time budget's step hook), then the Trainer trains;
4. ``after-training``: stages that work on the trained model (the band correction, the smoothing, the
   materials refit), then the evaluation.

A stage records what it did in ``run.records[name]`` (JSON-able); the records ride in the checkpoint,
so a resumed run does not redo a finished stage, and ``metrics.json`` keeps them under ``stages``.
A plugin adds a stage by registering its config class under the ``kneas.stages`` entry-point group.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, ClassVar, Literal, Optional

from ..config import InstantiateConfig, check_ranges

Phase = Literal["start", "before-training", "after-training"]
PHASES: tuple[str, ...] = Phase.__args__
# After a fit the model's volume is queried again only within this many voxels of where it moved the
# field: elsewhere such a fit moves the volume by an rms of about 6e-4 data units (at most 0.09 at
# single voxels), and the band correction's figures are the same as with the whole volume queried.
REQUERY_MARGIN = 1


@dataclass
class StageConfig(InstantiateConfig):
    """A stage's settings; ``setup()`` builds the :class:`Stage`.

    Class attributes: ``name`` (the stage's registered name, as ``--skip-stages`` takes it),
    ``phase`` (when it runs) and ``needs`` (stages it needs in the same procedure)."""

    name: ClassVar[str] = ""
    phase: ClassVar[Phase] = "after-training"
    needs: ClassVar[tuple[str, ...]] = ()

    def check(self, prefix: str) -> None:
        """One-line ConfigError for a setting out of its range (``config.at_least`` metadata)."""
        check_ranges(self, prefix)

    def describe(self) -> str:
        """One line for the run's printout: what the stage does with these settings."""
        return self.name


class Stage:
    """One part of a procedure: ``run(state)`` does the stage's work at its phase."""

    def __init__(self, config: StageConfig):
        self.config = config

    @property
    def name(self) -> str:
        return type(self.config).name

    def run(self, state: "RunState") -> None:
        raise NotImplementedError


@dataclass
class RunState:
    """What a neural run's stages share.

    Attributes:
        config: the run's resolved ``TrainConfig`` (K and the epochs follow the stages that change them).
        scene: the scene the views are fitted on (the fitting box's: ``data.truncation.FittingBox``).
        run_dir: the run folder.
        device: torch device.
        started: when the run started (``time.perf_counter`` seconds): the time budget counts from it.
        loss_scale: the unit the losses are measured in (``engine.loss_scale``), computed once.
        say: prints one progress line.
        fitting_wider_than_view: the object is wider than the detector's field of view
            (``data.truncation.FittingBox.wider_than_view``).
        records: stage name -> what it did (JSON-able); kept in the checkpoint and ``metrics.json``.
        start: the classical start's volume ``[nx, ny, nz]`` (data units) and its algorithm, or None.
        classical_seconds: time spent on classical reconstructions.
        bounds: the run's ``BoundsResult`` (surface models), or None.
        trainer: the Trainer, from phase 3 on.
        resumed: the Trainer continued from a checkpoint (a warm start is not done again).
        deadline: when the run's time budget runs out (``time.perf_counter`` seconds), or None.
        loss_terms: name -> a function of no arguments giving a loss term added to every training step.
        step_hooks: functions called with the Trainer after every training step.
        volume: the model's volume at the voxel centres as the last after-training stage left it
            (a tensor on the device), so the next one need not query the whole grid again; None: query it.
        moved_region: where a fit moved the field since ``volume`` was queried (bool), or None.
        projectors: ``classical.projector.Projector`` per grid factor, shared by the stages that project.
        scored_volume: the model volume :meth:`score` last scored (a stage that leaves it is not scored again).
    """

    config: Any
    scene: Any
    run_dir: Path
    device: Any
    started: float
    loss_scale: float
    say: Callable[[str], None]
    fitting_wider_than_view: bool = False
    records: dict[str, Any] = field(default_factory=dict)
    start: Optional[tuple[Any, str]] = None
    classical_seconds: float = 0.0
    bounds: Any = None
    trainer: Any = None
    resumed: bool = False
    deadline: Optional[float] = None
    loss_terms: dict[str, Callable[[], Any]] = field(default_factory=dict)
    step_hooks: list[Callable[[Any], None]] = field(default_factory=list)
    volume: Any = None
    moved_region: Any = None
    projectors: dict = field(default_factory=dict)
    scored_volume: Any = None
    train_views: Any = None

    def model_volume(self):
        """The model's volume ``[nx, ny, nz]`` (a tensor on the device): the one the last stage left,
        queried again where a fit has moved the field since (:meth:`moved`), or queried afresh at the
        voxel centres."""
        import torch

        from ..engine.evaluate import sample_volume
        from .band_correction import grow, requery_band

        if self.volume is None:
            self.volume = torch.as_tensor(sample_volume(self.trainer.model, self.scene.geometry, device=self.device),
                                          device=self.device)
        elif self.moved_region is not None:  # about a third of the voxels or less
            self.volume = requery_band(self.trainer.model, self.scene.geometry, self.volume, grow(self.moved_region, REQUERY_MARGIN))
        self.moved_region = None
        return self.volume

    def projector(self):
        """The scene grid's projector at the training views (built once, shared by the stages that project)."""
        from ..classical.projector import Projector

        if 1 not in self.projectors:
            self.projectors[1] = Projector(self.scene.geometry, self.scene.train.angles, device=self.device)
        return self.projectors[1]

    def views(self):
        """The training views' line integrals ``[N, nV, nU]`` as a float32 tensor on the device (made once,
        shared by the stages that compare a volume's projections with them)."""
        import numpy as np
        import torch

        if self.train_views is None:
            self.train_views = torch.as_tensor(np.asarray(self.scene.train.projections, dtype=np.float32), device=self.device)
        return self.train_views

    def score(self, after: str, volume=None) -> Optional[dict]:
        """Score the volume ``after`` a stage left (``volume``, numpy or tensor; by default the model's as
        :meth:`model_volume` holds it, queried again where a fit moved the field)
        against the scene's true volume, when it has one on the same grid: psnr3d / ssim3d as the
        evaluation scores them, printed and kept in ``records["scores"]`` (what each stage gained or
        lost). None when the scene has no truth."""
        import numpy as np

        from ..evaluation.metrics import psnr3d, ssim3d

        truth = getattr(self.scene, "image", None)
        if truth is None:
            return None
        if volume is None:
            unchanged = self.volume is not None and self.moved_region is None and self.volume is self.scored_volume
            volume = self.scored_volume = self.model_volume()
            if unchanged and self.records.get("scores"):  # the stage left the volume as it was: the last figures hold
                last = self.records["scores"][-1]
                return self._keep_score({**last, "after": after})
        v = volume.detach().float().cpu().numpy() if hasattr(volume, "detach") else np.asarray(volume, dtype=np.float32)
        if v.shape != tuple(np.shape(truth)):
            return None
        return self._keep_score({"after": after, "psnr3d": psnr3d(v, truth), "ssim3d": ssim3d(v, truth)})

    def _keep_score(self, row: dict) -> dict:
        after = row["after"]
        rows = [r for r in self.records.get("scores", []) if r.get("after") != after]  # a resumed run scores it again
        self.records["scores"] = rows + [row]
        self.say(f"score after {after}: psnr3d {row['psnr3d']:.2f} dB, ssim3d {row['ssim3d']:.4f} (against the scene's true volume)")
        return row

    def moved(self, region) -> None:
        """A fit moved the field in ``region`` [nx, ny, nz] (bool): :meth:`model_volume` queries it again there."""
        self.moved_region = region if self.moved_region is None else (self.moved_region | region)

    def put_back(self, volume) -> None:
        """The model was put back as it was when its volume was ``volume`` (a fit undone): no query needed."""
        self.volume, self.moved_region = volume, None

    def forget_volume(self) -> None:
        """The model changed everywhere (a new model): :meth:`model_volume` queries the whole grid again."""
        self.volume = self.moved_region = None


def stage_settings(config: StageConfig) -> dict:
    """A stage config's settings as a dict (for its record)."""
    return dataclasses.asdict(config)
