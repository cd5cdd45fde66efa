"""The bounds of a neural run with surfaces (SPEC §4): prior or classical start -> GMM -> bounds.

* :func:`estimate_bounds` ``(config, scene, run_dir, device) -> BoundsResult``: from
  ``--bounds FILE``, ``model.alphas/betas``, the NeAS wide defaults, or automatically:
  the GMM (``bounds.GMMBounds``) fitted to the voxel values of the bounds volume, which
  is a trained NeAS-1M prior (the paper; :func:`run_prior`) or, where the procedure has a
  classical start (``stages.classical_start``), that reconstruction. K by the run's K rule unless
  given. Writes the GMM figure; the caller keeps the result as ``bounds.json``.
* :func:`run_prior`: trains (or reuses) the NeAS-1M prior in a run folder of its own,
  ``DIR/<scene>/neas-1m-prior/<key>/``, keyed on the training data, views, preset, seed
  and the prior's settings; its attenuation at the voxel centres is kept as ``volume.npy``.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

import numpy as np

from .. import registry
from ..config import to_dict
from ..console import say
from ..errors import ConfigError
from ..model import build_component
from .evaluate import sample_volume
from .run_dir import safe_name, write_json

PRIOR_METHOD = "neas-1m"
PRIOR_FOLDER = "neas-1m-prior"
# The peaks rule's fallback (a histogram with fewer than two peaks: a noisy or textured volume): the
# mixtures are fitted to the volume after a bilateral filter of this width (voxels) and range (a
# fraction of the volume's 99.5th percentile), which flattens the noise inside each material into a
# plateau and keeps the edges of more contrast than the range.
FALLBACK_SIGMA = 3.0
FALLBACK_RANGE = 0.1


def histogram_smoothing(volume) -> np.ndarray:
    """[nx, ny, nz] (numpy or torch, data units) -> float32 numpy [nx, ny, nz]: the volume after
    ``denoise.bilateral`` with ``FALLBACK_SIGMA`` voxels and a range of ``FALLBACK_RANGE`` times its
    99.5th percentile, for the bounds' histogram only (the warm start and the anchor keep the volume)."""
    import torch

    from ..stages.denoise import bilateral

    v = volume.detach().float().cpu() if isinstance(volume, torch.Tensor) else torch.from_numpy(np.asarray(volume, dtype=np.float32))
    top = float(np.percentile(v.numpy(), 99.5))
    return bilateral(v, FALLBACK_SIGMA, FALLBACK_RANGE * top).numpy()


def run_mixtures(config, *, K: Optional[int] = None, k_rule: Optional[str] = None):
    """An unfitted ``GMMBounds`` with the run's settings (seed, method, K range, width floor,
    starts); ``K`` fixes the count, ``k_rule`` replaces ``config.bounds_k_rule``."""
    from ..bounds import GMMBounds

    return GMMBounds(n_components=K, random_state=int(config.seed), method=config.bounds_method,
                     max_components=int(config.bounds_max_materials), k_rule=k_rule or config.bounds_k_rule,
                     min_std=float(config.bounds_min_std), n_init=int(config.bounds_gmm_restarts),
                     upper_percentile=float(config.bounds_upper_percentile), upper_factor=float(config.bounds_upper_factor),
                     cover_percentile=float(config.bounds_cover_percentile or 0.0))


@dataclass
class BoundsResult:
    """Attenuation bounds per material (data units, 1/m) and where they came from.

    Attributes:
        alphas, betas: length K each.
        K: number of materials.
        source: one line (``gmm (gmm) on the FDK``, ``file b.json``, ...).
        prior_wall_time_s: seconds spent training the prior (0 when none or reused).
        details: the rest of ``bounds.json`` (the GMM fit, warnings, which volume, ...).
    """

    alphas: list[float]
    betas: list[float]
    K: int
    source: str
    prior_wall_time_s: float = 0.0
    details: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict:
        return {"alphas": [float(a) for a in self.alphas], "betas": [float(b) for b in self.betas], "K": int(self.K),
                "source": self.source, **self.details, "prior_wall_time_s": float(self.prior_wall_time_s)}

    @classmethod
    def from_json(cls, data: dict) -> "BoundsResult":
        rest = {k: v for k, v in data.items() if k not in ("alphas", "betas", "K", "source", "prior_wall_time_s")}
        return cls(list(data["alphas"]), list(data["betas"]), int(data["K"]), str(data.get("source", "")),
                   float(data.get("prior_wall_time_s", 0.0)), rest)


@dataclass
class PriorResult:
    """The NeAS-1M prior: its volume ``[nx, ny, nz]`` (data units), folder, training seconds, reused?"""

    volume: np.ndarray
    folder: Path
    seconds: float
    reused: bool


def scene_fingerprint(scene) -> str:
    """A hash of what training sees: geometry, training angles and projections, and the held-out angles."""
    h = hashlib.sha256()
    h.update(json.dumps(scene.geometry.to_mm(), sort_keys=True, default=str).encode())
    for arr in (scene.train.angles, scene.train.projections, scene.val.angles):
        a = np.ascontiguousarray(np.asarray(arr, dtype=np.float32))
        h.update(str(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def prior_config(config):
    """The resolved NeAS-1M prior config for a run: the method's NeAS-1M settings with the run's
    resolved encoding, attenuation width (the options its network takes), samples, rays and schedule
    (``prior_epochs``)."""
    base = registry.load("methods", PRIOR_METHOD).config.model
    own = {f.name for f in dataclasses.fields(build_component("attenuations", base.attenuation))}
    width = {k: v for k, v in (config.model.attenuation_options or {}).items() if k in own}
    model = dataclasses.replace(
        config.model,
        field=base.field, field_options=dict(base.field_options), attenuation=base.attenuation,
        attenuation_options={**base.attenuation_options, **width},
        selector=base.selector, selector_options=dict(base.selector_options), num_materials=1,
        floater=False, alphas=None, betas=None,
    )
    trainer = dataclasses.replace(config.trainer, epochs=config.trainer.prior_epochs)
    return dataclasses.replace(config, method=PRIOR_METHOD, num_materials=1, bounds=None, bounds_source="wide", resume=None,
                               model=model, trainer=trainer, stages=dataclasses.replace(config.stages, **{
                                   f.name: None for f in dataclasses.fields(config.stages) if f.name != "plugins"}),
                               skip_stages=(), add_stages=())


def prior_key(prior_cfg, scene) -> str:
    payload = {
        "scene": scene_fingerprint(scene),
        "views": prior_cfg.views,
        "preset": prior_cfg.preset,
        "seed": prior_cfg.seed,
        "model": to_dict(prior_cfg.model),
        "datamanager": to_dict(prior_cfg.datamanager),
        "trainer": to_dict(prior_cfg.trainer),
    }
    return hashlib.sha256(json.dumps(payload, sort_keys=True, default=str).encode()).hexdigest()[:16]


def run_prior(config, scene, device, loss_scale: float = 1.0) -> PriorResult:
    """Train (or reuse) the NeAS-1M prior of a run (its losses in the run's ``loss_scale``)."""
    from ..console import console
    from .figures import plot_loss_curves
    from .trainer import Trainer

    pcfg = prior_config(config)
    key = prior_key(pcfg, scene)
    folder = Path(config.output_dir) / safe_name(scene.name) / PRIOR_FOLDER / key
    vol_path = folder / "volume.npy"
    if config.reuse_prior and (folder / "metrics.json").is_file() and vol_path.is_file():
        try:
            volume = np.load(vol_path, allow_pickle=False)
            if tuple(volume.shape) == tuple(scene.geometry.n_voxel):
                say(f"prior: reusing the NeAS-1M prior already trained for this scene, views, preset and seed: {folder}")
                return PriorResult(volume, folder, 0.0, True)
        except (OSError, ValueError):
            pass
    if not config.reuse_prior and folder.exists():
        import shutil

        shutil.rmtree(folder / "checkpoints", ignore_errors=True)
        for name in ("metrics.json", "volume.npy"):
            (folder / name).unlink(missing_ok=True)
    for sub in ("checkpoints", "figures"):
        (folder / sub).mkdir(parents=True, exist_ok=True)
    write_json(folder / "config.json", to_dict(pcfg))
    say(f"prior: training the NeAS-1M prior for the GMM bounds in {folder}")
    trainer = Trainer(pcfg, scene, folder, epochs=pcfg.trainer.epochs, device=device, label="prior", console=console,
                      loss_scale=loss_scale)
    path = trainer.resume()
    if path is None and trainer.model.occupancy is not None:
        from .visual_hull import set_visual_hull

        set_visual_hull(trainer.model, scene, "prior", say=say)
    if path is not None:
        say(f"prior: resuming from {path} ({'complete' if trainer.complete else f'step {trainer.step}/{trainer.total_steps}'})")
    say(f"prior: {trainer.epochs} epochs x {trainer.steps_per_epoch} steps, {trainer.model.num_parameters():,} parameters")
    trainer.train()
    volume = sample_volume(trainer.model, scene.geometry, device=device)
    np.save(vol_path, volume.astype(np.float32))
    plot_loss_curves(trainer.loss_history(), folder / "figures" / "loss_curves.png", title="NeAS-1M prior")
    metrics = {"method": PRIOR_METHOD, "role": "prior for automatic bounds", "steps": trainer.step,
               "wall_time_s": trainer.wall_time_s, "parameters": trainer.model.num_parameters(), "preset": pcfg.preset,
               "scene_source": scene.source, "key": key}
    if scene.image is not None:
        from ..evaluation.metrics import volume_metrics

        metrics.update(volume_metrics(volume, np.asarray(scene.image, dtype=np.float32), ssim=False))
    write_json(folder / "metrics.json", metrics)
    return PriorResult(volume, folder, trainer.wall_time_s, False)


def _line_integral_check(gmm, scene, what: str) -> float:
    """The largest measured line integral needs at least ``p_max / (longest chord)`` 1/m
    somewhere; warn (in ``gmm.warnings_``) when the upper bound cannot reach it. Returns that floor."""
    hx, hy, hz = scene.geometry.volume_half_size
    chord_m = 2.0 * float(np.sqrt(hx * hx + hy * hy + hz * hz)) / float(scene.geometry.scale)
    mu_needed = float(np.max(np.asarray(scene.train.projections))) / chord_m
    if float(gmm.boundaries_[-1]) < mu_needed:
        gmm.warnings_.append(
            f"the upper bound b_K = {float(gmm.boundaries_[-1]):.4g} 1/m cannot explain the largest measured line integral "
            f"(it needs at least {mu_needed:.4g} 1/m along the longest chord): the {what} volume looks too weak; "
            + ("train the prior longer (--trainer.prior-epochs) or give --bounds" if what == "NeAS-1M prior"
               else "give --bounds or use --skip-stages classical-start (the bounds then come from a NeAS-1M prior)"))
    return mu_needed


def at_noise_k_rule(config) -> Optional[str]:
    """The K rule for a classical start that fits the training views to their noise
    (``config.bounds_at_noise_k_rule``), or None where the run's one rule decides: no such rule, the
    same rule as ``bounds_k_rule``, or K given (``num_materials``)."""
    rule = config.bounds_at_noise_k_rule
    return None if rule in (None, config.bounds_k_rule) or config.num_materials is not None else rule


def estimate_bounds(config, scene, run_dir: Path, device, start: Optional[tuple] = None, loss_scale: float = 1.0,
                    start_at_noise: bool = False) -> BoundsResult:
    """Bounds for a surface method (module docstring). ``start``: the classical start's ``(volume,
    algorithm)``, whose volume the automatic bounds are estimated on; None: a NeAS-1M prior's.
    ``loss_scale``: the run's loss unit (the wide defaults are NAF-scale: in a scanner's scan, in its unit).
    ``start_at_noise``: the start fits the training views to their noise (``classical_start.start_fit``);
    then ``config.bounds_at_noise_k_rule``, where set and not ``bounds_k_rule`` itself, picks K on the start after
    :func:`histogram_smoothing` (``details["at_noise_rule"]``)."""
    from ..bounds import load_bounds

    K = config.num_materials
    if config.bounds is not None:
        b = load_bounds(config.bounds)
        if K is not None and b.K != K:
            raise ConfigError(f"--bounds {config.bounds} has {b.K} materials but this {config.method} run trains K = {K}; "
                              f"give a bounds file with {K} materials, or --num-materials {b.K} (a K-material method such as "
                              "k-neas; without --num-materials it takes K from the file)")
        say(f"bounds: from {config.bounds} (K = {b.K})")
        return BoundsResult(list(b.alphas), list(b.betas), b.K, f"file {config.bounds}")
    m = config.model
    if m.alphas is not None and m.betas is not None:
        say(f"bounds: given on the command line (K = {len(m.alphas)})")
        return BoundsResult(list(m.alphas), list(m.betas), len(m.alphas), "given (model.alphas/betas)")
    if config.bounds_source == "wide":
        from ..fields.attenuation import default_bounds

        unit = float(loss_scale)
        a, b = ([unit * v for v in values] for values in default_bounds(int(m.num_materials)))
        say("bounds: NeAS wide defaults" + (f", times the scan's unit {unit:.4g} /m" if unit != 1.0 else ""))
        return BoundsResult(a, b, int(m.num_materials), "wide (NeAS defaults)")
    # automatic: GMM (SPEC §4) on the prior model's volume (the paper) or on a classical reconstruction
    prior: Optional[PriorResult] = None
    if start is None:
        prior = run_prior(config, scene, device, loss_scale=loss_scale)
        volume, what = prior.volume, "NeAS-1M prior"
    else:
        volume, what = start[0], start[1].upper()
    t0 = time.perf_counter()
    noisy_rule = at_noise_k_rule(config) if start is not None and start_at_noise else None
    k_rule = noisy_rule or config.bounds_k_rule
    if noisy_rule is not None:
        say(f"bounds: the {what} volume fits the views to their noise, so its histogram's peaks are smeared: Gaussian mixtures "
            f"(K = 1..{config.bounds_max_materials} by {'BIC' if noisy_rule == 'bic' else noisy_rule}, {config.bounds_gmm_restarts} start(s) "
            f"each) fitted to it after an edge-preserving filter (bilateral, {FALLBACK_SIGMA:g} voxels, range {FALLBACK_RANGE:g} x its "
            "99.5th percentile; --bounds-at-noise-k-rule peaks keeps the peaks rule)", markup=False)
    elif config.bounds_k_rule == "peaks" and K is None:
        say(f"bounds: one material per peak of the {what} voxel values' histogram (Gaussian mixtures, K = 1..{config.bounds_max_materials}, "
            "if it has fewer than two)", markup=False)
    else:
        say(f"bounds: fitting Gaussian mixtures ({'K = ' + str(K) if K is not None else f'K = 1..{config.bounds_max_materials}'}, "
            f"{config.bounds_gmm_restarts} start(s) each) to the {what} voxel values", markup=False)
    smoothed = []

    def fallback_values():
        smoothed.append(histogram_smoothing(volume))
        return smoothed[0]

    def fallback():  # the peaks rule found fewer than two peaks (a noisy or textured volume)
        say(f"bounds: the {what} voxel values' histogram has fewer than two peaks; the mixtures are fitted to the volume after "
            f"an edge-preserving filter (bilateral, {FALLBACK_SIGMA:g} voxels, range {FALLBACK_RANGE:g} x its 99.5th percentile)",
            markup=False)
        return fallback_values()

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # the mixtures' remarks: said below as "bounds warning:" lines, once
        if noisy_rule is not None:
            values = fallback_values()
            gmm = run_mixtures(config, K=K, k_rule=noisy_rule).fit(values, fallback_name=f"the {what} after a bilateral filter")
        else:
            gmm = run_mixtures(config, K=K).fit(volume, fallback=fallback, fallback_name=f"the {what} after a bilateral filter")
    fit = gmm.to_dict()
    fit["units"] = f"data units (1/m), the {what} attenuation at the voxel centres"
    rule = "BIC" if k_rule == "bic" else "lowest BIC with every boundary a density valley"
    if noisy_rule is not None:
        rule += " on the start after the filter, the start being at the views' noise"
    elif k_rule == "peaks":
        peaks = f"histogram peaks at {', '.join(f'{v:.4g}' for v in gmm.peaks_) or 'none'}"
        rule = peaks + ("" if gmm.gmm_ is None else f"; fewer than two, so the {rule}" + (" after the filter" if smoothed else ""))
    chosen = f"K = {gmm.n_components_} " + ("(given)" if K is not None else f"({rule}" + ("" if gmm.gmm_ is None else ": " + ", ".join(
        f"K={k}: {v:.4g}" + ("" if gmm.placeable_.get(k, True) else " no valley") for k, v in sorted(gmm.bic_.items()))) + ")")
    how = "histogram peaks" if gmm.gmm_ is None else f"GMM ({config.bounds_method})"
    gmm.plot(Path(run_dir) / "figures" / "gmm_bounds.png", title=f"{scene.name}: attenuation bounds ({how}"
             + (", the volume after a bilateral filter" if smoothed else "") + f"), K = {gmm.n_components_}")
    mu_needed = _line_integral_check(gmm, scene, what)
    for w in gmm.warnings_:
        say(f"[yellow]bounds warning:[/] {w}")
    say(f"bounds: {how} on {gmm.n_kept_:,} {what} voxel values in {time.perf_counter() - t0:.0f} s, {chosen}; "
        f"alphas ({', '.join(f'{v:.4g}' for v in gmm.alphas_)}) betas ({', '.join(f'{v:.4g}' for v in gmm.betas_)}) (data units)", markup=False)
    details = {"volume": "prior" if start is None else start[1], "k_chosen_by": "given" if K is not None else gmm.k_rule_used_,
               "smoothed": {"filter": "bilateral", "sigma_voxels": FALLBACK_SIGMA, "range_fraction": FALLBACK_RANGE} if smoothed else None,
               "at_noise_rule": noisy_rule,
               "prior_run": None if prior is None else str(prior.folder), "prior_reused": False if prior is None else prior.reused,
               "warnings": list(gmm.warnings_), "mu_needed_lower_bound": mu_needed, "fit_time_s": time.perf_counter() - t0, "gmm": fit}
    if gmm.gmm_ is None:  # the peaks rule: material 1's labels start half way from air to its level
        details["first_label_threshold"] = 0.5 * float(gmm.means_[0])
    return BoundsResult([float(v) for v in gmm.alphas_], [float(v) for v in gmm.betas_], int(gmm.n_components_),
                        f"{how.lower()} on the {what}",
                        0.0 if prior is None else prior.seconds, details)
