"""The materials refit (not in the paper): the materials of a noisy scan, found again on its trained
volume (after the correction and the smoothing).

Where the bounds came from the peaks rule's fallback (``bounds.json`` ``smoothed``: the classical
start's histogram had fewer than two peaks, as a noisy scan's has), they are mixtures fitted to a
noisy volume, and the noise hides the materials of little contrast or few voxels. After training
and the SURE smoothing the model's volume is cleaner than that start by 3-4 dB. ``materials_stage``
fits the same mixtures (``bic-valleys``, the run's K range and starts) to it after the same
bilateral filter; where they find more materials than the start did, the model is replaced by a
fresh one with those bounds, fitted to the trained volume as the warm start fits
(:func:`refit_materials`, ``--stages.materials-refit.steps`` steps), and ``bounds.json``,
``config.json`` and the checkpoint follow. Where they find as many or fewer (a textured scan, whose
texture the filter smooths into one plateau), the model is kept. What was found is kept in the
checkpoint, so a resumed run does not redo it.
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from ..config import at_least
from ..console import say
from ..engine.bounds_stage import FALLBACK_RANGE, FALLBACK_SIGMA, BoundsResult, histogram_smoothing, run_mixtures
from ..engine.run_dir import save_run_config, write_json
from .base import RunState, Stage, StageConfig
from .volume_fit import fit_whole_volume

REFIT_SEED_OFFSET = 15485863  # the materials refit's initialisation and draws: the run's seed plus this
LEGACY_KEY = "materials_refit"  # where checkpoints written before the stages kept the record


def refits(bounds) -> bool:
    """Whether the materials refit runs on a run with these bounds (a ``BoundsResult`` or None): where
    they came from the peaks rule's fallback (``details["smoothed"]``), not from the at-noise rule, whose
    mixtures already counted the filtered start's materials."""
    return bounds is not None and bool(bounds.details.get("smoothed")) and not bounds.details.get("at_noise_rule")


def refit_materials(trainer, volume: np.ndarray, alphas: Sequence[float], betas: Sequence[float], steps: int,
                    points_per_step: int, occupancy_weight: float, what: str = "trained") -> None:
    """Replace the trainer's model by a fresh one with ``len(alphas)`` materials and these bounds (data
    units; the trainer's ``config.num_materials`` follows), the old one's empty-space and voxel grids, and
    fit it to ``volume`` [nx, ny, nz] (data units) as the warm start fits (``steps`` steps on
    ``points_per_step`` voxel centres, the occupancy cross-entropy at ``occupancy_weight``)."""
    from ..model import CTModel

    old = trainer.model
    K = len(alphas)
    model_config = dataclasses.replace(trainer.config.model, num_materials=K)
    config = dataclasses.replace(trainer.config, num_materials=K, model=model_config)
    torch.manual_seed(int(config.seed) + REFIT_SEED_OFFSET)
    model = CTModel(model_config, scale=trainer.scene.geometry.scale, device=trainer.device).to(trainer.device)
    model.set_bounds(alphas, betas)
    model.loss_scale = old.loss_scale
    if old.occupancy is not None:
        model.set_occupancy(old.occupancy, old.occupancy_box[0].tolist(), old.occupancy_box[1].tolist())
    if model.quadrature == "voxel-planes":
        model.set_voxel_grid(old.voxel_count.tolist(), old.voxel_box[0].tolist(), old.voxel_box[1].tolist())
    trainer.replace_model(model, config)
    fit_whole_volume(trainer, volume, what, steps, points_per_step, occupancy_weight, REFIT_SEED_OFFSET,
                     f"{trainer.label} materials fit", f"fit of {K} materials to the {what} volume",
                     "use --skip-stages materials-refit")
    trainer.model.eval()


@dataclass
class MaterialsRefitConfig(StageConfig):
    """Where the bounds came from the peaks rule's fallback (the start's histogram had fewer than two
    peaks: a noisy scan), the mixtures are fitted again to the trained volume after the same bilateral
    filter; if they find more materials than the start did, the model is replaced by a fresh one with
    those bounds, fitted to the trained volume as the warm start fits.

    Attributes:
        steps: Adam steps of the new model's fit.
        points: voxel centres per step of the fit.
        occupancy: weight of the fit's per-material occupancy cross-entropy.
    """

    _target = "kneas_method.stages.materials_refit:MaterialsRefit"
    name = "materials-refit"
    phase = "after-training"
    steps: int = field(default=1500, metadata=at_least(1, whole=True))
    points: int = field(default=16384, metadata=at_least(1, whole=True))
    occupancy: float = field(default=0.01, metadata=at_least(0))

    def describe(self) -> str:
        return "materials refit: on a noisy scan, the materials found again on the trained volume (more of them: a new model)"


class MaterialsRefit(Stage):
    def run(self, state: RunState) -> None:
        trainer, bounds, config, c = state.trainer, state.bounds, state.config, self.config
        if not refits(bounds):
            return
        if state.records.get(self.name) is not None:
            say(f"materials: already found again on the trained volume for this run (K = {state.records[self.name]['K']})")
            return
        started = time.perf_counter()
        from ..engine.evaluate import sample_volume

        volume = sample_volume(trainer.model, state.scene.geometry, device=trainer.device)  # the whole grid, afresh
        say(f"materials: the mixtures fitted again to the trained volume after the start's filter (bilateral, {FALLBACK_SIGMA:g} voxels, "
            f"range {FALLBACK_RANGE:g} x its 99.5th percentile; --skip-stages materials-refit keeps the start's K = {bounds.K})",
            markup=False)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the mixtures' remarks are the bounds stage's to make
            gmm = run_mixtures(config, k_rule="bic-valleys").fit(histogram_smoothing(volume))
        K = int(gmm.n_components_)
        found = {"K": K, "start_K": int(bounds.K), "boundaries": [float(b) for b in gmm.boundaries_], "refit": K > bounds.K,
                 "steps": int(c.steps) if K > bounds.K else 0}
        if K <= bounds.K:
            found["seconds"] = time.perf_counter() - started
            say(f"materials: the trained volume shows K = {K}, not more than the start's {bounds.K}: the model is kept "
                f"({found['seconds']:.0f} s)")
            state.records[self.name] = found
            trainer.save(complete=True)
            return
        alphas, betas = [float(a) for a in gmm.alphas_], [float(b) for b in gmm.betas_]
        say(f"materials: the trained volume shows K = {K} (the start {bounds.K}), boundaries "
            f"{', '.join(f'{b:.4g}' for b in gmm.boundaries_)}; a model with those bounds fitted to it for {c.steps} steps", markup=False)
        refit_materials(trainer, volume, alphas, betas, int(c.steps), int(c.points), float(c.occupancy))
        state.forget_volume()
        found["seconds"] = time.perf_counter() - started
        state.records[self.name] = found
        trainer.save(complete=True)  # the new model's checkpoint first: config.json and bounds.json then name its K
        start = {"K": bounds.K, "alphas": bounds.alphas, "betas": bounds.betas, "source": bounds.source,
                 "k_chosen_by": bounds.details.get("k_chosen_by"), "gmm": bounds.details.get("gmm")}
        fit = gmm.to_dict()
        fit["units"] = "data units (1/m), the trained model's attenuation at the voxel centres after a bilateral filter"
        state.bounds = BoundsResult(alphas, betas, K, f"gmm ({config.bounds_method}) on the trained volume after a bilateral filter",
                                    bounds.prior_wall_time_s,
                                    {**bounds.details, "k_chosen_by": f"{gmm.k_rule_used_} on the trained volume after a bilateral filter "
                                     f"(more materials than the start's {start['K']})", "gmm": fit, "materials_refit": found,
                                     "start_bounds": start})
        write_json(Path(state.run_dir) / "bounds.json", state.bounds.to_json())
        state.config = trainer.config  # the run's, with the new K
        save_run_config(state.run_dir, state.config)
        gmm.plot(Path(state.run_dir) / "figures" / "gmm_bounds_trained.png",
                 title=f"{state.scene.name}: attenuation bounds found again (the trained volume after a bilateral filter), K = {K}")
        say(f"materials: K = {K} written into the model in {found['seconds']:.0f} s", markup=False)


def refit_bounds(bounds: BoundsResult, run_dir: Path, method: str) -> BoundsResult:
    """``bounds`` (a resumed run's ``bounds.json``), or where the run's newest checkpoint holds a
    model with the materials found again on the trained volume and the run stopped before
    ``bounds.json`` said so (``materials_stage`` writes the checkpoint first), those bounds,
    written into ``bounds.json``: the model is then rebuilt with the checkpoint's K."""
    from ..engine.checkpoint import CheckpointError, list_checkpoints, load_latest_checkpoint

    folder = Path(run_dir) / "checkpoints"
    if not list_checkpoints(folder):
        return bounds
    try:
        state, _, _ = load_latest_checkpoint(folder, method=method, map_location="cpu")
    except CheckpointError:
        return bounds  # the trainer says why when it resumes
    extra = state.get("extra") or {}
    found = (extra.get("stages") or {}).get(MaterialsRefitConfig.name) or extra.get(LEGACY_KEY)
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
