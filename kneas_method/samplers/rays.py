"""Ray samplers: sample positions ``t`` along rays (SPEC §3).

Training: stratified, S bins of equal width between ``near`` and ``far``, one
point uniformly inside each bin. Evaluation: S evenly spaced points from
``near`` to ``far`` inclusive. ``t`` is the ray parameter along the
unnormalised direction (model units along the central axis, see geometry).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..config import InstantiateConfig


def _as_column(v, n_rays: int, device, dtype) -> torch.Tensor:
    v = torch.as_tensor(v, device=device, dtype=dtype)
    return v.reshape(-1, 1).expand(n_rays, 1) if v.numel() == 1 else v.reshape(n_rays, 1)


@dataclass
class StratifiedRaySamplerConfig(InstantiateConfig):
    _target = "kneas_method.samplers.rays:StratifiedRaySampler"


class StratifiedRaySampler:
    """``sample(near, far, n_rays, n_samples, stratified, ...) -> t [R, S]`` (sorted ascending)."""

    def __init__(self, config: StratifiedRaySamplerConfig | None = None):
        self.config = config

    def sample(
        self,
        near,
        far,
        n_rays: int,
        n_samples: int,
        stratified: bool,
        *,
        device=None,
        dtype=torch.float32,
        generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        """Args: near, far: scalars or [R] (model units); stratified: jitter inside bins."""
        near = _as_column(near, n_rays, device, dtype)
        far = _as_column(far, n_rays, device, dtype)
        if stratified:
            edges = torch.linspace(0.0, 1.0, n_samples + 1, device=device, dtype=dtype)
            # drawn on the generator's device (the trainer's is a CPU one, so that a run draws the same
            # jitter on any device and resumes anywhere), then moved to the rays'
            u = torch.rand(n_rays, n_samples, dtype=dtype, generator=generator,
                           device=generator.device if generator is not None else device).to(device)
            frac = edges[:-1] + (edges[1:] - edges[:-1]) * u
        else:
            frac = torch.linspace(0.0, 1.0, n_samples, device=device, dtype=dtype).expand(n_rays, n_samples)
        return near + (far - near) * frac
