"""``kneas-train``'s training pipeline: scene -> (prior -> bounds) -> model -> evaluation -> run folder.

Stages of a run (``train(config)``):

1. **scene**: ``resolve_scene(config.scene)`` (a public ``data/<name>_50.pickle``
   wins over the built-in phantom), then ``subsample_views(config.views)``; the
   source is printed and recorded as ``scene_source``.
2. **prior** (methods with automatic bounds): the single-material NeAS-1M prior
   is trained (``trainer.prior_epochs``) in a run folder of its own,
   ``DIR/<scene>/neas-1m-prior/<key>/``, keyed on the training data (geometry,
   angles, projections), views, preset, seed and the prior's settings, and
   reused by later runs with the same key. Its attenuation at the voxel centres
   (data units) is kept there as ``volume.npy``.
3. **bounds** (SPEC §4): ``GMMBounds`` on the prior's voxel values; K by BIC
   unless ``--num-materials`` (neas-2m: K = 2). ``--bounds FILE`` or
   ``model.alphas/betas`` override the estimate; ``bounds_source wide`` uses the
   NeAS defaults. Written to ``bounds.json`` (data units) with the GMM fit figure.
4. **model**: the K-material (or NAF / NeAS-1M) model, :class:`.trainer.Trainer`.
5. **evaluation**: :func:`.evaluate.evaluate_model` on all held-out views and
   the voxel centres; ``metrics.json``, figures, a summary table.

``fdk`` runs replace 2–4 by ``fdk_reconstruct`` and save ``volume.npy``.

Resuming (``--resume RUN_DIR``): the run's ``config.json`` is reloaded; a
prior/bounds stage is done when ``bounds.json`` exists, the model stage when
its newest checkpoint says ``complete``, the run when ``metrics.json`` exists.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import time
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from .. import presets, registry
from ..cli.common import EXIT_INTERRUPTED, console
from ..config import to_dict, update_from_dict
from ..errors import ConfigError, KneasError
from .evaluate import evaluate_volume, model_metrics_from_arrays, render_views, sample_volume
from .progress import stage_progress, summary_table
from .run_dir import create_run_dir, read_json, write_json
from .trainer import StageInterrupted, Trainer

PRIOR_METHOD = "neas-1m"
PRIOR_FOLDER = "neas-1m-prior"


# ------------------------------------------------------------------ helpers
def say(msg: str, markup: bool = True) -> None:
    """One message line, never wrapped (paths stay copyable and greppable)."""
    console.print(msg, soft_wrap=True, markup=markup)


def _tensorboard(run_dir: Path):
    """A SummaryWriter in ``run_dir/tensorboard`` when tensorboard is installed, else None."""
    try:
        from torch.utils.tensorboard import SummaryWriter  # needs the tensorboard package
    except Exception:
        return None
    try:
        return SummaryWriter(str(run_dir / "tensorboard"))
    except Exception:
        return None


def load_scene(config, *, quiet: bool = False):
    """The run's scene (views subsampled) as ``kneas-train`` resolves it."""
    from ..data.scenes import resolve_scene

    def note(msg):
        if not quiet:
            say(f"  {msg}")

    scene = resolve_scene(config.scene, data_dir=config.data_dir, progress=note)
    full_train = len(scene.train)
    scene = scene.subsample_views(config.views)
    if not quiet:
        say(f"scene: {scene.name} from {scene.source}; {len(scene.train)} of {full_train} training views, "
                      f"{len(scene.val)} held-out views, volume {tuple(scene.geometry.n_voxel)}, detector {tuple(scene.geometry.n_detector)}")
    return scene


def scene_fingerprint(scene) -> str:
    """A hash of what training sees: geometry, training angles and projections, and the held-out angles."""
    h = hashlib.sha256()
    h.update(json.dumps(scene.geometry.to_mm(), sort_keys=True, default=str).encode())
    for arr in (scene.train.angles, scene.train.projections, scene.val.angles):
        a = np.ascontiguousarray(np.asarray(arr, dtype=np.float32))
        h.update(str(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def method_defaults(method: str):
    try:
        return registry.load("methods", method).config
    except Exception as exc:  # not installed
        raise ConfigError(f"method {method!r} is not installed ({exc}); available: {', '.join(registry.names('methods'))}") from None


def config_from_json(data: dict):
    """A resolved TrainConfig from a run's ``config.json``."""
    base = dataclasses.replace(method_defaults(data["method"]), method=data["method"])
    return update_from_dict(base, data)


def prior_config(config):
    """The resolved NeAS-1M prior config for a run: the method's NeAS-1M settings with
    the run's preset-resolved encoding, samples, rays and schedule (``prior_epochs``)."""
    base = method_defaults(PRIOR_METHOD).model
    model = dataclasses.replace(
        config.model,
        field=base.field, field_options=dict(base.field_options), attenuation=base.attenuation, attenuation_options=dict(base.attenuation_options),
        selector=base.selector, selector_options=dict(base.selector_options), num_materials=1,
        floater=False, alphas=None, betas=None,
    )
    trainer = dataclasses.replace(config.trainer, epochs=config.trainer.prior_epochs)
    return dataclasses.replace(
        config, method=PRIOR_METHOD, num_materials=1, bounds=None, bounds_source="wide", resume=None,
        reconstructor="neural", model=model, trainer=trainer,
    )


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


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in str(name)) or "scene"


def _print_interrupted(exc: StageInterrupted, run_dir: Path) -> int:
    where = exc.checkpoint or "no checkpoint (none written yet)"
    say(f"[yellow]interrupted at step {exc.step}[/]: checkpoint {where}")
    say(f"resume with: kneas-train --resume {run_dir}")
    return EXIT_INTERRUPTED


# -------------------------------------------------------------------- stages
def _train_stage(config, scene, run_dir: Path, *, epochs: int, device, bounds, label: str, tb=None, warm_volume=None) -> Trainer:
    """Build the stage's Trainer, resume it if it has checkpoints, else warm-start it from
    ``warm_volume`` when given (``trainer.warm_start_steps`` steps), and train it."""
    trainer = Trainer(config, scene, run_dir, epochs=epochs, device=device, bounds=bounds, label=label, console=console,
                      tb=tb, tb_prefix=f"{label}/")
    path = trainer.resume()
    if path is not None:
        state = "complete" if trainer.complete else f"step {trainer.step}/{trainer.total_steps}"
        say(f"{label}: resuming from {path} ({state})")
    elif warm_volume is not None and int(config.trainer.warm_start_steps or 0) > 0:
        steps = int(config.trainer.warm_start_steps)
        say(f"{label}: warm start: fitting the model to the FDK reconstruction for {steps} steps "
            f"({config.trainer.warm_start_points:,} voxel centres each; --trainer.warm-start none trains from the initialisation, as the paper)")
        seconds = trainer.warm_start(warm_volume, steps, int(config.trainer.warm_start_points),
                                     occupancy_weight=float(config.trainer.warm_start_occupancy))
        say(f"{label}: warm start done in {seconds:.1f} s")
    say(f"{label}: {trainer.epochs} epochs x {trainer.steps_per_epoch} steps, {trainer.model.num_parameters():,} parameters")
    trainer.train()
    return trainer


def fdk_volume(config, scene, run_dir: Path, device) -> tuple[np.ndarray, float]:
    """The FDK reconstruction of the run's training views (data units), computed once per
    run and kept as ``run_dir/fdk_volume.npy`` (reused on resume). Returns ``(volume, seconds)``."""
    from ..evaluation.fdk import fdk_reconstruct

    path, info_path = run_dir / "fdk_volume.npy", run_dir / "fdk_volume.json"
    if path.is_file() and info_path.is_file():
        try:
            volume = np.load(path, allow_pickle=False)
            if tuple(volume.shape) == tuple(scene.geometry.n_voxel):
                return volume, float(read_json(info_path, "FDK volume info").get("seconds", 0.0))
        except (OSError, ValueError, KneasError):
            pass
    t0 = time.perf_counter()
    say(f"fdk: reconstructing {len(scene.train)} training views (filter {config.fdk_filter}) for the bounds / warm start")
    volume = np.asarray(fdk_reconstruct(scene, filter=config.fdk_filter, device=device), dtype=np.float32)
    from ..atomic import atomic_write

    atomic_write(path, lambda fh: np.save(fh, volume))
    seconds = time.perf_counter() - t0
    write_json(info_path, {"seconds": seconds, "filter": config.fdk_filter, "views": len(scene.train)})
    return volume, seconds


def run_prior(config, scene, device) -> tuple[np.ndarray, Path, float, bool]:
    """Train (or reuse) the NeAS-1M prior; returns ``(volume [nx,ny,nz] data units, folder, wall_time_s, reused)``."""
    pcfg = prior_config(config)
    key = prior_key(pcfg, scene)
    folder = Path(config.output_dir) / _safe(scene.name) / PRIOR_FOLDER / key
    vol_path = folder / "volume.npy"
    if config.reuse_prior and (folder / "metrics.json").is_file() and vol_path.is_file():
        try:
            volume = np.load(vol_path, allow_pickle=False)
            if tuple(volume.shape) == tuple(scene.geometry.n_voxel):
                say(f"prior: reusing the NeAS-1M prior already trained for this scene, views, preset and seed: {folder}")
                return volume, folder, 0.0, True
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
    trainer = _train_stage(pcfg, scene, folder, epochs=pcfg.trainer.epochs, device=device, bounds=None, label="prior")
    volume = sample_volume(trainer.model, scene.geometry, device=device)
    np.save(vol_path, volume.astype(np.float32))
    from .figures import plot_loss_curves

    plot_loss_curves(_loss_history(trainer.history), folder / "figures" / "loss_curves.png", title="NeAS-1M prior")
    metrics = {"method": PRIOR_METHOD, "role": "prior for automatic bounds", "steps": trainer.step,
               "wall_time_s": trainer.wall_time_s, "parameters": trainer.model.num_parameters(), "preset": pcfg.preset,
               "scene_source": scene.source, "key": key}
    if scene.image is not None:
        from ..evaluation.metrics import volume_metrics

        metrics.update(volume_metrics(volume, np.asarray(scene.image, dtype=np.float32), ssim=False))
    write_json(folder / "metrics.json", metrics)
    return volume, folder, trainer.wall_time_s, False


def estimate_bounds(config, scene, run_dir: Path, device) -> tuple[dict, float]:
    """Bounds for an SDF method; writes ``bounds.json`` (and the GMM figure). Returns ``(bounds dict, prior wall time)``."""
    from ..bounds import GMMBounds, load_bounds

    K = config.num_materials
    if config.bounds is not None:
        b = load_bounds(config.bounds)
        if K is not None and b.K != K:
            raise ConfigError(f"--bounds {config.bounds} has {b.K} materials but the run asks for K = {K}; "
                              f"drop --num-materials or use --num-materials {b.K}")
        info = {"alphas": list(b.alphas), "betas": list(b.betas), "K": b.K, "source": f"file {config.bounds}"}
        say(f"bounds: from {config.bounds} (K = {b.K})")
        return info, 0.0
    m = config.model
    if m.alphas is not None and m.betas is not None:
        info = {"alphas": list(m.alphas), "betas": list(m.betas), "K": len(m.alphas), "source": "given (model.alphas/betas)"}
        say(f"bounds: given on the command line (K = {len(m.alphas)})")
        return info, 0.0
    if config.bounds_source == "wide":
        from ..fields.attenuation import default_bounds

        a, b = default_bounds(int(m.num_materials))
        say("bounds: NeAS wide defaults")
        return {"alphas": a, "betas": b, "K": int(m.num_materials), "source": "wide (NeAS defaults)"}, 0.0
    # automatic: GMM (SPEC §4) on the prior model's volume (the paper) or on the FDK reconstruction
    if config.bounds_volume == "fdk":
        volume, _ = fdk_volume(config, scene, run_dir, device)  # its time is reported as fdk_time_s
        prior_time, prior_dir, reused, what = 0.0, None, False, "FDK"
    else:
        volume, prior_dir, prior_time, reused = run_prior(config, scene, device)
        what = "NeAS-1M prior"
    n_comp = K if K is not None else None
    t0 = time.perf_counter()
    gmm = GMMBounds(n_components=n_comp, random_state=int(config.seed), method=config.bounds_method).fit(volume)
    fit = gmm.to_dict()
    fit["units"] = f"data units (1/m), the {what} attenuation at the voxel centres"
    chosen = f"K = {gmm.n_components_} " + ("(given)" if n_comp is not None else "(BIC: " + ", ".join(f"K={k}: {v:.4g}" for k, v in sorted(gmm.bic_.items())) + ")")
    gmm.plot(run_dir / "figures" / "gmm_bounds.png", title=f"{scene.name}: GMM attenuation bounds ({config.bounds_method}), K = {gmm.n_components_}")
    # sanity check: the largest measured line integral needs at least p_max / (longest chord) 1/m somewhere
    hx, hy, hz = scene.geometry.volume_half_size
    chord_m = 2.0 * float(np.sqrt(hx * hx + hy * hy + hz * hz)) / float(scene.geometry.scale)
    mu_needed = float(np.max(np.asarray(scene.train.projections))) / chord_m
    if float(gmm.boundaries_[-1]) < mu_needed:
        gmm.warnings_.append(
            f"the upper bound b_K = {float(gmm.boundaries_[-1]):.4g} 1/m cannot explain the largest measured line integral "
            f"(it needs at least {mu_needed:.4g} 1/m along the longest chord): the {what} volume looks too weak; "
            + ("train the prior longer (--trainer.prior-epochs) or give --bounds" if what != "FDK" else "give --bounds or use --bounds-volume prior"))
    for w in gmm.warnings_:
        say(f"[yellow]bounds warning:[/] {w}")
    say(f"bounds: GMM ({config.bounds_method}) on {gmm.n_kept_:,} {what} voxel values, {chosen}; "
                  f"alphas ({', '.join(f'{v:.4g}' for v in gmm.alphas_)}) betas ({', '.join(f'{v:.4g}' for v in gmm.betas_)}) (data units)", markup=False)
    info = {"alphas": [float(v) for v in gmm.alphas_], "betas": [float(v) for v in gmm.betas_], "K": int(gmm.n_components_),
            "source": f"gmm ({config.bounds_method}) on the {what}", "volume": config.bounds_volume, "k_chosen_by": "given" if n_comp is not None else "bic",
            "prior_run": None if prior_dir is None else str(prior_dir), "prior_reused": reused, "warnings": list(gmm.warnings_), "mu_needed_lower_bound": mu_needed, "fit_time_s": time.perf_counter() - t0, "gmm": fit}
    return info, prior_time


def _loss_history(history: dict) -> dict:
    return {k: [tuple(p) for p in v] for k, v in history.items() if k not in ("lr", "val_psnr2d")}


def _figures(run_dir: Path, scene, proj: np.ndarray, volume: Optional[np.ndarray], title: str, history: Optional[dict] = None):
    from .figures import plot_loss_curves, plot_projection_comparison, plot_slice_comparison

    fig = run_dir / "figures"
    if history:
        plot_loss_curves(_loss_history(history), fig / "loss_curves.png", title=title)
        if history.get("val_psnr2d"):
            _plot_val(history["val_psnr2d"], fig / "validation_psnr2d.png", title)
    plot_projection_comparison(proj[0], np.asarray(scene.val.projections[0]), fig / "projection_val0.png", title=f"{title}: held-out view 0")
    if volume is not None:
        plot_slice_comparison(volume, None if scene.image is None else np.asarray(scene.image), fig / "slices.png", title=f"{title}: volume (data units)")


def _plot_val(points, path, title):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s, v = zip(*points)
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.plot(s, v, "o-")
    ax.set_xlabel("step")
    ax.set_ylabel("validation PSNR2D [dB]")
    ax.set_title(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _evaluate(model, scene, config, device) -> tuple[dict, np.ndarray, Optional[np.ndarray], float]:
    t0 = time.perf_counter()
    nu, nv = scene.geometry.n_detector
    total_rays = len(scene.val) * nu * nv
    with stage_progress(console, unit="rays") as progress:
        task = progress.add_task("evaluation", total=total_rays, info=f"{len(scene.val)} held-out views x {config.model.num_eval_samples} samples")
        proj = render_views(model, scene, scene.val.angles, device=device, chunk=int(config.trainer.eval_chunk or 4096),
                            n_samples=config.model.num_eval_samples, progress=lambda d, t: progress.update(task, completed=d))
        volume = None
        if scene.image is not None:
            vtask = progress.add_task("volume", total=int(np.prod(scene.geometry.n_voxel)), info="attenuation at the voxel centres")
            volume = sample_volume(model, scene.geometry, device=device, progress=lambda d, t: progress.update(vtask, completed=d))
    metrics = model_metrics_from_arrays(proj, scene, volume)
    return metrics, proj, volume, time.perf_counter() - t0


def _finish(run_dir: Path, metrics: dict) -> int:
    write_json(run_dir / "metrics.json", metrics)
    console.print(summary_table(metrics, title=f"{metrics.get('method')} on {metrics.get('scene')}"))
    say(f"run folder: {run_dir}")
    return 0


# ---------------------------------------------------------------------- runs
def _run_fdk(config, scene, run_dir: Path, device) -> int:
    from ..evaluation.fdk import fdk_reconstruct

    t0 = time.perf_counter()
    say(f"fdk: reconstructing from {len(scene.train)} views (filter {config.fdk_filter})")
    volume = fdk_reconstruct(scene, filter=config.fdk_filter, device=device)
    rec_time = time.perf_counter() - t0
    np.save(run_dir / "volume.npy", volume.astype(np.float32))
    t1 = time.perf_counter()
    metrics, (proj, vol) = evaluate_volume(volume, scene, return_arrays=True)
    _figures(run_dir, scene, proj, vol, f"fdk, {scene.name}")
    metrics = {**_headline(metrics), "method": config.method, "scene": scene.name, "views": len(scene.train), "parameters": 0,
               "steps": 0, "wall_time_s": time.perf_counter() - t0, "reconstruct_time_s": rec_time,
               "eval_time_s": time.perf_counter() - t1, "preset": config.preset, "scene_source": scene.source,
               "device": str(device), **_per_view(metrics)}
    return _finish(run_dir, metrics)


def _headline(metrics: dict) -> dict:
    return {k: v for k, v in metrics.items() if not k.endswith("_per_view")}


def _per_view(metrics: dict) -> dict:
    return {k: v for k, v in metrics.items() if k.endswith("_per_view")}


def _run_neural(config, scene, run_dir: Path, device, run_start_wall: float) -> int:
    tb = _tensorboard(run_dir)
    prior_time = fdk_time = 0.0
    bounds = None
    info: dict = {}
    model_cfg = config
    try:
        if config.model.field != "naf":
            bpath = run_dir / "bounds.json"
            if bpath.is_file():
                info = read_json(bpath, "bounds file")
                say(f"bounds: already estimated for this run ({bpath}; K = {info['K']})")
                prior_time = float(info.get("prior_wall_time_s", 0.0))
            else:
                info, prior_time = estimate_bounds(config, scene, run_dir, device)
                info["prior_wall_time_s"] = prior_time
                write_json(bpath, info)
            K = int(info["K"])
            if config.model.selector == "hard" and K != 2:
                raise ConfigError(f"method {config.method!r} uses the hard selector (2 materials) but the bounds have K = {K}; give 2-material bounds")
            model_cfg = dataclasses.replace(config, num_materials=K, model=dataclasses.replace(config.model, num_materials=K))
            write_json(run_dir / "config.json", to_dict(model_cfg))  # the K actually trained
            bounds = (info["alphas"], info["betas"])
        warm = None
        if config.trainer.warm_start == "fdk" or info.get("volume") == "fdk":  # computed once per run, cached in the run folder
            warm, fdk_time = fdk_volume(config, scene, run_dir, device)
            if config.trainer.warm_start != "fdk":
                warm = None
        trainer = _train_stage(model_cfg, scene, run_dir, epochs=model_cfg.trainer.epochs, device=device, bounds=bounds, label="model", tb=tb,
                               warm_volume=warm)
    except StageInterrupted as exc:
        return _print_interrupted(exc, run_dir)
    except KeyboardInterrupt:
        say("[yellow]interrupted[/] outside a training loop")
        say(f"resume with: kneas-train --resume {run_dir}")
        return EXIT_INTERRUPTED
    finally:
        if tb is not None:
            tb.flush()
    try:
        metrics, proj, volume, eval_time = _evaluate(trainer.model, scene, model_cfg, device)
    except KeyboardInterrupt:
        say(f"[yellow]interrupted during the evaluation[/]; training is complete (checkpoint {trainer.last_checkpoint})")
        say(f"resume with: kneas-train --resume {run_dir}")
        return EXIT_INTERRUPTED
    if tb is not None:
        for k in ("psnr2d", "ssim2d", "psnr3d", "ssim3d"):
            if k in metrics:
                tb.add_scalar(f"eval/{k}", metrics[k], trainer.step)
        tb.close()
    _figures(run_dir, scene, proj, volume, f"{config.method}, {scene.name}", trainer.history)
    out = {**_headline(metrics), "method": config.method, "scene": scene.name, "views": len(scene.train),
           "parameters": trainer.model.num_parameters(), "steps": trainer.step, "epochs": trainer.epochs,
           "wall_time_s": trainer.wall_time_s + trainer.warm_start_time_s + prior_time + fdk_time + eval_time,
           "train_time_s": trainer.wall_time_s, "warm_start_time_s": trainer.warm_start_time_s, "warm_start": config.trainer.warm_start,
           "prior_time_s": prior_time, "fdk_time_s": fdk_time, "eval_time_s": eval_time, "preset": config.preset, "scene_source": scene.source,
           "device": str(device), "bad_steps": len(trainer.bad_steps)}
    if trainer.model.has_sdf:
        out["num_materials"] = int(trainer.model.num_materials)
        out["alphas"], out["betas"] = trainer.model.bounds
        out["bounds_source"] = info.get("source")
        if "prior_reused" in info:
            out["prior_reused"] = info["prior_reused"]
            out["prior_run"] = info.get("prior_run")
    out["session_wall_time_s"] = time.perf_counter() - run_start_wall
    out.update(_per_view(metrics))
    return _finish(run_dir, out)


def train(config) -> int:
    """Train (or FDK-reconstruct) and evaluate one resolved TrainConfig; returns the exit code."""
    start = time.perf_counter()
    device = presets.resolve_device(config.device)
    if config.resume:
        run_dir = Path(config.resume)
        saved = config_from_json(read_json(run_dir / "config.json", "run config"))
        config = dataclasses.replace(saved, resume=None, device=config.device)
        if (run_dir / "metrics.json").is_file():
            say(f"run {run_dir} is already complete; nothing to resume")
            metrics = read_json(run_dir / "metrics.json", "metrics file")
            console.print(summary_table(metrics, title=f"{metrics.get('method')} on {metrics.get('scene')}"))
            return 0
        from .run_dir import check_writable

        check_writable(run_dir)  # a full or read-only run folder is reported before training resumes
        say(f"resuming run {run_dir} ({config.method}, preset {config.preset}, seed {config.seed})")
        scene = load_scene(config)
    else:
        scene = load_scene(config)
        run_dir = create_run_dir(config.output_dir, scene.name, config.method)
        write_json(run_dir / "config.json", to_dict(config))
        say(f"run folder: {run_dir}")
    say(f"device: {device}; torch threads: {torch.get_num_threads()}")
    if config.reconstructor == "fdk":
        return _run_fdk(config, scene, run_dir, device)
    return _run_neural(config, scene, run_dir, device, start)
