"""The anchor (not in the paper): the classical start's volume kept as a prior during projection
training. Sparse views leave much of the volume unconstrained; there the (TV-regularised) classical
volume holds the field instead of the step noise, and the projections still decide where they
disagree.

:func:`build_anchor` makes the :class:`Anchor` whose :meth:`Anchor.loss` every training step adds;
:func:`label_interior` says where that volume's labels can be trusted and :func:`edge_trust` how much
each of its values is.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, Optional, Sequence

import numpy as np
import torch
from scipy import ndimage

from ..config import at_least
from ..errors import KneasError
from .base import RunState, Stage, StageConfig
from .band_correction import gradient_magnitude
from .volume_fit import voxel_targets

# labels are kept only this many voxels away from any other label (a 5^3 neighbourhood):
# measured on the ASD-POCS volumes of seven scenes against the truth, the labels there are
# wrong at 0 to 199 voxels in a million (at the edges themselves, blur: tens of thousands)
LABEL_MARGIN_VOXELS = 2


def label_interior(volume: np.ndarray, thresholds: Sequence[float], margin: int = LABEL_MARGIN_VOXELS) -> np.ndarray:
    """Voxels whose label is the label of every voxel within ``margin`` voxels (a cube).

    A voxel's label is how many of ``thresholds`` (ascending) its value exceeds. A
    reconstruction's labels are wrong mostly where its edges are blurred; away from any
    edge they agree with the truth's.

    Args:
        volume: ``[X, Y, Z]`` attenuation.
        thresholds: ``[K]`` ascending label thresholds, same units.
        margin: half the cube's side, voxels (0: every voxel).

    Returns:
        ``[X, Y, Z]`` bool.
    """
    labels = np.digitize(np.asarray(volume), np.asarray(thresholds, dtype=np.float64)).astype(np.int16)
    size = 2 * int(margin) + 1
    return ndimage.maximum_filter(labels, size=size, mode="nearest") == ndimage.minimum_filter(labels, size=size, mode="nearest")


def edge_trust(volume: np.ndarray, contrast: float) -> np.ndarray:
    """How much each voxel's value of a reconstruction is trusted: ``1 / (1 + (g / g0)^2)``.

    ``g`` is the voxel's central-difference gradient magnitude (``band_correction.gradient_magnitude``) and ``g0 = contrast x``
    the volume's 99.5th percentile, so the weight is 1 where the volume is flat and 1/2 where its
    values change by ``contrast`` of its range per voxel. A sparse-view reconstruction's error
    grows with its gradient (at the edges it blurs and shifts), and this weighs it as a Gaussian
    prior whose spread grows with that gradient; faint edges, where the projections say little,
    keep most of their weight.

    Args:
        volume: ``[X, Y, Z]`` attenuation (negative values count as 0).
        contrast: ``> 0``, a fraction of the volume's 99.5th percentile.

    Returns:
        ``[X, Y, Z]`` float32 in ``(0, 1]``.
    """
    v = np.clip(np.asarray(volume, dtype=np.float32), 0.0, None)
    g0 = float(contrast) * float(np.percentile(v, 99.5))
    if not g0 > 0:
        return np.ones(v.shape, dtype=np.float32)
    g = gradient_magnitude(torch.from_numpy(v)).numpy()
    return (1.0 / (1.0 + (g / g0) ** 2)).astype(np.float32)


AnchorRegion = Literal["box", "hull"]


@dataclass(frozen=True)
class Anchor:
    """A prior volume on the scene's voxel grid, as :meth:`loss` draws from it.

    Attributes:
        points: ``[V, 3]`` voxel centres, model units.
        targets: ``[V]`` the volume's values there, data units (negative values clipped to 0).
        weight: the prior's weight in the loss.
        points_per_step: voxel centres drawn each step.
        occupancy_weight: weight, inside the prior, of its labels (``CTModel.occupancy_loss``); 0 = none.
        label_mask: ``[V]`` bool, the voxels whose labels count (:func:`label_interior`);
            ``None`` when ``occupancy_weight`` is 0.
        value_weights: ``[V]`` each voxel's weight in the MSE (:func:`edge_trust`); ``None`` = 1 everywhere.
        outside: ``[V]`` bool, the voxels outside the model's occupancy grid, which the loss leaves out
            of its field query; ``None`` = query every draw.
    """

    points: torch.Tensor
    targets: torch.Tensor
    weight: float
    points_per_step: int
    occupancy_weight: float = 0.0
    label_mask: Optional[torch.Tensor] = None
    value_weights: Optional[torch.Tensor] = None
    outside: Optional[torch.Tensor] = None

    def loss(self, model, generator: torch.Generator) -> torch.Tensor:
        """``weight`` x (the MSE between ``mu`` and the prior volume, each voxel times its
        ``value_weights`` where set, + ``occupancy_weight`` x the per-material occupancy
        cross-entropy on its trusted labels, ``CTModel.occupancy_loss``) at ``points_per_step``
        voxel centres drawn with ``generator`` (the run's loss generator, so a resumed run draws the
        same ones). With ``outside`` the field is queried only at the draws inside the occupancy
        grid: outside it ``mu`` is 0 whatever the field, so their squared error is the same constant
        (kept in the value) and their label term is left out; the means keep all the draws' counts,
        so the gradient inside the grid is the one every draw's query gives."""
        n = min(self.points_per_step, len(self.points))
        idx = torch.randint(0, len(self.points), (n,), generator=generator).to(self.points.device)
        if self.outside is None:
            q = model.query(self.points[idx])
            squared = (q["mu"] - self.targets[idx]) ** 2
            loss = torch.mean(squared if self.value_weights is None else self.value_weights[idx] * squared)
            if model.loss_scale != 1.0:  # in the model's loss unit, as its other terms
                loss = loss / model.loss_scale ** 2
            if self.label_mask is not None:
                loss = loss + self.occupancy_weight * model.occupancy_loss(q["distances"], self.targets[idx], mask=self.label_mask[idx])
            return self.weight * loss
        gone = self.outside[idx]
        queried = idx[~gone]
        unseen = self.targets[idx[gone]] ** 2  # (0 - target)^2 at the draws outside the grid
        constant = (unseen if self.value_weights is None else self.value_weights[idx[gone]] * unseen).sum()
        q = model.query(self.points[queried])
        squared = (q["mu"] - self.targets[queried]) ** 2
        squared = squared if self.value_weights is None else self.value_weights[queried] * squared
        loss = (squared.sum() + constant) / n
        if model.loss_scale != 1.0:  # in the model's loss unit, as its other terms
            loss = loss / model.loss_scale ** 2
        if self.label_mask is not None:  # the mean over every draw's trusted labels, as a query of every draw gives
            labels = model.occupancy_loss(q["distances"], self.targets[queried], mask=self.label_mask[queried])
            loss = loss + self.occupancy_weight * labels * self.label_mask[queried].sum().clamp(min=1) / self.label_mask[idx].sum().clamp(min=1)
        return self.weight * loss


def build_anchor(trainer, volume: np.ndarray, weight: float, points_per_step: int, occupancy_weight: float = 0.0,
                 edge_contrast: float = 0.0, region: str = "box", skip_outside: bool = True) -> Optional[Anchor]:
    """The :class:`Anchor` that keeps ``volume`` (data units, the scene's voxel grid; negative values
    clipped to 0) as a prior during the trainer's projection training; None for weight 0.
    ``occupancy_weight`` > 0 keeps the labels its values give too (SDF models), only where they are
    trusted (:func:`label_interior`, away from the volume's edges); ``edge_contrast`` > 0 weighs each
    voxel's value by :func:`edge_trust` (less at its sharp edges). ``region`` ``hull`` keeps only the
    voxel centres inside the model's occupancy grid, the weight times their share of the voxels (the
    ``box``'s loss in expectation); without a grid it is the box. ``skip_outside``: the box's draws
    outside the occupancy grid are left out of the field's query (``False``: every draw is queried,
    the naive version the tests compare with)."""
    if region not in ("box", "hull"):
        raise KneasError(f"the anchor's region is {region!r}; choose box or hull (--stages.anchor.region)")
    if weight <= 0:
        return None
    model = trainer.model
    points, targets = voxel_targets(trainer, volume, "prior")
    mask = values = None
    if occupancy_weight > 0 and model.has_surfaces:
        thresholds = model.label_thresholds().detach().cpu().numpy()
        mask = torch.as_tensor(label_interior(np.clip(volume, 0.0, None), thresholds).reshape(-1), device=trainer.device)
    if edge_contrast > 0:
        values = torch.as_tensor(edge_trust(volume, edge_contrast).reshape(-1), device=trainer.device)
    inside = model.occupied(points) if (region == "hull" or skip_outside) else None
    out_of_grid = None
    if inside is not None and region == "hull" and bool((inside > 0).any()):
        keep = (inside > 0).nonzero()[:, 0]
        weight = float(weight) * len(keep) / len(points)
        points, targets = points[keep], targets[keep]
        mask = None if mask is None else mask[keep]
        values = None if values is None else values[keep]
    elif inside is not None and skip_outside:
        out_of_grid = inside <= 0
    return Anchor(points, targets, float(weight), int(points_per_step), float(occupancy_weight), mask, values, out_of_grid)


@dataclass
class AnchorConfig(StageConfig):
    """Keep the classical start's volume as a prior during projection training: every step adds
    ``weight`` x the MSE between ``mu`` and that volume at ``points`` random voxel centres.

    Attributes:
        weight: the prior's weight.
        weight_at_noise: the weight instead where the classical start already fits the training views
            to their noise (``classical_start.start_fit``: a noisy scan). There the views hold little the
            start has not fitted, and what training on them adds is mostly their noise (0.05 against
            0.01 on four real scans at 1e5-1e6 photons: +0.01 to +0.59 dB; on two noisy phantoms -0.17
            and -0.27). Clean scans and the phantoms, whose starts are far above their views' noise,
            keep ``weight``. ``None``: ``weight`` everywhere.
        points: voxel centres per step.
        occupancy: weight, inside the prior, of the per-material occupancy cross-entropy on the
            volume's labels, where they are trusted (two voxels or more from any other label): where
            two materials' ranges meet near a level, the projections cannot tell which material holds
            it and the MSE alone lets the neighbour take it. 0 = the MSE alone.
        edge_contrast: each voxel counts ``1 / (1 + (g / g0)^2)`` in the MSE, ``g`` the volume's
            gradient per voxel and ``g0`` this fraction of its 99.5th percentile (:func:`edge_trust`),
            so its sharp edges are held less; 0 = every voxel alike.
        region: where the centres are drawn: ``box`` (every voxel of the volume box) or ``hull``
            (only those the model's occupancy grid keeps, the weight times their share of the box).
    """

    _target = "kneas_method.stages.anchor:AnchorStage"
    name = "anchor"
    phase = "before-training"
    needs = ("classical-start",)
    weight: float = field(default=0.01, metadata=at_least(0))
    weight_at_noise: Optional[float] = field(default=0.05, metadata=at_least(0))
    points: int = field(default=4096, metadata=at_least(1, whole=True))
    occupancy: float = field(default=0.03, metadata=at_least(0))
    edge_contrast: float = field(default=0.0, metadata=at_least(0))
    region: AnchorRegion = "box"

    @property
    def other_weight_at_noise(self) -> bool:
        """Whether a start at the views' noise gets a weight of its own (``weight_at_noise``)."""
        return self.weight_at_noise is not None and self.weight_at_noise != self.weight

    def describe(self) -> str:
        labels = f", its labels away from its edges at weight {self.occupancy:g}" if self.occupancy else ""
        at_noise = f" ({self.weight_at_noise:g} where the start fits the views to their noise)" if self.other_weight_at_noise else ""
        return f"anchor: the classical start kept as a prior during training, weight {self.weight:g}{at_noise}{labels}"


def anchor_weight(config: AnchorConfig, state: RunState) -> tuple[float, bool]:
    """The anchor's weight in ``state``'s run and whether it is the at-noise one: ``(config.weight_at_noise,
    True)`` where the classical start fits the training views to their noise (``classical_start.start_fit``),
    else ``(config.weight, False)``."""
    if config.other_weight_at_noise:
        from .classical_start import start_fit

        fit = start_fit(state)
        if fit is not None and fit["at_noise"]:
            return float(config.weight_at_noise), True
    return float(config.weight), False


class AnchorStage(Stage):
    def run(self, state: RunState) -> None:
        trainer, c = state.trainer, self.config
        if state.start is None:
            return
        volume, algorithm = state.start
        weight, at_noise = anchor_weight(c, state)
        state.records[self.name] = {"weight": weight, "at_noise": at_noise}
        anchor = build_anchor(trainer, volume, weight, int(c.points), occupancy_weight=float(c.occupancy),
                              edge_contrast=float(c.edge_contrast), region=str(c.region))
        if anchor is None:
            return
        state.loss_terms["anchor"] = lambda: anchor.loss(trainer.model, trainer.generator)
        where = (f" drawn in the visual hull ({len(anchor.points):,} voxels, weight {anchor.weight:.3g} for their share)"
                 if c.region == "hull" and trainer.model.occupancy is not None else "")
        if anchor.outside is not None:
            where = (f" (the field queried only at those inside the visual hull, {1 - float(anchor.outside.float().mean()):.1%} "
                     "of the box; outside it the volume is 0 whatever the field)")
        labels = ""
        if c.edge_contrast > 0:
            labels = f", its values held less at its sharp edges (half at a step of {c.edge_contrast:g} of its range per voxel)"
        if c.occupancy > 0 and trainer.model.has_surfaces:
            labels += f", and its labels away from its edges, weight {c.occupancy:g} inside it"
        because = " (the start fits the views to their noise)" if at_noise else ""
        state.say(f"{trainer.label}: anchor: the {algorithm.upper()} volume kept as a prior, weight {weight:g}{because}, "
                  f"{c.points:,} voxel centres per step{where}{labels} (--skip-stages anchor trains on the projections alone)")
