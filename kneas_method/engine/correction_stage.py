"""The band-correction stage of a neural run (``kneas_method.correction``).

After training, ``correct_stage`` runs ``trainer.correction_passes`` passes on the trained surface
model: each computes the band correction ``x`` of the model's volume ``v`` against the training
projections and fits the model to ``v + x`` inside the band (``Trainer.fit_to_volume``), so the
field, and with it the surfaces, carries the correction. A pass that stops at the noise level
before its first iteration ends them. Then (``trainer.denoise sure``) ``denoise_stage`` smooths the
model's volume as far as SURE says its own noise allows (``kneas_method.denoise``; nothing on a clean
scan) and fits the model to it. The passes' and the smoothing's figures are kept in the checkpoint (rewritten at
the same step), so a resumed run does not redo them and ``load_run`` opens the corrected model.

**The time budget** (``trainer.time_budget``, ``engine.budget``): the pipeline gives the stage the
moment the run started (``run_started``, ``time.perf_counter`` seconds); a pass that ``budget.pass_fits``
does not expect to end ``budget.TIME_RESERVE_S`` before the budget runs out is not started, and
``trainer.correction_budget`` says so.
"""

from __future__ import annotations

import time
from typing import Optional

import numpy as np
import torch

from ..console import say
from .budget import TIME_RESERVE_S, pass_fits, run_budget

# After the first pass the model's volume is queried again only within this many voxels of the band
# the last pass fitted (within two of the last volume's edges): elsewhere the fit moves it by an rms
# of 6e-4 data units on abdomen, at most 0.09 at single voxels (docs/experiments.md, 46th stop), and
# the passes' psnr3d is the same as with the whole volume queried.
REQUERY_MARGIN = 1


def correct_stage(trainer, scene, config, device, run_started: Optional[float] = None) -> Optional[list]:
    """The band-correction passes of a trained surface model, then its SURE smoothing
    (``denoise_stage``, kept in ``trainer.denoising``); returns one dict per pass
    (``Correction.to_json``), or None where the run has none. ``run_started``: when the run started
    (``time.perf_counter`` seconds; None: no budget): no pass is started that is not expected to end
    ``TIME_RESERVE_S`` before the run's time budget (``budget.run_budget``) runs out (``budget.pass_fits``)."""
    from ..correction import band_correction, grow, requery_band
    from .evaluate import sample_volume

    t = config.trainer
    model = trainer.model
    if not t.correction_passes or not t.correction_iterations or not model.has_surfaces:
        return None
    if trainer.correction is not None:
        say(f"correction: already done for this run ({len(trainer.correction)} passes, checkpoint {trainer.last_checkpoint})")
        return trainer.correction
    say(f"correction: up to {t.correction_passes} pass{'es' if t.correction_passes != 1 else ''} of what the {len(scene.train)} training views still say, in a band "
        f"around the edges (at most {t.correction_iterations} CGLS iterations each), written into the model "
        "(--trainer.correction-passes 0 skips it)")
    started = time.perf_counter()
    projections = torch.as_tensor(np.asarray(scene.train.projections, dtype=np.float32), device=device)
    passes: list[dict] = []
    discretisation = None
    volume = fitted = None
    projectors: dict = {}  # the passes' projectors, kept with their ray tables
    seconds: list[float] = []  # what each pass took, and whether it estimated the discretisation error afresh
    refreshed: list[bool] = []
    trainer.correction_budget = None
    budget = run_budget(t.time_budget, scene.geometry.n_voxel) if run_started is not None else None
    deadline = None if budget is None else run_started + budget
    for k in range(int(t.correction_passes)):
        refresh = k % int(t.correction_refresh) == 0
        if deadline is not None and not pass_fits(deadline - TIME_RESERVE_S - time.perf_counter(), seconds, refreshed, refresh):
            left = deadline - time.perf_counter()
            trainer.correction_budget = {"time_budget_s": round(budget, 1), "passes_left_out": int(t.correction_passes) - k,
                                         "seconds_left": round(left, 1)}
            say(f"correction: the run's time budget ({budget:.0f} s, --trainer.time-budget; 0 = none) has {max(left, 0.0):.0f} s left, "
                f"{TIME_RESERVE_S:.0f} s of them kept for the evaluation: no time for pass {k + 1}, "
                f"so {int(t.correction_passes) - k} of {t.correction_passes} passes are left out (--trainer.time-budget 0 runs them all)")
            break
        begun = time.perf_counter()
        if volume is None:
            volume = torch.as_tensor(sample_volume(model, scene.geometry, device=device), device=device)
        else:  # the last fit moved the field in its band: query there again (about a third of the voxels or less)
            volume = requery_band(model, scene.geometry, volume, grow(fitted, REQUERY_MARGIN))
        with torch.no_grad():
            result = band_correction(model, volume, projections, scene.geometry, scene.train.angles,
                                     iterations=int(t.correction_iterations), noise_factor=float(t.correction_noise_factor),
                                     weighting=t.correction_weights, ring=t.correction_ring,
                                     discretisation=None if refresh else discretisation,
                                     projectors=projectors,
                                     progress=lambda message: say(f"correction {k + 1}: {message}"))
        discretisation = result.discretisation
        passes.append(result.to_json())
        if result.iterations == 0:
            break
        target = (volume + result.grid).clamp_min(0).cpu().numpy()
        fitted = result.band
        trainer.fit_to_volume(target, result.band.cpu().numpy(), int(t.correction_steps), int(t.correction_points),
                              float(t.correction_lr), curvature=float(t.correction_curvature))
        seconds.append(time.perf_counter() - begun)
        refreshed.append(refresh)
        say(f"correction {k + 1}: {result.iterations} iterations, residual {result.residuals[0]:.3g} -> {result.residuals[-1]:.3g} "
            f"(noise {result.noise_variance:.3g}); model fitted to the corrected volume, {time.perf_counter() - started:.0f} s so far")
    done = sum(1 for p in passes if p["iterations"] > 0)
    say(f"correction: {done} pass{'es' if done != 1 else ''} written into the model in {time.perf_counter() - started:.0f} s"
        + ("" if done == len(passes) else "; the last found nothing above the data's noise"))
    if t.denoise in ("sure", "sure-gaussian"):
        if volume is None:  # the budget left no time for a pass
            volume = torch.as_tensor(sample_volume(model, scene.geometry, device=device), device=device)
        elif passes[-1]["iterations"] > 0:  # the last pass's fit moved the field in its band
            volume = requery_band(model, scene.geometry, volume, grow(fitted, REQUERY_MARGIN))
        if 1 not in projectors:
            from ..classical.projector import Projector

            projectors[1] = Projector(scene.geometry, scene.train.angles, device=volume.device)
        trainer.denoising = denoise_stage(trainer, volume, config, projections, projectors[1])
    trainer.correction = passes
    trainer.correction_time_s = time.perf_counter() - started
    trainer.save(complete=True)
    return passes


def denoise_stage(trainer, volume: torch.Tensor, config, projections: torch.Tensor, projector) -> dict:
    """Smooth the corrected model's ``volume`` [nx, ny, nz] as far as SURE says its own noise
    allows, raising its noise estimate while the smoothed volume still fits the training
    ``projections`` [N, nV, nU] (through the passes' ``projector`` of the scene's grid) closer than
    their noise (``kneas_method.denoise.discrepancy_smoothing``), and fit the model to the result
    (the passes' fit, in the voxels that carry noise); nothing where no smoothing lowers the
    estimate. Returns ``Denoising.to_json``."""
    from ..correction import noise_variance
    from ..denoise import BILATERALS, discrepancy_smoothing

    t = config.trainer

    def misfit(v: torch.Tensor) -> float:
        r = projections - projector.forward(v.clamp_min(0))
        return float((r * r).mean())

    data_noise = noise_variance(projections - projector.forward(volume))
    smoothed, choice = discrepancy_smoothing(volume, misfit, data_noise, bilaterals=BILATERALS if t.denoise == "sure" else ())
    if len(choice.misfit) > 1:
        say("denoise: " + "; ".join(f"{label} (noise estimate x{m:g}) fits the projections to {r:.3f} of their noise"
                                    for m, label, r in choice.misfit[:-1])
            + ": closer than the noise, so the volume holds more noise than estimated, and the estimate was raised")
    if choice.filter == "none":
        say(f"denoise: no smoothing lowers the estimated error (SURE; noise std {choice.noise_std:.3g}, "
            f"correlation with a neighbour {choice.neighbour_correlation:.2f}): the volume is left as it is")
        return choice.to_json()
    what = (f"a Gaussian of {choice.sigma:g} voxel" if choice.filter == "gaussian" else
            f"a bilateral filter of {choice.sigma:g} voxels and {choice.range_stds:g} noise std")
    fits = f", its projections' misfit {choice.misfit[-1][2]:.3f} of the data's noise" if choice.misfit else ""
    say(f"denoise: {what} lowers the estimated squared error {choice.sure['none']:.4g} -> "
        f"{choice.sure[choice.label]:.4g} (SURE; noise std {choice.noise_std:.3g}, correlation with a neighbour "
        f"{choice.neighbour_correlation:.2f}{fits}; {choice.seconds:.0f} s); fitting the model to it (--trainer.denoise none skips it)")
    region = (volume != 0).cpu().numpy()
    trainer.fit_to_volume(smoothed.clamp_min(0).cpu().numpy(), region, int(t.denoise_steps), int(t.correction_points),
                          float(t.denoise_lr), curvature=float(t.correction_curvature),
                          what=f"the volume smoothed by {what}", stage="denoise")
    return choice.to_json()
