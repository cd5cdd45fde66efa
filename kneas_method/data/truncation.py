"""Whether a scan's object goes on beyond the reconstructed box along the rotation axis.

The detector's first and last rows see the box's ends. Where they see the object (line integrals
above the noise-aware air threshold, ``datamanagers.ct.noise_air_threshold``) in most views, the
object continues beyond the box along the axis (a leg, a spine), and every method, classical or
neural, puts the attenuation of what lies outside into the box's end slices. Measured in the 68th
stop on the held-out ``knee-long`` (the knee with the leg 130 mm longer than the box at both ends):
its first and last rows see the object in 47 % of their pixels in every view, against at most 2 %
(noise) on the thirteen other scans; ASD-POCS's end slices reach 22.8 /m where the leg's most is
0.86, and k-neas ends at 12.7 dB over the whole box, 31.7 dB eight slices or more from its ends.
"""

from __future__ import annotations

import numpy as np

# a row sees the object where at least this share of its pixels is above the air threshold
ROW_OBJECT_SHARE = 0.1
# a scan is truncated along the axis where its first or last row sees the object in this share of the views
TRUNCATED_VIEW_SHARE = 0.5


def axial_truncation(projections, air_threshold: float) -> float:
    """``[N, nV, nU]`` line integrals (rows along the rotation axis) -> the share of views whose
    first or last detector row sees the object (``ROW_OBJECT_SHARE`` of its pixels above
    ``air_threshold``)."""
    p = np.asarray(projections)
    first = (p[:, 0, :] > air_threshold).mean(axis=1)
    last = (p[:, -1, :] > air_threshold).mean(axis=1)
    return float(np.mean((first >= ROW_OBJECT_SHARE) | (last >= ROW_OBJECT_SHARE)))


def truncation_warning(scene, air_threshold: float | None = None) -> str | None:
    """One line for the user when ``scene``'s object goes on beyond its box along the axis, else None;
    ``air_threshold``: the training projections' noise-aware one where the caller has it already."""
    from ..datamanagers.ct import noise_air_threshold

    p = np.asarray(scene.train.projections)
    share = axial_truncation(p, noise_air_threshold(p)[0] if air_threshold is None else air_threshold)
    if share < TRUNCATED_VIEW_SHARE:
        return None
    return (f"the object reaches the detector's first or last row in {round(share * len(p))} of {len(p)} training views: it goes on "
            "beyond the reconstructed box along the rotation axis, and every method puts what lies outside into the box's end "
            "slices; do not trust the slices near the ends, or reconstruct a box long enough to hold the whole object")
