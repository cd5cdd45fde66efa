"""A fresh model's empty-space grid from the training views (``model.occupancy_grid``)."""

from __future__ import annotations

import numpy as np

from ..datamanagers.ct import noise_air_threshold
from ..occupancy import box_of, visual_hull


def set_visual_hull(model, scene, label: str = "model", say=None) -> None:
    """Give ``model`` its empty-space grid: the visual hull of the scene's training views
    (``occupancy.visual_hull``; air = at or below the noise-aware air threshold of
    ``datamanagers.ct.noise_air_threshold``); ``say`` receives one line about it."""
    threshold, _ = noise_air_threshold(np.asarray(scene.train.projections))
    occupied = visual_hull(scene.geometry, scene.train.angles, scene.train.projections,
                           resolution=int(model.config.occupancy_resolution), air_threshold=threshold)
    model.set_occupancy(occupied, *box_of(scene.geometry))
    if say is not None:
        say(f"{label}: empty space: the visual hull of the {len(scene.train)} training views keeps "
            f"{100 * float(occupied.float().mean()):.1f} % of the volume box ({occupied.shape[0]}^3 cells)")
