"""Surface smoothness of signed distance fields: how far the normals turn within a short step.

Used by the band correction's fits (``stages.volume_fit.fit_in_region``, ``--stages.correction.curvature``):
the views leave part of an edge's position free (what 50 projections do not see), and the fit
of each pass fills that part from the field's own prior. This term makes that prior prefer
surfaces whose normals turn slowly, i.e. smooth surfaces, over the voxel-scale ripples a
correction's noise leaves. The naive per-point version is kept as the test oracle in
``tests/test_losses.py``.
"""

from __future__ import annotations

import torch


def surface_smoothness(grads: torch.Tensor, grads_step: torch.Tensor, distances: torch.Tensor, width: float) -> torch.Tensor:
    """``mean over P, K of w · ‖∇d_k(x) − ∇d_k(x + δ)‖²``, ``w = exp(−(d_k(x) / width)²)``.

    Args:
        grads: [P, K, 3] distance gradients at the points ``x``.
        grads_step: [P, K, 3] the same at ``x + δ`` (``δ`` a short step, e.g. one voxel in a random direction).
        distances: [P, K] signed distances at ``x`` (model units); only where a surface is near
            (within about ``width``) does a point count. No gradient flows through the weights.
        width: model units (e.g. one voxel).

    Returns:
        scalar; 0 for planar surfaces, growing with the surfaces' curvature (about ``(|δ| κ)²``).
    """
    w = torch.exp(-(distances.detach() / float(width)) ** 2)
    return (w * ((grads - grads_step) ** 2).sum(-1)).mean()
