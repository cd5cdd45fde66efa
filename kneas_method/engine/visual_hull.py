"""A fresh model's empty-space grid from the training views (``model.occupancy_grid``)."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from ..datamanagers.ct import noise_air_threshold
from ..occupancy import box_of, visual_hull

# Detector pixels: noisy views are averaged over squares this many pixels across before the air test,
# which cuts white pixel noise this many times and widens an object by at most half of it.
AIR_TEST_SQUARE = 7


def air_test_views(projections) -> tuple[np.ndarray, float, int]:
    """The views ``[N, nV, nU]`` the hull's air test reads, its threshold, and the width of the square
    each pixel was averaged over (0: none). Where the views carry noise (``noise_air_threshold`` finds some), a single
    noisy pixel cannot tell a thin or faint stretch of tissue from air: 3 noise sigmas of a 1e5-photon
    real chest's pixel are the line integral of 9 voxels of fat. So each pixel is first replaced by
    the mean of the ``AIR_TEST_SQUARE`` x ``AIR_TEST_SQUARE`` pixels around it (those inside the
    detector) and the threshold read off the averaged views' own noise. Noise-free views are read as
    they are (threshold 0: any attenuation is material)."""
    views = np.asarray(projections, dtype=np.float32)
    threshold, sigma = noise_air_threshold(views)
    if sigma <= 0:
        return views, threshold, 0
    smoothed = F.avg_pool2d(torch.as_tensor(views)[:, None], AIR_TEST_SQUARE, stride=1, padding=AIR_TEST_SQUARE // 2,
                            count_include_pad=False)[:, 0].numpy()
    return smoothed, noise_air_threshold(smoothed)[0], AIR_TEST_SQUARE


def set_visual_hull(model, scene, label: str = "model", say=None) -> None:
    """Give ``model`` its empty-space grid: the visual hull of the scene's training views
    (``occupancy.visual_hull``; air = at or below the noise-aware air threshold of
    ``datamanagers.ct.noise_air_threshold``, read on views averaged over a square of pixels first where they are noisy:
    :func:`air_test_views`); ``say`` receives one line about it."""
    views, threshold, smoothing = air_test_views(scene.train.projections)
    occupied = visual_hull(scene.geometry, scene.train.angles, views,
                           resolution=int(model.config.occupancy_resolution), air_threshold=threshold)
    model.set_occupancy(occupied, *box_of(scene.geometry))
    if say is not None:
        read = f" (air read on the views' means over {smoothing} x {smoothing} pixels: they are noisy)" if smoothing else ""
        say(f"{label}: empty space: the visual hull of the {len(scene.train)} training views keeps "
            f"{100 * float(occupied.float().mean()):.1f} % of the volume box ({occupied.shape[0]}^3 cells){read}")
