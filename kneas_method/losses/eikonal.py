"""Eikonal regularisation (SPEC §3): ``mean((‖∇_x d_k‖ − 1)^2)`` averaged over the K fields.

Two ways to get the spatial gradient of the distances (model units):

- ``autograd``: exact, ``torch.autograd.grad(..., create_graph=True)``; when the
  caller already evaluated ``distances`` on ``points`` (with ``points.requires_grad``)
  no extra forward pass is made.
- ``finite-difference``: central differences with step ``h`` (model units) along
  each axis: 6 extra distance evaluations per point, but only first-order
  autograd through the network (the only option with tinycudann, whose hash
  grid has no second derivative). Default ``h``: half the finest encoding cell.

How the exact gradients are obtained (fastest first; all give the same values):

1. the caller passes ``grads`` computed in forward mode alongside the distances
   (``SDFField.forward_with_gradients``, torch hash grid): no double backward at all;
2. ``autograd``: one ``torch.autograd.grad(..., is_grads_batched=True)`` call for
   all K distance fields (the straightforward K separate double backwards are kept
   as the test oracle and benchmark reference in ``benchmarks/naive.py``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch

from ..config import InstantiateConfig
from ..errors import ConfigError

MODES = ("autograd", "finite-difference")
DistanceFn = Callable[[torch.Tensor], torch.Tensor]


@dataclass
class EikonalLossConfig(InstantiateConfig):
    """Attributes:
    mode: "autograd" or "finite-difference".
    fd_step: finite-difference step in model units; None = half the finest grid cell of the encoding.
    """

    _target = "kneas_method.losses.eikonal:EikonalLoss"
    mode: str = "autograd"
    fd_step: float | None = None


class EikonalLoss:
    """``loss(distance_fn, points [P, 3], distances [P, K] | None, mask [P] | None) -> scalar``.

    ``distance_fn(points [P, 3]) -> [P, K]`` signed distances. ``mask`` keeps
    points where the eikonal term applies (e.g. inside the encoding's box).
    """

    def __init__(self, config: EikonalLossConfig, *, default_step: float = 1e-3):
        if config.mode not in MODES:
            raise ConfigError(f"eikonal mode {config.mode!r} is unknown; choose one of {', '.join(MODES)}")
        self.config = config
        self.step = float(config.fd_step) if config.fd_step is not None else float(default_step)
        if not self.step > 0:
            raise ConfigError(f"eikonal fd_step must be > 0 (model units), got {self.step}")

    def gradients(self, distance_fn: DistanceFn, points: torch.Tensor, distances: torch.Tensor | None = None) -> torch.Tensor:
        """Spatial gradients [P, K, 3] of the distances at ``points``."""
        if self.config.mode == "autograd":
            if distances is None or not points.requires_grad:
                points = points.detach().requires_grad_(True)
                with torch.enable_grad():
                    distances = distance_fn(points)
            K = distances.shape[-1]
            if K == 1:
                (g,) = torch.autograd.grad(distances.sum(), points, create_graph=True)
                return g[:, None, :]
            eye = torch.eye(K, device=distances.device, dtype=distances.dtype)
            tangents = eye[:, None, :].expand(K, *distances.shape).contiguous()  # [K, P, K]
            (g,) = torch.autograd.grad(distances, points, tangents, create_graph=True, is_grads_batched=True)
            return g.transpose(0, 1)  # [P, K, 3]
        h = self.step
        x = points.detach()
        offsets = torch.eye(3, device=x.device, dtype=x.dtype) * h  # [3, 3]
        probe = torch.cat([x[:, None, :] + offsets, x[:, None, :] - offsets], dim=1)  # [P, 6, 3]
        d = distance_fn(probe.reshape(-1, 3)).reshape(len(x), 6, -1)  # [P, 6, K]
        return ((d[:, :3] - d[:, 3:]) / (2 * h)).transpose(1, 2)  # [P, K, 3]

    def __call__(
        self,
        distance_fn: DistanceFn,
        points: torch.Tensor,
        distances: torch.Tensor | None = None,
        mask: torch.Tensor | None = None,
        grads: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """The loss; ``grads [P, K, 3]`` (already computed, e.g. in forward mode) skips :meth:`gradients`."""
        if grads is None:
            grads = self.gradients(distance_fn, points, distances)
        return self.penalty(grads, mask)

    @staticmethod
    def penalty(grads: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        """``mean((‖grads‖ − 1)^2)`` over the points kept by ``mask`` [P] and the K fields."""
        norm = torch.sqrt((grads**2).sum(-1) + 1e-12)  # [P, K]; safe at a zero gradient
        pen = (norm - 1.0) ** 2
        if mask is None:
            return pen.mean() if pen.numel() else grads.new_zeros(())
        # masked mean without boolean indexing (no nonzero / host sync); 0 when nothing is kept
        w = mask.to(pen.dtype)
        return (pen * w[:, None]).sum() / (w.sum() * pen.shape[-1]).clamp_min(1.0)
