"""One training stage: a model, its datamanager, Adam, the LR schedule, checkpoints (SPEC §3).

:class:`Trainer` trains one :class:`~kneas_method.model.CTModel` for a number of
epochs (one step per training projection) and owns everything a resumed run
needs to continue bit-for-bit where it stopped: model, optimizer and scheduler
state, the datamanager's sampler state, the generator passed to
``model.loss_dict(..., generator=)``, the torch RNG, the step and the loss
history. Checkpoints go to ``<run>/checkpoints/`` (atomic, weights-only; see
:mod:`.checkpoint`).

Interrupts: while a stage runs, the first Ctrl-C (SIGINT) only sets a flag; the
current step finishes, a checkpoint of that consistent state is written and
:class:`StageInterrupted` is raised (the CLI prints where and exits 130). A
second Ctrl-C interrupts at once (the last checkpoint written stays valid).

Bad numbers: a non-finite loss (or gradient) is not applied — the gradients are
zeroed, the step is counted and reported. ``max_bad_steps`` of them in a row
end the stage with a one-line :class:`~kneas_method.errors.KneasError` naming
the last good checkpoint; a checkpoint is never written while a parameter is
non-finite.
"""

from __future__ import annotations

import dataclasses
import signal
import threading
import time
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

import numpy as np
import torch

from ..errors import KneasError
from ..evaluation.metrics import psnr2d
from .anchor import Anchor, edge_trust, label_interior
from .checkpoint import load_latest_checkpoint, save_checkpoint
from .loss_scale import LOSS_SCALE_TOP, loss_scale
from .progress import format_losses, stage_progress


class StageInterrupted(Exception):
    """Ctrl-C during training; ``checkpoint`` is the file written (or the last good one, or None)."""

    def __init__(self, checkpoint: Optional[Path], step: int):
        super().__init__(f"interrupted at step {step}")
        self.checkpoint = checkpoint
        self.step = step


class _DeferredInterrupt:
    """Context manager: the first SIGINT sets ``requested``; a second raises KeyboardInterrupt."""

    def __init__(self):
        self.requested = False
        self._previous = None

    def _handler(self, signum, frame):
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGINT, self._handler)
        return self

    def __exit__(self, *exc):
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)
        return False


REFIT_SEED_OFFSET = 15485863  # the materials refit's initialisation and draws: the run's seed plus this


def _finite_params(model: torch.nn.Module) -> bool:
    return all(bool(torch.isfinite(p).all()) for p in model.parameters())


def _finite_grads(model: torch.nn.Module) -> bool:
    return all(p.grad is None or bool(torch.isfinite(p.grad).all()) for p in model.parameters())


class Trainer:
    """Train one model for ``epochs`` epochs.

    Args:
        config: the resolved TrainConfig of this stage (its ``model``, ``datamanager``,
            ``trainer`` and ``seed`` are used; ``method`` is written into checkpoints).
        scene: the scene with the training views already subsampled.
        run_dir: the stage's run folder (checkpoints go to ``run_dir/checkpoints``).
        epochs: number of epochs of this stage.
        device: torch device.
        bounds: ``(alphas, betas)`` in data units for SDF models, or None (the
            model's own: config values or placeholders).
        label: progress-bar label (``prior``, ``model``).
        console: a rich Console for the progress bar and messages.
        tb: optional TensorBoard ``SummaryWriter``.
        tb_prefix: tag prefix for TensorBoard scalars.
    """

    def __init__(self, config, scene, run_dir, *, epochs: int, device, bounds=None, label: str = "model", console=None,
                 tb=None, tb_prefix: str = "", max_bad_steps: Optional[int] = None):
        from ..model import CTModel

        self.config = config
        self.scene = scene
        self.run_dir = Path(run_dir)
        self.ckpt_dir = self.run_dir / "checkpoints"
        self.device = torch.device(device)
        self.label = label
        self.console = console
        self.tb = tb
        self.tb_prefix = tb_prefix
        t = config.trainer
        self.max_bad_steps = int(max_bad_steps if max_bad_steps is not None else getattr(t, "max_bad_steps", 5))
        self.epochs = int(epochs)
        if self.epochs < 1:
            raise KneasError(f"the {label} stage has {epochs} epochs; give at least 1 (--trainer.epochs / --trainer.prior-epochs)")
        seed = int(config.seed)
        torch.manual_seed(seed)
        self.model = CTModel(config.model, scale=scene.geometry.scale, device=self.device).to(self.device)
        self.model.loss_scale = loss_scale(scene)
        if not self.model.has_surfaces:  # its network's outputs in the same unit (the bounds carry it for the others)
            self.model.attenuation_unit.fill_(self.model.loss_scale)
        if self.model.loss_scale != 1.0:
            self._print(f"{label}: losses measured in units of {self.model.loss_scale:.4g} /m, the 99.5th percentile of the scan's "
                        f"FDK volume, which is above NAF's normalised {LOSS_SCALE_TOP:g} /m, so that they weigh as on NAF's "
                        "scale; the volume and the bounds stay in /m")
        if bounds is not None:
            self.model.set_bounds(*bounds)
        elif self.model.has_surfaces and self.model.loss_scale != 1.0:  # NeAS's wide defaults are NAF-scale: in the scan's unit
            alphas, betas = self.model.bounds
            self.model.set_bounds([self.model.loss_scale * a for a in alphas], [self.model.loss_scale * b for b in betas])
        if self.model.quadrature == "voxel-planes":
            from ..occupancy import box_of

            self.model.set_voxel_grid(scene.geometry.n_voxel, *box_of(scene.geometry))
        self.datamanager = config.datamanager.setup(scene=scene, device=self.device, seed=seed)
        self.steps_per_epoch = self.datamanager.steps_per_epoch
        self.total_steps = self.epochs * self.steps_per_epoch
        self._make_optimizer()
        self.generator = torch.Generator(device="cpu")
        self.generator.manual_seed(seed + 7919)
        self.step = 0
        self.history: dict[str, list[list[float]]] = {}
        self.bad_steps: list[int] = []
        self.wall_time_s = 0.0
        self.warm_start_time_s = 0.0
        self.last_checkpoint: Optional[Path] = None
        self.complete = False
        self.anchor: Optional[Anchor] = None
        self.correction: Optional[list] = None  # the band-correction passes after training (correction_stage)
        self.correction_time_s = 0.0
        self.correction_budget: Optional[dict] = None  # where the run's time budget ended the passes early (correction_stage)
        self.training_budget: Optional[dict] = None  # where it shortened training (train(deadline=...))
        self.denoising: Optional[dict] = None  # the SURE smoothing after the passes (correction_stage.denoise_stage)
        self.materials_refit: Optional[dict] = None  # the materials found again on the trained volume (materials_stage)

    def _make_optimizer(self) -> None:
        """A fresh Adam optimiser over the model's parameters and the learning-rate schedule."""
        t = self.config.trainer
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=float(t.lr))
        self.decay_step = int(round(float(t.lr_decay_at) * self.total_steps))
        factor = float(t.lr_decay_factor)
        self.scheduler = torch.optim.lr_scheduler.LambdaLR(self.optimizer, lambda s: factor if s >= self.decay_step else 1.0)

    # ---------------------------------------------------------------- state
    def state(self, complete: bool = False) -> dict[str, Any]:
        return {
            "step": self.step,
            "epoch": self.step // self.steps_per_epoch,
            "method": self.config.method,
            "model": self.model.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "scheduler": self.scheduler.state_dict(),
            "datamanager": self.datamanager.state_dict(),
            "rng": {"torch": torch.get_rng_state(), "loss_generator": self.generator.get_state()},
            "extra": {
                "stage": self.label,
                "complete": bool(complete),
                "total_steps": self.total_steps,
                "history": self.history,
                "bad_steps": list(self.bad_steps),
                "wall_time_s": float(self.wall_time_s),
                "warm_start_time_s": float(self.warm_start_time_s),
                "num_materials": int(self.model.num_materials),
                "correction": self.correction,
                "correction_time_s": float(self.correction_time_s),
                "correction_budget": self.correction_budget,
                "training_budget": self.training_budget,
                "denoising": self.denoising,
                "materials_refit": self.materials_refit,
            },
        }

    def load_state(self, state: dict[str, Any]) -> None:
        extra = state.get("extra", {})
        if int(extra.get("total_steps", self.total_steps)) != self.total_steps:
            raise KneasError(f"the checkpoint was written for {extra.get('total_steps')} steps but this stage has {self.total_steps}; "
                             "resume with the run's own config.json unchanged")
        self.model.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.scheduler.load_state_dict(state["scheduler"])
        self.datamanager.load_state_dict(state["datamanager"])
        torch.set_rng_state(state["rng"]["torch"])
        self.generator.set_state(state["rng"]["loss_generator"])
        self.step = int(state["step"])
        self.history = {k: [list(map(float, p)) for p in v] for k, v in extra.get("history", {}).items()}
        self.bad_steps = [int(s) for s in extra.get("bad_steps", [])]
        self.wall_time_s = float(extra.get("wall_time_s", 0.0))
        self.warm_start_time_s = float(extra.get("warm_start_time_s", 0.0))
        self.complete = bool(extra.get("complete", False))
        self.correction = extra.get("correction")
        self.correction_time_s = float(extra.get("correction_time_s", 0.0))
        self.correction_budget = extra.get("correction_budget")
        self.training_budget = extra.get("training_budget")
        self.denoising = extra.get("denoising")
        self.materials_refit = extra.get("materials_refit")

    def resume(self) -> Optional[Path]:
        """Load the newest checkpoint of this stage, if any; returns its path."""
        from .checkpoint import list_checkpoints

        if not list_checkpoints(self.ckpt_dir):
            return None
        state, path, skipped = load_latest_checkpoint(self.ckpt_dir, method=self.config.method)
        for reason in skipped:
            self._print(f"[yellow]skipped damaged checkpoint:[/] {reason}")
        self.load_state(state)
        self.last_checkpoint = path
        return path

    def save(self, complete: bool = False) -> Optional[Path]:
        """Write a checkpoint of the current (consistent) state; never with non-finite parameters."""
        if not _finite_params(self.model):
            self._print(f"[red]not writing a checkpoint at step {self.step}: the model has non-finite parameters[/]; "
                        f"the last good one is {self.last_checkpoint}")
            return None
        try:
            path = save_checkpoint(self.ckpt_dir, self.state(complete))
        except OSError as exc:  # disk full, folder gone or read-only: keep the last good one and say where it is
            raise KneasError(
                f"cannot write a checkpoint at step {self.step} in {self.ckpt_dir} ({exc.strerror or exc}); "
                f"the last good checkpoint is {self.last_checkpoint or 'none (none was written yet)'}; "
                f"free some space, then resume with: kneas-train --resume {self.run_dir}") from None
        self.last_checkpoint = path
        return self.last_checkpoint

    def loss_history(self) -> dict[str, list[tuple[float, float]]]:
        """The recorded loss terms ``{name: [(step, value), ...]}`` (no learning rate or validation)."""
        return {k: [tuple(p) for p in v] for k, v in self.history.items() if k not in ("lr", "val_psnr2d")}

    # -------------------------------------------------------------- helpers
    def _print(self, msg: str) -> None:
        if self.console is not None:
            self.console.print(msg, soft_wrap=True)

    def _record(self, name: str, value: float) -> None:
        self.history.setdefault(name, []).append([float(self.step), float(value)])
        if self.tb is not None:
            self.tb.add_scalar(f"{self.tb_prefix}{name}", value, self.step)

    @torch.no_grad()
    def validate(self) -> float:
        """Mean 2D PSNR over ``trainer.eval_views`` held-out views (all when None), their projections
        made as the final evaluation makes them (``trainer.eval_projections``: rendered through the
        field, or the model's volume projected)."""
        from .evaluate import held_out_projections

        val = self.scene.val
        n = len(val)
        k = self.config.trainer.eval_views
        idx = np.arange(n) if not k or k >= n else np.unique(np.round(np.linspace(0, n - 1, int(k))).astype(int))
        pred = held_out_projections(self.model, self.scene, self.config, self.device, np.asarray(val.angles)[idx])
        return float(np.mean(psnr2d(pred, np.asarray(val.projections)[idx])))

    # ----------------------------------------------------------- warm start
    def _voxel_targets(self, volume: np.ndarray, what: str) -> tuple[torch.Tensor, torch.Tensor]:
        """The voxel centres ``[V, 3]`` (model units) and ``volume``'s values there ``[V]`` (data
        units, negative values clipped to 0); ``volume`` must be on the scene's voxel grid."""
        if tuple(volume.shape) != tuple(self.scene.geometry.n_voxel):
            raise KneasError(f"{what} volume has shape {tuple(volume.shape)} but the scene's grid is "
                             f"{tuple(self.scene.geometry.n_voxel)}; recompute it for this scene")
        points = self.scene.geometry.voxel_centres(device=self.device).reshape(-1, 3)
        targets = torch.as_tensor(np.clip(np.asarray(volume, dtype=np.float32), 0.0, None), device=self.device).reshape(-1)
        return points, targets

    def warm_start(self, volume: np.ndarray, steps: int, points_per_step: int, what: str = "FDK",
                   occupancy_weight: float = 0.0) -> float:
        """Fit the fresh model to an attenuation ``volume`` (data units, the scene's voxel
        grid; negative values clipped to 0) before projection training: ``steps`` Adam
        steps at the trainer's learning rate, each on ``points_per_step`` random voxel
        centres, loss = MSE of ``mu`` + ``occupancy_weight`` x the per-material occupancy
        cross-entropy (``CTModel.volume_loss_dict``) + the model's eikonal term. Seeded from the run's
        seed; leaves the training optimiser, sampler and RNG states untouched (so a
        resumed run matches a straight one). Returns the wall time in seconds."""
        if self.step != 0:
            raise KneasError(f"the warm start runs before training, but the {self.label} stage is at step {self.step}")
        started = time.perf_counter()
        values = self._fit_whole_volume(volume, "warm-start", steps, points_per_step, occupancy_weight, 104729, f"{self.label} warm start",
                                        f"fit to the {what} volume", f"check the {what} volume or use --trainer.warm-start none")
        for k, v in values.items():
            self._record(f"warm_start_{k}", v)
        self.warm_start_time_s = time.perf_counter() - started
        return self.warm_start_time_s

    def _fit_whole_volume(self, volume: np.ndarray, name: str, steps: int, points_per_step: int, occupancy_weight: float,
                          seed_offset: int, task: str, info: str, fix: str) -> dict[str, float]:
        """``steps`` steps of ``_fit_steps`` on ``points_per_step`` voxel centres drawn anywhere in
        the box (seeded from the run's seed + ``seed_offset``) at the trainer's learning rate;
        ``name``: the volume, as a wrong shape's error names it."""
        points, targets = self._voxel_targets(volume, name)
        gen = torch.Generator(device="cpu")
        gen.manual_seed(int(self.config.seed) + int(seed_offset))
        n = min(int(points_per_step), len(points))
        return self._fit_steps(points, targets, lambda: torch.randint(0, len(points), (n,), generator=gen).to(self.device),
                               int(steps), float(self.config.trainer.lr), float(occupancy_weight), task, info, fix)

    def refit_materials(self, volume: np.ndarray, alphas: Sequence[float], betas: Sequence[float], steps: int,
                        points_per_step: int, occupancy_weight: float, what: str = "trained") -> None:
        """Replace the trained model by a fresh one with ``len(alphas)`` materials and these bounds
        (data units; ``config.num_materials`` follows), the old one's empty-space and voxel grids,
        and fit it to ``volume`` [nx, ny, nz] (data units) as the warm start fits (``steps`` steps on
        ``points_per_step`` voxel centres, the occupancy cross-entropy at ``occupancy_weight``).
        The optimiser and its schedule are made afresh for the new parameters: the stage runs after
        training, and they only keep a checkpoint loadable."""
        from ..model import CTModel

        old = self.model
        K = len(alphas)
        model_config = dataclasses.replace(self.config.model, num_materials=K)
        self.config = dataclasses.replace(self.config, num_materials=K, model=model_config)
        torch.manual_seed(int(self.config.seed) + REFIT_SEED_OFFSET)
        model = CTModel(model_config, scale=self.scene.geometry.scale, device=self.device).to(self.device)
        model.set_bounds(alphas, betas)
        model.loss_scale = old.loss_scale
        if old.occupancy is not None:
            model.set_occupancy(old.occupancy, old.occupancy_box[0].tolist(), old.occupancy_box[1].tolist())
        if model.quadrature == "voxel-planes":
            model.set_voxel_grid(old.voxel_count.tolist(), old.voxel_box[0].tolist(), old.voxel_box[1].tolist())
        self.model = model
        self._make_optimizer()
        self._fit_whole_volume(volume, what, steps, points_per_step, occupancy_weight, REFIT_SEED_OFFSET, f"{self.label} materials fit",
                               f"fit of {K} materials to the {what} volume", "use --trainer.materials-refit-steps 0")
        self.model.eval()

    def _fit_steps(self, points: torch.Tensor, targets: torch.Tensor, draw, steps: int, lr: float, occupancy_weight: float,
                   task: str, info: str, fix: str, curvature: float = 0.0,
                   generator: Optional[torch.Generator] = None) -> dict[str, float]:
        """``steps`` Adam steps (a fresh optimiser at ``lr``) fitting ``mu`` at ``points[draw()]`` to
        ``targets`` (``CTModel.volume_loss_dict``), with a progress bar; returns the last loss values.
        ``curvature`` > 0 adds the surface-smoothness term with steps of one voxel in random
        directions drawn with ``generator``. With ``TrainConfig.fit_outside`` ``skip`` the field is
        queried only at the draws inside the occupancy grid (``queried`` of ``volume_loss_dict``)."""
        queried = None
        if str(self.config.trainer.fit_outside) == "skip":
            inside = self.model.occupied(points)
            queried = None if inside is None else inside > 0
        voxel = float(min(self.scene.geometry.d_voxel))
        optimizer = torch.optim.Adam(self.model.parameters(), lr=lr)
        self.model.train()
        values: dict[str, float] = {}
        with stage_progress(self.console) as progress:
            bar = progress.add_task(task, total=steps, info=info)
            for i in range(steps):
                idx = draw()
                offsets = None
                if curvature > 0:
                    u = torch.randn(len(idx), 3, generator=generator).to(self.device)
                    offsets = voxel * u / u.norm(dim=-1, keepdim=True)
                losses = self.model.volume_loss_dict(points[idx], targets[idx], occupancy_weight=occupancy_weight,
                                                     curvature_weight=curvature, steps=offsets,
                                                     queried=None if queried is None else queried[idx])
                optimizer.zero_grad(set_to_none=True)
                if not torch.isfinite(losses["total"]):
                    raise KneasError(f"non-finite loss in the {task} (step {i}); {fix}")
                losses["total"].backward()
                optimizer.step()
                if i % 10 == 0 or i == steps - 1:
                    values = {k: float(v.detach()) for k, v in losses.items() if k != "total"}
                    progress.update(bar, completed=i + 1, info=format_losses(values))
            progress.update(bar, completed=steps)
        self.model.zero_grad(set_to_none=True)
        return values

    def fit_to_volume(self, volume: np.ndarray, mask: np.ndarray, steps: int, points_per_step: int, lr: float,
                      curvature: float = 0.0, what: str = "the corrected volume in the band",
                      stage: str = "correction") -> None:
        """Fit the trained model to ``volume`` (data units, the scene's grid) for ``steps`` Adam steps
        at ``lr``: each on ``points_per_step`` voxel centres inside ``mask`` [nx, ny, nz] (bool) and a
        quarter as many anywhere, loss = MSE of ``mu`` + the eikonal term (``CTModel.volume_loss_dict``)
        + ``curvature`` x the surface-smoothness term (``losses.curvature``; 0 = none).
        ``what``: the target, as the progress bar names it; ``stage``: ``correction`` or ``denoise``, the
        stage it belongs to (the progress bar's label, and the flag a failure names to skip it).
        Seeded from the run's seed and the step; the training optimiser and RNG are untouched."""
        points, targets = self._voxel_targets(volume, "correction")
        inside = torch.as_tensor(np.asarray(mask).reshape(-1), device=self.device).nonzero()[:, 0]
        if len(inside) == 0:
            return
        gen = torch.Generator(device="cpu")
        gen.manual_seed(int(self.config.seed) + 7919 + self.step)
        n = int(points_per_step)

        def draw() -> torch.Tensor:
            return torch.cat([inside[torch.randint(0, len(inside), (n,), generator=gen).to(self.device)],
                              torch.randint(0, len(points), (n // 4,), generator=gen).to(self.device)])

        skip = "use --trainer.denoise none" if stage == "denoise" else "use --trainer.correction-passes 0"
        self._fit_steps(points, targets, draw, int(steps), float(lr), 0.0, f"{self.label} {stage} fit",
                        f"fit to {what}", skip,
                        curvature=float(curvature), generator=gen)
        self.model.eval()

    def set_anchor(self, volume: np.ndarray, weight: float, points_per_step: int, occupancy_weight: float = 0.0,
                   edge_contrast: float = 0.0, region: str = "box", outside: str = "labels") -> None:
        """Keep ``volume`` (data units, the scene's voxel grid; negative values clipped to 0) as a
        prior during projection training: every step adds :meth:`anchor_loss`. Weight 0 = none;
        ``occupancy_weight`` > 0 keeps the labels its values give too (SDF models), only where
        they are trusted: :func:`~.anchor.label_interior`, away from the volume's edges;
        ``edge_contrast`` > 0 weighs each voxel's value by :func:`~.anchor.edge_trust` (less at
        its sharp edges). ``region`` ``hull`` keeps only the voxel centres inside the model's
        occupancy grid, the weight times their share of the voxels (the ``box``'s loss in
        expectation; see ``TrainConfig.anchor_region``); without a grid it is the box. ``outside``
        ``skip``: the box's draws outside the occupancy grid are left out of the field's query
        (``TrainConfig.anchor_outside``)."""
        if region not in ("box", "hull"):
            raise KneasError(f"the anchor's region is {region!r}; choose box or hull (--trainer.anchor-region)")
        if outside not in ("labels", "skip"):
            raise KneasError(f"the anchor's outside rule is {outside!r}; choose labels or skip (--trainer.anchor-outside)")
        if weight <= 0:
            self.anchor = None
            return
        points, targets = self._voxel_targets(volume, "prior")
        mask = values = None
        if occupancy_weight > 0 and self.model.has_surfaces:
            thresholds = self.model.label_thresholds().detach().cpu().numpy()
            mask = torch.as_tensor(label_interior(np.clip(volume, 0.0, None), thresholds).reshape(-1), device=self.device)
        if edge_contrast > 0:
            values = torch.as_tensor(edge_trust(volume, edge_contrast).reshape(-1), device=self.device)
        inside = self.model.occupied(points) if (region == "hull" or outside == "skip") else None
        out_of_grid = None
        if inside is not None and region == "hull" and bool((inside > 0).any()):
            keep = (inside > 0).nonzero()[:, 0]
            weight = float(weight) * len(keep) / len(points)
            points, targets = points[keep], targets[keep]
            mask = None if mask is None else mask[keep]
            values = None if values is None else values[keep]
        elif inside is not None and outside == "skip":
            out_of_grid = inside <= 0
        self.anchor = Anchor(points, targets, float(weight), int(points_per_step), float(occupancy_weight), mask, values,
                             out_of_grid)

    def anchor_loss(self) -> torch.Tensor:
        """``weight`` x (the MSE between ``mu`` and the prior volume, each voxel times its
        ``value_weights`` where set, + ``occupancy_weight`` x the per-material occupancy
        cross-entropy on its trusted labels, ``CTModel.occupancy_loss``) at ``points_per_step``
        voxel centres drawn with the run's loss generator (so a resumed run draws the same ones).
        With ``Anchor.outside`` the field is queried only at the draws inside the occupancy grid:
        outside it ``mu`` is 0 whatever the field, so their squared error is the same constant
        (kept in the value) and their label term is left out; the means keep all the draws'
        counts, so the gradient inside the grid is the one every draw's query gives."""
        a = self.anchor
        n = min(a.points_per_step, len(a.points))
        idx = torch.randint(0, len(a.points), (n,), generator=self.generator).to(self.device)
        if a.outside is None:
            q = self.model.query(a.points[idx])
            squared = (q["mu"] - a.targets[idx]) ** 2
            loss = torch.mean(squared if a.value_weights is None else a.value_weights[idx] * squared)
            if self.model.loss_scale != 1.0:  # in the model's loss unit, as its other terms
                loss = loss / self.model.loss_scale ** 2
            if a.label_mask is not None:
                loss = loss + a.occupancy_weight * self.model.occupancy_loss(q["distances"], a.targets[idx], mask=a.label_mask[idx])
            return a.weight * loss
        gone = a.outside[idx]
        queried = idx[~gone]
        unseen = a.targets[idx[gone]] ** 2  # (0 - target)^2 at the draws outside the grid
        constant = (unseen if a.value_weights is None else a.value_weights[idx[gone]] * unseen).sum()
        q = self.model.query(a.points[queried])
        squared = (q["mu"] - a.targets[queried]) ** 2
        squared = squared if a.value_weights is None else a.value_weights[queried] * squared
        loss = (squared.sum() + constant) / n
        if self.model.loss_scale != 1.0:  # in the model's loss unit, as its other terms
            loss = loss / self.model.loss_scale ** 2
        if a.label_mask is not None:  # the mean over every draw's trusted labels, as a query of every draw gives
            labels = self.model.occupancy_loss(q["distances"], a.targets[queried], mask=a.label_mask[queried])
            loss = loss + a.occupancy_weight * labels * a.label_mask[queried].sum().clamp(min=1) / a.label_mask[idx].sum().clamp(min=1)
        return a.weight * loss

    def shorten(self, total_steps: int, seconds_per_step: float, left: float, say: Callable[[str], None] = print) -> None:
        """Train ``total_steps`` (whole epochs) instead of the planned steps, the learning rate's step at
        the same share of them, because the run's time budget (``left`` seconds of it) does not hold them
        at ``seconds_per_step``; ``config.json`` is rewritten with the epochs, so that a resumed run
        trains the same, and ``training_budget`` keeps what was done."""
        from .run_dir import save_run_config

        t = self.config.trainer
        planned, planned_steps = self.epochs, self.total_steps
        self.epochs = int(total_steps) // self.steps_per_epoch
        self.total_steps = self.epochs * self.steps_per_epoch
        self.decay_step = int(round(float(t.lr_decay_at) * self.total_steps))
        self.config = dataclasses.replace(self.config, trainer=dataclasses.replace(t, epochs=self.epochs))
        save_run_config(self.run_dir, self.config)
        self.training_budget = {"epochs_planned": planned, "epochs": self.epochs,
                                "seconds_per_step": round(float(seconds_per_step), 5), "seconds_left": round(float(left), 1)}
        say(f"{self.label}: the run's time budget (--trainer.time-budget; 0 = none) has {left:.0f} s left, and a step takes "
            f"{seconds_per_step:.3f} s: {self.total_steps} of the {planned_steps} steps ({self.epochs} of {planned} epochs) leave the "
            "band-correction passes their time, so training is shortened to them (--trainer.time-budget 0 trains them all)")

    # ----------------------------------------------------------------- loop
    def train(self, on_step: Optional[Callable[[int], None]] = None, deadline: Optional[float] = None, passes: bool = False) -> None:
        """Run the remaining steps; raise StageInterrupted on Ctrl-C, KneasError on repeated bad steps.

        ``deadline``: when the run's time budget runs out (``time.perf_counter`` seconds; None: no
        budget). After ``budget.TIMED_STEPS`` steps training is shortened, where it must be, to the
        whole epochs that leave the run's band-correction passes (``passes``) their time
        (:meth:`shorten`, ``budget.training_steps``)."""
        if self.complete or self.step >= self.total_steps:
            self.complete = True
            return
        t = self.config.trainer
        eval_every = int(t.eval_every or 0)
        ckpt_every = int(t.checkpoint_every or 0)
        log_every = max(1, int(t.log_every or 1))
        consecutive = 0
        self.model.train()
        progress = stage_progress(self.console)
        started = time.perf_counter()
        from .budget import TIME_RESERVE_S, TIMED_STEPS, training_steps

        timed_from, check_at = started, (self.step + TIMED_STEPS if deadline is not None else None)
        last_info = ""
        with progress, _DeferredInterrupt() as interrupt:
            task = progress.add_task(self.label, total=self.total_steps, completed=self.step, info="")
            try:
                while self.step < self.total_steps:
                    batch = self.datamanager.next_train()
                    frac = self.step / self.total_steps
                    losses = self.model.loss_dict(batch, frac, generator=self.generator)
                    if self.anchor is not None:
                        losses["anchor"] = self.anchor_loss()
                        losses["total"] = losses["total"] + losses["anchor"]
                    total = losses["total"]
                    ok = bool(torch.isfinite(total))
                    self.optimizer.zero_grad(set_to_none=True)
                    if ok:
                        total.backward()
                        ok = _finite_grads(self.model)
                    if ok:
                        self.optimizer.step()
                        consecutive = 0
                    else:
                        self.optimizer.zero_grad(set_to_none=True)
                        consecutive += 1
                        self.bad_steps.append(self.step)
                        progress.console.print(f"[yellow]step {self.step}: non-finite loss or gradient "
                                               f"({format_losses({k: float(v.detach()) for k, v in losses.items()})}); not applied[/]")
                    self.scheduler.step()
                    self.step += 1
                    values = {k: float(v.detach()) for k, v in losses.items()}
                    for k, v in values.items():
                        self._record(k, v)
                    if self.step % log_every == 0 or self.step == self.total_steps:
                        self._record("lr", self.optimizer.param_groups[0]["lr"])
                    if consecutive >= self.max_bad_steps:
                        self.wall_time_s += time.perf_counter() - started
                        started = time.perf_counter()
                        raise KneasError(
                            f"{consecutive} non-finite losses in a row ({self.label} stage, step {self.step}): training stopped; "
                            f"the last good checkpoint is {self.last_checkpoint or 'none (none was written yet)'}; "
                            "lower the learning rate (--trainer.lr) or check the data")
                    if self.step % 5 == 0 or self.step == self.total_steps:
                        last_info = format_losses({k: v for k, v in values.items() if k != "total"})
                    progress.update(task, completed=self.step, info=last_info)
                    if on_step is not None:
                        on_step(self.step)
                    if self.step == check_at:
                        now = time.perf_counter()
                        per_step = (now - timed_from) / TIMED_STEPS
                        fits = training_steps(deadline - TIME_RESERVE_S - now, self.step, self.total_steps, per_step,
                                              self.steps_per_epoch, passes)
                        if fits < self.total_steps:
                            self.shorten(fits, per_step, deadline - now, say=progress.console.print)
                            progress.update(task, total=self.total_steps)
                    epoch_done = self.step % self.steps_per_epoch == 0
                    epoch = self.step // self.steps_per_epoch
                    last = self.step == self.total_steps
                    if epoch_done and eval_every and epoch % eval_every == 0 and not last:
                        p = self.validate()
                        self._record("val_psnr2d", p)
                        progress.console.print(f"{self.label} epoch {epoch}/{self.epochs}: validation PSNR2D {p:.2f} dB "
                                               f"({t.eval_views or 'all'} held-out views)")
                    if last or (epoch_done and ckpt_every and epoch % ckpt_every == 0) or interrupt.requested:
                        self.wall_time_s += time.perf_counter() - started
                        started = time.perf_counter()
                        if self.save(complete=last) is None and last:
                            raise KneasError(
                                f"the model has non-finite parameters at the end of the {self.label} stage (step {self.step}); "
                                f"nothing was marked complete; the last good checkpoint is "
                                f"{self.last_checkpoint or 'none (none was written yet)'}; lower the learning rate (--trainer.lr)")
                    if interrupt.requested and not last:
                        raise StageInterrupted(self.last_checkpoint, self.step)
            except KeyboardInterrupt:  # second Ctrl-C, mid-step: keep the last consistent checkpoint
                raise StageInterrupted(self.last_checkpoint, self.step) from None
        self.complete = True
