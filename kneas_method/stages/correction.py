"""The band correction (not in the paper): after training, passes that solve for what the training
views still say about the model's volume in a band around its edges, and write it into the model.

Each pass computes the band correction ``x`` of the model's volume ``v`` against the training
projections (``band_correction.band_correction``: CGLS in the band against the scene grid's
projector, the grid's discretisation error estimated from the model's own sharper field on a finer
grid and taken out, stopped at the data's noise) and fits the model to ``v + x`` inside the band
(``volume_fit.fit_in_region``), so the field, its surfaces included, carries the correction. A pass
that stops at the noise level before its first iteration ends them. Under the run's time budget
(``time_budget``), a pass not expected to end before it is not started.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Literal, Optional

import torch

from ..config import at_least
from ..errors import ConfigError
from .base import RunState, Stage, StageConfig
from .band_correction import NOISE_FACTOR
from .time_budget import TIME_RESERVE_S, pass_fits
from .volume_fit import fit_in_region

CorrectionWeights = Literal["gradient", "ring"]


@dataclass
class CorrectionConfig(StageConfig):
    """The band-correction passes after training (surface models).

    Attributes:
        passes: passes at most.
        iterations: CGLS iterations per pass at most.
        weights: the column weights of each pass's CGLS in the band (a voxel of weight ``w`` moves as
            if its unknown were ``w`` times less free): ``ring``, 1 at the steep voxels and ``ring`` on
            the rest of the band (its outer ring); ``gradient``, the square root of the volume's
            gradient over its median on the steep voxels, at most 2.
        ring: with ``weights ring``, the weight of the band's outer ring (1: the whole band alike; 0:
            the steep voxels only).
        refresh: the discretisation error is computed afresh every this many passes and reused in
            between (computing it, the model queried on a finer grid, is the dearest part of a pass).
        noise_factor: a pass's iterations stop once the residual's mean square is within this factor
            of the data's noise variance (the discrepancy principle), so a noisy scan is not fitted to
            its noise.
        steps: Adam steps of each pass's fit of the model to the corrected volume.
        lr: learning rate of that fit.
        points: band voxel centres per step of the fit (and a quarter as many anywhere).
        curvature: weight of a surface-smoothness term in the fit (the distances' gradients one voxel
            apart should agree near a surface), so that what the views leave free of an edge is filled
            with a smooth surface rather than the correction's ripples.
    """

    _target = "kneas_method.stages.correction:Correction"
    name = "correction"
    phase = "after-training"
    passes: int = field(default=12, metadata=at_least(1, whole=True))
    iterations: int = field(default=4, metadata=at_least(1, whole=True))
    weights: CorrectionWeights = "ring"
    ring: float = field(default=0.5, metadata=at_least(0, at_most=1))
    refresh: int = field(default=3, metadata=at_least(1, whole=True))
    noise_factor: float = field(default=NOISE_FACTOR, metadata=at_least(0))
    steps: int = field(default=75, metadata=at_least(0, whole=True))
    lr: float = field(default=1e-4, metadata=at_least(0))
    points: int = field(default=8192, metadata=at_least(1, whole=True))
    curvature: float = field(default=3e-3, metadata=at_least(0))

    def check(self, prefix: str) -> None:
        super().check(prefix)
        if self.weights != "ring" and self.ring != CorrectionConfig.ring:
            raise ConfigError(f"--{prefix}ring weights the band's outer ring in the ring rule, and the weights are "
                              f"{self.weights!r}; add --{prefix}weights ring or leave --{prefix}ring out")

    def describe(self) -> str:
        return (f"correction: up to {self.passes} passes of what the training views still say in a band around the edges "
                "(CGLS), written into the model")


class Correction(Stage):
    def run(self, state: RunState) -> None:
        from .band_correction import band_correction

        c, trainer, scene = self.config, state.trainer, state.scene
        model = trainer.model
        if not model.has_surfaces:
            return
        done = state.records.get(self.name)
        if done is not None:
            state.say(f"correction: already done for this run ({len(done['passes'])} passes, checkpoint {trainer.last_checkpoint})")
            return
        state.say(f"correction: up to {c.passes} pass{'es' if c.passes != 1 else ''} of what the {len(scene.train)} training views still "
                  f"say, in a band around the edges (at most {c.iterations} CGLS iterations each), written into the model "
                  "(--skip-stages correction skips it)")
        started = time.perf_counter()
        projections = state.views()
        passes: list[dict] = []
        discretisation = None
        seconds: list[float] = []  # what each pass took, and whether it estimated the discretisation error afresh
        refreshed: list[bool] = []
        left_out: Optional[dict] = None
        for k in range(int(c.passes)):
            refresh = k % int(c.refresh) == 0
            if state.deadline is not None and not pass_fits(state.deadline - TIME_RESERVE_S - time.perf_counter(), seconds,
                                                             refreshed, refresh):
                left = state.deadline - time.perf_counter()
                left_out = {"passes_left_out": int(c.passes) - k, "seconds_left": round(left, 1)}
                state.say(f"correction: the run's time budget has {max(left, 0.0):.0f} s left, {TIME_RESERVE_S:.0f} s of them kept for "
                          f"the evaluation: no time for pass {k + 1}, so {int(c.passes) - k} of {c.passes} passes are left out "
                          "(--skip-stages time-budget runs them all)")
                break
            begun = time.perf_counter()
            volume = state.model_volume()
            with torch.no_grad():
                result = band_correction(model, volume, projections, scene.geometry, scene.train.angles,
                                         iterations=int(c.iterations), noise_factor=float(c.noise_factor),
                                         weighting=c.weights, ring=float(c.ring),
                                         discretisation=None if refresh else discretisation, projectors=state.projectors,
                                         progress=lambda message: state.say(f"correction {k + 1}: {message}"))
            discretisation = result.discretisation
            passes.append(result.to_json())
            if result.iterations == 0:
                break
            target = (volume + result.grid).clamp_min(0).cpu().numpy()
            fit_in_region(trainer, target, result.band.cpu().numpy(), int(c.steps), int(c.points), float(c.lr),
                          curvature=float(c.curvature))
            state.moved(result.band)  # the fit moved the field in the band: the next query there is afresh
            seconds.append(time.perf_counter() - begun)
            refreshed.append(refresh)
            state.say(f"correction {k + 1}: {result.iterations} iterations, residual {result.residuals[0]:.3g} -> "
                      f"{result.residuals[-1]:.3g} (noise {result.noise_variance:.3g}); model fitted to the corrected volume, "
                      f"{time.perf_counter() - started:.0f} s so far")
        written = sum(1 for p in passes if p["iterations"] > 0)
        state.say(f"correction: {written} pass{'es' if written != 1 else ''} written into the model in {time.perf_counter() - started:.0f} s"
                  + ("" if written == len(passes) else "; the last found nothing above the data's noise"))
        state.records[self.name] = {"passes": passes, "budget": left_out, "seconds": time.perf_counter() - started}
        trainer.save(complete=True)
