"""The attenuation unit a neural run's losses are measured in (``CTModel.loss_scale``).

The intensity loss (SPEC §3) compares ``exp(-p)``; the warm start, the anchor, the correction fits
and the materials fit compare attenuations. Their weights were set on NAF-normalised scans, whose
volumes lie within [0, 1] /m and whose line integrals stay below ~0.1. A scanner's data
(``kneas-data import``) are in physical units, water at about 20 /m and line integrals up to ~5,
where ``exp(-p)`` is far from linear and the attenuation terms outweigh the projections by the
square of the unit. So the losses are measured in units of :func:`loss_scale`: the FDK volume's
99.5th percentile where that is above ``LOSS_SCALE_TOP`` (1 /m, NAF's normalised range), else 1.
NAF-normalised scans keep their losses. The volume, the bounds and every output stay in data units.
The pipeline computes it once per run and hands it to every model it trains.
"""

from __future__ import annotations

import numpy as np

# the FDK volume's 99.5th percentile (data units, 1/m) up to which a scan is taken as NAF-normalised
LOSS_SCALE_TOP = 1.0


def loss_scale(scene) -> float:
    """``scene`` -> the unit (data units) the losses of a neural run on it are measured in: its FDK
    volume's 99.5th percentile where that is above ``LOSS_SCALE_TOP``, else 1 (module docs)."""
    from ..classical.reconstruct import reconstruct

    top = float(np.percentile(np.asarray(reconstruct("fdk", scene).volume), 99.5))
    return top / LOSS_SCALE_TOP if top > LOSS_SCALE_TOP else 1.0
