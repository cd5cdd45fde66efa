"""The materials of a noisy scan, found again on its trained volume (after the correction stage).

Where the bounds came from the peaks rule's fallback (``bounds.json`` ``smoothed``: the classical
start's histogram had fewer than two peaks, as a noisy scan's has), they are mixtures fitted to a
noisy volume, and the noise hides the materials of little contrast or few voxels. After training
and the SURE smoothing the model's volume is cleaner than that start by 3-4 dB. ``materials_stage``
fits the same mixtures (``bic-valleys``, the run's K range and starts) to it after the same
bilateral filter; where they find more materials than the start did, the model is replaced by a
fresh one with those bounds, fitted to the trained volume as the warm start fits
(``Trainer.refit_materials``, ``trainer.materials_refit_steps`` steps), and ``bounds.json``,
``config.json`` and the checkpoint follow. Where they find as many or fewer (a textured scan, whose
texture the filter smooths into one plateau), the model is kept. What was found is kept in the
checkpoint (``materials_refit``), so a resumed run does not redo it.
"""

from __future__ import annotations

import time
import warnings
from pathlib import Path
from typing import Optional

from ..console import say
from .bounds_stage import FALLBACK_RANGE, FALLBACK_SIGMA, BoundsResult, histogram_smoothing, run_mixtures
from .run_dir import save_run_config, write_json


def materials_stage(trainer, scene, config, bounds: Optional[BoundsResult], run_dir: Path) -> tuple:
    """``(config, bounds)`` after the materials are found again on the trained volume (module docs):
    the given ones where the stage does not apply or keeps the model, else the new K's."""
    from .evaluate import sample_volume

    steps = int(config.trainer.materials_refit_steps or 0)
    if bounds is None or not bounds.details.get("smoothed") or steps <= 0:
        return config, bounds
    done = trainer.materials_refit
    if done is not None:
        say(f"materials: already found again on the trained volume for this run (K = {done['K']})")
        return config, bounds
    started = time.perf_counter()
    volume = sample_volume(trainer.model, scene.geometry, device=trainer.device)
    say(f"materials: the mixtures fitted again to the trained volume after the start's filter (bilateral, {FALLBACK_SIGMA:g} voxels, "
        f"range {FALLBACK_RANGE:g} x its 99.5th percentile; --trainer.materials-refit-steps 0 keeps the start's K = {bounds.K})",
        markup=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the mixtures' remarks are the bounds stage's to make
        gmm = run_mixtures(config, k_rule="bic-valleys").fit(histogram_smoothing(volume))
    K = int(gmm.n_components_)
    found = {"K": K, "start_K": int(bounds.K), "boundaries": [float(b) for b in gmm.boundaries_], "refit": K > bounds.K,
             "steps": steps if K > bounds.K else 0}
    if K <= bounds.K:
        found["seconds"] = time.perf_counter() - started
        say(f"materials: the trained volume shows K = {K}, not more than the start's {bounds.K}: the model is kept "
            f"({found['seconds']:.0f} s)")
        trainer.materials_refit = found
        trainer.save(complete=True)
        return config, bounds
    alphas, betas = [float(a) for a in gmm.alphas_], [float(b) for b in gmm.betas_]
    say(f"materials: the trained volume shows K = {K} (the start {bounds.K}), boundaries "
        f"{', '.join(f'{b:.4g}' for b in gmm.boundaries_)}; a model with those bounds fitted to it for {steps} steps", markup=False)
    trainer.refit_materials(volume, alphas, betas, steps, int(config.trainer.warm_start_points),
                            float(config.trainer.warm_start_occupancy))
    found["seconds"] = time.perf_counter() - started
    trainer.materials_refit = found
    trainer.save(complete=True)  # the new model's checkpoint first: config.json and bounds.json then name its K
    start = {"K": bounds.K, "alphas": bounds.alphas, "betas": bounds.betas, "source": bounds.source,
             "k_chosen_by": bounds.details.get("k_chosen_by"), "gmm": bounds.details.get("gmm")}
    fit = gmm.to_dict()
    fit["units"] = "data units (1/m), the trained model's attenuation at the voxel centres after a bilateral filter"
    bounds = BoundsResult(alphas, betas, K, f"gmm ({config.bounds_method}) on the trained volume after a bilateral filter",
                          bounds.prior_wall_time_s,
                          {**bounds.details, "k_chosen_by": f"{gmm.k_rule_used_} on the trained volume after a bilateral filter "
                           f"(more materials than the start's {start['K']})", "gmm": fit, "materials_refit": found,
                           "start_bounds": start})
    write_json(Path(run_dir) / "bounds.json", bounds.to_json())
    config = trainer.config  # the run's, with the new K (Trainer.refit_materials)
    save_run_config(run_dir, config)
    gmm.plot(Path(run_dir) / "figures" / "gmm_bounds_trained.png",
             title=f"{scene.name}: attenuation bounds found again (the trained volume after a bilateral filter), K = {K}")
    say(f"materials: K = {K} written into the model in {found['seconds']:.0f} s", markup=False)
    return config, bounds


def refit_bounds(bounds: BoundsResult, run_dir: Path, method: str) -> BoundsResult:
    """``bounds`` (a resumed run's ``bounds.json``), or where the run's newest checkpoint holds a
    model with the materials found again on the trained volume and the run stopped before
    ``bounds.json`` said so (``materials_stage`` writes the checkpoint first), those bounds,
    written into ``bounds.json``: the model is then rebuilt with the checkpoint's K."""
    from .checkpoint import CheckpointError, list_checkpoints, load_latest_checkpoint

    folder = Path(run_dir) / "checkpoints"
    if not list_checkpoints(folder):
        return bounds
    try:
        state, _, _ = load_latest_checkpoint(folder, method=method, map_location="cpu")
    except CheckpointError:
        return bounds  # the trainer says why when it resumes
    found = (state.get("extra") or {}).get("materials_refit")
    if not found or not found.get("refit") or int(found["K"]) == bounds.K:
        return bounds
    b = [float(v) for v in found["boundaries"]]
    refit = BoundsResult([hi - lo for lo, hi in zip(b, b[1:])], b[:-1], int(found["K"]),
                         "the materials found again on the trained volume (from the checkpoint)", bounds.prior_wall_time_s,
                         {**bounds.details, "materials_refit": found,
                          "start_bounds": {"K": bounds.K, "alphas": bounds.alphas, "betas": bounds.betas, "source": bounds.source}})
    write_json(Path(run_dir) / "bounds.json", refit.to_json())
    say(f"bounds: the run stopped after the materials were found again (K = {refit.K}) and before bounds.json said so; "
        "taken from the checkpoint", markup=False)
    return refit
