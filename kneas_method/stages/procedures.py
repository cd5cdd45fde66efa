"""Procedures: how a method's model is fitted, by name (``--procedure``).

A procedure is a list of stages (``kneas.stages``) run around the core every neural run has (the
bounds and the training loop), and the values it gives the fitting settings a run leaves unset
(the SDF's starting sharpness, the eikonal weight, the learning rate's step, the visual hull, the
bounds' K rule). The preset (compute: epochs, rays, grid, width) picks a default procedure; a plugin
registers its own under the ``kneas.procedures`` entry-point group.

* ``paper``: the paper's (SPEC §3-4): a NeAS-1M prior, GMM bounds on its volume (K = 1..4 by BIC),
  then training. No stage outside the core.
* ``refine-classical``: the model refines a classical reconstruction: bounds from the histogram
  peaks of an ASD-POCS start (on a noisy scan, mixtures by BIC on the start after an edge-preserving
  filter), the model warm-started from it and anchored to it during training
  (sampling only in the visual hull), then band-correction passes, SURE smoothing and, on a noisy
  scan, the materials found again; all within a time budget.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any


@dataclass(frozen=True)
class Procedure:
    """A named procedure.

    Attributes:
        name: as ``--procedure`` takes it.
        description: one line for ``--help`` and the run's printout.
        stages: the registered stages it runs, in order (the core, bounds and training, is not listed).
        settings: values for settings the run leaves at None, by section: ``model`` (``s_init``,
            ``lambda_eikonal``, ``occupancy_grid``), ``trainer`` (``lr_decay_at``) and ``run`` (the
            bounds' ``bounds_k_rule``, ``bounds_max_materials``, ``bounds_min_std``, ``bounds_gmm_restarts``,
            ``bounds_upper_percentile``, ``bounds_upper_factor``, ``bounds_cover_percentile``,
            ``bounds_at_noise_k_rule``).
    """

    name: str
    description: str
    stages: tuple[str, ...] = ()
    settings: dict[str, dict[str, Any]] = field(default_factory=dict)


PAPER = Procedure(
    name="paper",
    description="the paper's: a NeAS-1M prior, GMM bounds on its volume (K = 1..4 by BIC), then training",
    stages=(),
    settings={
        "model": {"s_init": 20.0, "lambda_eikonal": 0.01, "occupancy_grid": False},
        "trainer": {"lr_decay_at": 0.5},
        "run": {"bounds_k_rule": "bic", "bounds_max_materials": 4, "bounds_min_std": 0.0, "bounds_gmm_restarts": 1,
                "bounds_upper_percentile": 99.5, "bounds_upper_factor": 1.15, "bounds_cover_percentile": 0.0},
    },
)

# The values below were chosen on the cpu preset's short schedule: an eikonal
# weight of 0.01 outweighs the ~1e-5 intensity loss of NAF-scale data in a few thousand steps, and a
# sharper start (s = 100) and a later learning-rate step suit a model warm-started from a volume.
REFINE_CLASSICAL = Procedure(
    name="refine-classical",
    description="the model refines an ASD-POCS start: bounds from its histogram's peaks, a warm start and an anchor to it, "
                "the visual hull, band-correction passes, SURE smoothing, the materials refit on noisy scans, a time budget",
    stages=("classical-start", "time-budget", "warm-start", "anchor", "correction", "smoothing", "materials-refit"),
    settings={
        "model": {"s_init": 100.0, "lambda_eikonal": 1e-5, "occupancy_grid": True},
        "trainer": {"lr_decay_at": 0.85},
        "run": {"bounds_k_rule": "peaks", "bounds_max_materials": 8, "bounds_min_std": 0.0, "bounds_gmm_restarts": 3,
                "bounds_upper_percentile": 99.5, "bounds_upper_factor": 1.15, "bounds_cover_percentile": 99.99,
                "bounds_at_noise_k_rule": "bic"},
    },
)

# the setting names a procedure may give, by section (a plugin's procedure is checked against them)
SETTINGS = {
    "model": ("s_init", "lambda_eikonal", "occupancy_grid"),
    "trainer": ("lr_decay_at",),
    "run": ("bounds_k_rule", "bounds_max_materials", "bounds_min_std", "bounds_gmm_restarts", "bounds_upper_percentile",
            "bounds_upper_factor", "bounds_cover_percentile", "bounds_at_noise_k_rule"),
}
