"""The smoothing (not in the paper): the trained model's volume smoothed as far as SURE says its own
noise allows, and the model fitted to the result.

``denoise.discrepancy_smoothing`` picks the filter (none, a Gaussian, or an edge-preserving bilateral
filter) that minimises Stein's unbiased estimate of the volume's squared error under its own
correlated noise, raising the noise estimate while the smoothed volume's projections still fit the
training views closer than their noise, as a whole or in a band of detector frequency (the discrepancy
principle), and refusing a filter whose
projections fit the views worse than the unsmoothed volume's by more than their noise (it would take
out texture the views show). Where no filter lowers the estimate, or the one that does is refused
(a clean scan), the volume is left as it is and the model is not touched. Where the model's fit to
the smoothed volume ends further from it than the model was before the fit (a lightly noisy scan,
where the filter moves the volume less than a fresh fit shakes the model), the fit is undone.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Literal, Optional

import torch

from ..config import at_least
from .base import RunState, Stage, StageConfig
from .volume_fit import fit_in_region

SmoothingRule = Literal["sure", "sure-gaussian"]


@dataclass
class SmoothingConfig(StageConfig):
    """SURE-chosen smoothing of the trained model's volume, then a fit of the model to it.

    Attributes:
        rule: ``sure``: none, Gaussians or bilateral filters, whichever SURE prefers;
            ``sure-gaussian``: none or Gaussians only.
        steps: Adam steps of the model's fit to the smoothed volume (the whole filled volume moves).
        lr: learning rate of that fit.
        points: voxel centres per step of the fit.
        curvature: weight of the fit's surface-smoothness term.
    """

    _target = "kneas_method.stages.smoothing:Smoothing"
    name = "smoothing"
    phase = "after-training"
    rule: SmoothingRule = "sure"
    steps: int = field(default=300, metadata=at_least(0, whole=True))
    lr: float = field(default=1e-3, metadata=at_least(0))
    points: int = field(default=8192, metadata=at_least(1, whole=True))
    curvature: float = field(default=3e-3, metadata=at_least(0))

    def describe(self) -> str:
        return ("smoothing: the volume smoothed as far as SURE says its noise allows (nothing on a clean scan), the model fitted to it "
                "(undone where it ends further from it)")


def smooth_against_views(volume: torch.Tensor, projections: torch.Tensor, projector, rule: SmoothingRule = "sure",
                         mask: Optional[torch.Tensor] = None):
    """``volume`` [nx, ny, nz] smoothed as the smoothing stage smooths a model's volume: the filter SURE
    prefers (``rule``), its noise estimate raised while the smoothed volume's projections still fit
    ``projections`` [N, nV, nU] closer than their noise, as a whole or in any band of detector frequency
    where a voxel's noise shows (``denoise.discrepancy_smoothing``, ``denoise.band_power_ratios``; the
    noise from the volume's own residual, ``band_correction.noise_variance``). ``projector`` projects a volume
    at the views' angles (``classical.projector.Projector``). ``mask`` [nx, ny, nz] (bool): where the
    volume's noise is estimated; None: its non-zero voxels (a model's volume is exactly 0 outside its
    visual hull; a classical one, whose zeros are clamped noise, passes the whole grid). Returns
    ``(smoothed, denoise.Denoising)``; ``benchmarks/classical.py --smooth`` smooths classical volumes so."""
    import math

    from ..classical.iterative import pixels_per_voxel
    from .band_correction import noise_variance
    from .denoise import BILATERALS, band_power_ratios, discrepancy_smoothing

    last = {}  # the last volume asked about and its residual: its misfit and its bands share one projection

    def residual(v: torch.Tensor) -> torch.Tensor:
        if last.get("volume") is not v:
            last["volume"], last["residual"] = v, projections - projector.forward(v.clamp_min(0))
        return last["residual"]

    def misfit(v: torch.Tensor) -> float:
        r = residual(v)
        return float((r * r).mean())

    data_noise = noise_variance(projections - projector.forward(volume))
    footprint = 1.0 / pixels_per_voxel(projector.geometry)  # a voxel's width on the detector, pixels

    def band_fit(v: torch.Tensor) -> float:
        ratios = [b for b in band_power_ratios(residual(v), data_noise, footprint) if not math.isnan(b)]
        return min(ratios) if ratios else math.inf

    return discrepancy_smoothing(volume, misfit, data_noise, mask=mask, bilaterals=BILATERALS if rule == "sure" else (),
                                 band_fit=band_fit)


def material_voxels(volume: torch.Tensor, bounds=None) -> torch.Tensor:
    """The voxels of a model's ``volume`` [nx, ny, nz] whose noise the smoothing estimates: inside the
    visual hull (not exactly 0) and, given the run's ``bounds`` (``alphas``, ``betas``), at or above the
    middle of the lowest material's interval: [nx, ny, nz] bool. The model holds the air that the hull
    keeps at its lowest level, quiet, so a hull that keeps more air would otherwise dilute the estimate
    (a noisy phantom chest: 0.023 over the hull's 54 % of the box against 0.051 over its material)."""
    inside = volume != 0
    if bounds is None:
        return inside
    return inside & (volume >= float(bounds.betas[0]) + 0.5 * float(bounds.alphas[0]))


def filter_words(choice) -> str:
    """The filter of ``choice`` (a ``denoise.Denoising``) in words."""
    return (f"a Gaussian of {choice.sigma:g} voxel" if choice.filter == "gaussian" else
            f"a bilateral filter of {choice.sigma:g} voxels and {choice.range_stds:g} noise std")


def describe_choice(choice) -> list[str]:
    """What the smoothing chose and why, a line a step (a ``denoise.Denoising``): the noise estimate
    raised, a choice refused for giving up more fit than the noise, the filter kept or none."""
    lines = []
    accepted = choice.misfit[:-1] if choice.refused else choice.misfit  # a refused choice is the last one tried
    raised = accepted[:-1]  # the chosen filter is the last accepted one
    if raised:
        bands = list(choice.band_fit) + [None] * len(raised)

        def why(i: int, m: float, label: str, r: float) -> str:
            band = "" if bands[i] is None else f" (its closest detector band {bands[i]:.3f})"
            return f"{label} (noise estimate x{m:g}) fits the projections to {r:.3f} of their noise{band}"

        lines.append("; ".join(why(i, *t) for i, t in enumerate(raised))
                     + ": closer than the noise, so the volume holds more noise than estimated, and the estimate was raised")
    if choice.refused:
        r = choice.misfit[-1][2]
        lines.append(f"{choice.refused} would fit the projections to {r:.3g} x their noise against the unsmoothed volume's "
                     f"{choice.own_misfit:.3g}: it gives up more fit than the noise holds, so it would take out what the views "
                     "show (texture or edges), and is refused")
    if choice.filter == "none":
        if not choice.refused:
            lines.append(f"no smoothing lowers the estimated error (SURE; noise std {choice.noise_std:.3g}, "
                         f"correlation with a neighbour {choice.neighbour_correlation:.2f}): the volume is left as it is")
        else:
            lines.append("the volume is left as it is")
    else:
        fits = f", its projections' misfit {accepted[-1][2]:.3f} of the data's noise" if accepted else ""
        lines.append(f"{filter_words(choice)} lowers the estimated squared error {choice.sure['none']:.4g} -> "
                     f"{choice.sure[choice.label]:.4g} (SURE; noise std {choice.noise_std:.3g}, correlation with a neighbour "
                     f"{choice.neighbour_correlation:.2f}{fits}; {choice.seconds:.0f} s); fitting the model to it "
                     "(--skip-stages smoothing skips it)")
    return lines


def describe_fit(before: float, after: float, kept: bool) -> str:
    """The smoothing fit's outcome in a line: the squared distance (summed over the fitted voxels) of
    the model's volume to the smoothed one ``before`` and ``after`` the fit, and whether it was ``kept``."""
    head = f"the fit leaves {after:.4g} of the smoothed volume (squares summed) against {before:.4g} before it"
    return head + (": kept" if kept else ": it ended further from its target than where it began, so the model is put back "
                   "as it was (the volume left unsmoothed)")


class Smoothing(Stage):
    def run(self, state: RunState) -> None:
        c, trainer, scene = self.config, state.trainer, state.scene
        if state.records.get(self.name) is not None:
            state.say(f"smoothing: already done for this run (checkpoint {trainer.last_checkpoint})")
            return
        started = time.perf_counter()
        volume = state.model_volume()
        smoothed, choice = smooth_against_views(volume, state.views(), state.projector(), c.rule,
                                                mask=material_voxels(volume, state.bounds))
        for line in describe_choice(choice):
            state.say("smoothing: " + line)
        record = choice.to_json()
        if choice.filter != "none":
            what = filter_words(choice)
            target, region = smoothed.clamp_min(0), volume != 0
            before = float(((volume - target)[region] ** 2).sum())
            weights = {k: v.detach().clone() for k, v in trainer.model.state_dict().items()}
            fit_in_region(trainer, target.cpu().numpy(), region.cpu().numpy(), int(c.steps), int(c.points), float(c.lr),
                          curvature=float(c.curvature), what=f"the volume smoothed by {what}", stage="smoothing")
            state.moved(region)
            after = float(((state.model_volume() - target)[region] ** 2).sum())
            kept = after < before
            state.say("smoothing: " + describe_fit(before, after, kept))
            if not kept:
                trainer.model.load_state_dict(weights)
                state.put_back(volume)
            record.update(fit_distance_before=before, fit_distance_after=after, fit_kept=kept)
        state.records[self.name] = {**record, "seconds": time.perf_counter() - started}
        trainer.save(complete=True)
