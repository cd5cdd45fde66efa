"""The attenuation unit a neural run's losses are measured in (``CTModel.loss_scale``).

The intensity loss (SPEC §3) compares ``exp(-p)``; the warm start, the anchor, the correction fits
and the materials fit compare attenuations. Their weights were set on NAF-normalised scans, whose
volumes lie within [0, 1] /m and whose line integrals stay below ~0.1. A scanner's data
(``kneas-data import``) are in physical units, water at about 20 /m and line integrals up to ~5,
where ``exp(-p)`` is far from linear and the attenuation terms outweigh the projections by the
square of the unit (68th stop: the held-out knee in a scanner's units ended 1.25 dB below the
same scan NAF-normalised). So the losses are measured in units of :func:`loss_scale`: the FDK
volume's 99.5th percentile where that is above ``LOSS_SCALE_TOP`` (1 /m, NAF's normalised range),
else 1. NAF-normalised scans keep their losses (the FDK percentiles of the built-in scenes and of
the held-out NAF-scale ones: 0.57-0.99) or nearly (the noisy head's noise lifts its percentile to
1.05). The volume, the bounds and every output stay in data units.
"""

from __future__ import annotations

import weakref

import numpy as np

# the FDK volume's 99.5th percentile (data units, 1/m) up to which a scan is taken as NAF-normalised
LOSS_SCALE_TOP = 1.0


# id(training projections) -> (a weak reference to them, the geometry, the angles, the unit): a run asks once per
# trainer and for the wide bounds, and the FDK behind the answer is the same each time
_MEASURED: dict = {}


def loss_scale(scene) -> float:
    """``scene`` -> the unit (data units) the losses of a neural run on it are measured in: its FDK
    volume's 99.5th percentile where that is above ``LOSS_SCALE_TOP``, else 1 (module docs).
    Measured once per training projections array, angles and geometry."""
    from ..classical.reconstruct import reconstruct

    projections = scene.train.projections
    known = _MEASURED.get(id(projections))
    if known is not None and known[0]() is projections and known[1] == scene.geometry and np.array_equal(known[2], scene.train.angles):
        return known[3]
    top = float(np.percentile(np.asarray(reconstruct("fdk", scene).volume), 99.5))
    unit = top / LOSS_SCALE_TOP if top > LOSS_SCALE_TOP else 1.0
    try:
        _MEASURED[id(projections)] = (weakref.ref(projections, lambda _, key=id(projections): _MEASURED.pop(key, None)),
                                      scene.geometry, np.array(scene.train.angles), unit)
    except TypeError:  # not weakly referable (a list): measured each time
        pass
    return unit
