"""Fitting a model to a volume at the voxel centres: what the warm start, the band correction's and
the smoothing's fits and the materials refit share.

Each fit is a fresh Adam optimiser on the trainer's model, seeded from the run's seed, so the training
optimiser, sampler and RNG states are left as they were (a resumed run matches a straight one).
The loss is ``CTModel.volume_loss_dict``: the MSE of ``mu`` + the per-material occupancy term + the
eikonal term (+ a surface-smoothness term). Outside the model's occupancy grid ``mu`` is 0 whatever
the field, so the field is queried only at the draws inside it; the means keep every draw's count,
so the value term's gradient is the one a query of every draw gives (``skip_outside=False`` is that
query, kept as the test oracle).
"""

from __future__ import annotations

from typing import Callable, Optional

import numpy as np
import torch

from ..engine.optim import adam
from ..engine.progress import format_losses, stage_progress
from ..errors import KneasError


def voxel_targets(trainer, volume: np.ndarray, what: str) -> tuple[torch.Tensor, torch.Tensor]:
    """The voxel centres ``[V, 3]`` (model units) and ``volume``'s values there ``[V]`` (data
    units, negative values clipped to 0); ``volume`` must be on the scene's voxel grid."""
    geometry = trainer.scene.geometry
    if tuple(volume.shape) != tuple(geometry.n_voxel):
        raise KneasError(f"{what} volume has shape {tuple(volume.shape)} but the scene's grid is "
                         f"{tuple(geometry.n_voxel)}; recompute it for this scene")
    points = geometry.voxel_centres(device=trainer.device).reshape(-1, 3)
    targets = torch.as_tensor(np.clip(np.asarray(volume, dtype=np.float32), 0.0, None), device=trainer.device).reshape(-1)
    return points, targets


def fit_steps(trainer, points: torch.Tensor, targets: torch.Tensor, draw: Callable[[], torch.Tensor], steps: int, lr: float,
              occupancy_weight: float, task: str, info: str, fix: str, curvature: float = 0.0,
              generator: Optional[torch.Generator] = None, skip_outside: bool = True) -> dict[str, float]:
    """``steps`` Adam steps (a fresh optimiser at ``lr``) fitting ``mu`` at ``points[draw()]`` to
    ``targets`` (``CTModel.volume_loss_dict``), with a progress bar named ``task``; returns the last
    loss values. ``curvature`` > 0 adds the surface-smoothness term with steps of one voxel in random
    directions drawn with ``generator``. ``fix``: what a non-finite loss's error tells the user to do."""
    model = trainer.model
    queried = None
    if skip_outside:
        inside = model.occupied(points)
        queried = None if inside is None else inside > 0
    voxel = float(min(trainer.scene.geometry.d_voxel))
    optimizer = adam(model.parameters(), lr=lr)
    model.train()
    values: dict[str, float] = {}
    with stage_progress(trainer.console) as progress:
        bar = progress.add_task(task, total=steps, info=info)
        for i in range(steps):
            idx = draw()
            offsets = None
            if curvature > 0:
                u = torch.randn(len(idx), 3, generator=generator).to(trainer.device)
                offsets = voxel * u / u.norm(dim=-1, keepdim=True)
            losses = model.volume_loss_dict(points[idx], targets[idx], occupancy_weight=occupancy_weight,
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
    model.zero_grad(set_to_none=True)
    return values


def fit_whole_volume(trainer, volume: np.ndarray, name: str, steps: int, points_per_step: int, occupancy_weight: float,
                     seed_offset: int, task: str, info: str, fix: str) -> dict[str, float]:
    """:func:`fit_steps` on ``points_per_step`` voxel centres drawn anywhere in the box (seeded from the
    run's seed + ``seed_offset``) at the trainer's learning rate; ``name``: the volume, as a wrong
    shape's error names it."""
    points, targets = voxel_targets(trainer, volume, name)
    gen = torch.Generator(device="cpu")
    gen.manual_seed(int(trainer.config.seed) + int(seed_offset))
    n = min(int(points_per_step), len(points))
    return fit_steps(trainer, points, targets, lambda: torch.randint(0, len(points), (n,), generator=gen).to(trainer.device),
                     int(steps), float(trainer.config.trainer.lr), float(occupancy_weight), task, info, fix)


def fit_in_region(trainer, volume: np.ndarray, mask: np.ndarray, steps: int, points_per_step: int, lr: float,
                  curvature: float = 0.0, what: str = "the corrected volume in the band", stage: str = "correction",
                  skip_outside: bool = True) -> None:
    """Fit the trained model to ``volume`` (data units, the scene's grid) for ``steps`` Adam steps
    at ``lr``: each on ``points_per_step`` voxel centres inside ``mask`` [nx, ny, nz] (bool) and a
    quarter as many anywhere, + ``curvature`` x the surface-smoothness term (0 = none).
    ``what``: the target, as the progress bar names it; ``stage``: the stage it belongs to (the
    progress bar's label, and the stage a failure says to skip). Seeded from the run's seed and the
    training step."""
    points, targets = voxel_targets(trainer, volume, stage)
    inside = torch.as_tensor(np.asarray(mask).reshape(-1), device=trainer.device).nonzero()[:, 0]
    if len(inside) == 0:
        return
    gen = torch.Generator(device="cpu")
    gen.manual_seed(int(trainer.config.seed) + 7919 + trainer.step)
    n = int(points_per_step)

    def draw() -> torch.Tensor:
        return torch.cat([inside[torch.randint(0, len(inside), (n,), generator=gen).to(trainer.device)],
                          torch.randint(0, len(points), (n // 4,), generator=gen).to(trainer.device)])

    fit_steps(trainer, points, targets, draw, int(steps), float(lr), 0.0, f"{trainer.label} {stage} fit", f"fit to {what}",
              f"use --skip-stages {stage}", curvature=float(curvature), generator=gen, skip_outside=skip_outside)
    trainer.model.eval()
