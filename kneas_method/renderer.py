"""Beer–Lambert renderer (SPEC §3) as small pure functions.

``I = exp(−Σ_n mu(x_n) · δ_n)`` with ``δ_n = (t_{n+1} − t_n) · ‖d‖`` and the
last ``δ = 0``. Ray parameters ``t`` and directions ``d`` are in model units;
attenuation ``mu`` is in data units (1/m), so lengths are converted to metres
with ``δ_m = δ_model / scale`` (``scale`` = model units per metre, from the
geometry). The line integral then equals the data projection value ``p``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class RenderOutput:
    """Rendered rays.

    Attributes:
        intensity: [R] ``exp(−line_integral)``.
        line_integral: [R] ``Σ mu·δ`` (unit-free; compare with projections ``p``).
    """

    intensity: torch.Tensor
    line_integral: torch.Tensor


def sample_points(origins: torch.Tensor, directions: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Points [R, S, 3] = origins [R, 3] + t [R, S] · directions [R, 3] (model units)."""
    return origins[:, None, :] + t[..., None] * directions[:, None, :]


def segment_lengths(t: torch.Tensor, directions: torch.Tensor, scale: float = 1.0) -> torch.Tensor:
    """``δ`` [R, S] in metres: ``(t_{n+1} − t_n)·‖d‖ / scale``, last entry 0."""
    dt = torch.cat([t[:, 1:] - t[:, :-1], torch.zeros_like(t[:, :1])], dim=-1)
    return dt * directions.norm(dim=-1, keepdim=True) / scale


def beer_lambert(mu: torch.Tensor, delta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """mu [R, S] (1/m), delta [R, S] (m) -> (intensity [R], line_integral [R])."""
    line = (mu * delta).sum(-1)
    return torch.exp(-line), line
