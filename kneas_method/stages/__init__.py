"""How a model is fitted: procedures (``procedures``) as lists of stages, each stage a module of its own
with a small typed config and one interface (``base``).

Stages, by the phase they run at:

* ``classical-start`` (start): a classical reconstruction of the training views (``classical_start``);
* ``time-budget`` (before training): the whole run within a number of seconds (``time_budget``);
* ``warm-start`` (before training): the fresh model fitted to the classical start (``warm_start``);
* ``anchor`` (before training): the classical start kept as a prior during training (``anchor``);
* ``correction`` (after training): band-correction passes against the views (``correction``,
  ``band_correction``);
* ``smoothing`` (after training): SURE-chosen smoothing (``smoothing``, ``denoise``);
* ``materials-refit`` (after training): a noisy scan's materials found again (``materials_refit``).

``volume_fit`` holds the fit of a model to a volume the stages share. In a run's config each stage's
settings are ``stages.<name>``; a resolved config holds ``None`` for every stage the run does not run.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Annotated, Any, Optional

import tyro

from .anchor import AnchorConfig
from .base import PHASES, RunState, Stage, StageConfig
from .classical_start import ClassicalStartConfig
from .correction import CorrectionConfig
from .materials_refit import MaterialsRefitConfig
from .procedures import PAPER, REFINE_CLASSICAL, Procedure
from .smoothing import SmoothingConfig
from .time_budget import TimeBudgetConfig
from .warm_start import WarmStartConfig

__all__ = ["StagesConfig", "StageConfig", "Stage", "RunState", "Procedure", "PAPER", "REFINE_CLASSICAL", "BUILT_IN",
           "field_name", "PHASES"]

# tyro: show each stage's flags (--stages.correction.passes) rather than a choice of "on" or "off"
_Part = tyro.conf.AvoidSubcommands


@dataclass
class StagesConfig:
    """Each stage's settings (``--stages.<stage>.<setting>``); the procedure decides which stages run
    (``--skip-stages`` leaves some out), and a resolved config holds null for the others.

    Attributes:
        classical_start: the classical reconstruction the bounds, the warm start and the anchor use.
        time_budget: the whole run within a number of seconds.
        warm_start: the fresh model fitted to the classical start before training.
        anchor: the classical start kept as a prior during training.
        correction: band-correction passes after training (surface models).
        smoothing: SURE-chosen smoothing after training, the model fitted to it (undone where it ends further from it).
        materials_refit: a noisy scan's materials found again on the trained volume (surface models).
        plugins: settings of stages from plugins (``kneas.stages``), by stage name (config files only).
    """

    classical_start: Annotated[Optional[ClassicalStartConfig], _Part] = field(default_factory=ClassicalStartConfig)
    time_budget: Annotated[Optional[TimeBudgetConfig], _Part] = field(default_factory=TimeBudgetConfig)
    warm_start: Annotated[Optional[WarmStartConfig], _Part] = field(default_factory=WarmStartConfig)
    anchor: Annotated[Optional[AnchorConfig], _Part] = field(default_factory=AnchorConfig)
    correction: Annotated[Optional[CorrectionConfig], _Part] = field(default_factory=CorrectionConfig)
    smoothing: Annotated[Optional[SmoothingConfig], _Part] = field(default_factory=SmoothingConfig)
    materials_refit: Annotated[Optional[MaterialsRefitConfig], _Part] = field(default_factory=MaterialsRefitConfig)
    plugins: Annotated[dict[str, dict[str, Any]], tyro.conf.Suppress] = field(default_factory=dict)


# the built-in stages: name -> its field in StagesConfig
BUILT_IN: dict[str, str] = {f.default_factory.name: f.name for f in dataclasses.fields(StagesConfig) if f.name != "plugins"}
# the stages a model without surfaces skips: they fit surfaces (correction, refit), or follow the correction (smoothing)
SURFACES_ONLY = ("correction", "smoothing", "materials-refit")


def field_name(stage: str) -> str:
    """``classical-start`` -> ``classical_start``."""
    return stage.replace("-", "_")
