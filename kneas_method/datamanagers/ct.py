"""CT datamanager: a scene -> training batches on the device (SPEC §3).

One step = one training projection. Each epoch visits the training views in a
fresh random permutation; for the current view it draws ``num_object`` object
pixels and ``num_air`` air pixels without replacement (``samplers.pixels``) and
builds their rays with ``geometry.rays``.

Object vs air: SPEC §1 calls ``p > 0`` object and ``p == 0`` air, which holds for
noise-free data. Measured (and TIGRE-noised) line integrals scatter around 0 in
air, so the split is ``p > τ`` / ``p <= τ`` with ``τ`` estimated from the data
(:func:`noise_air_threshold`: 3 noise sigmas, the sigma read off the negative
values, which only noise produces). Noise-free data have no negative values and
``τ = 0``: exactly SPEC §1. Negative values stay in the data: object rays lie
above ``τ >= 0`` and the floater loss on air rays targets intensity 1 without
reading ``p``, so no method here needs them clipped. All
randomness comes from one seeded ``torch.Generator`` (CPU), and
:meth:`CTDataManager.state_dict` / :meth:`load_state_dict` capture it, so a
resumed run draws exactly the batches a straight run would.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Optional

import numpy as np
import torch

from ..config import InstantiateConfig, at_least, check_ranges
from ..errors import CheckpointError, ConfigError
from ..data.scene import Scene


AIR_NOISE_SIGMAS = 3.0
_ANNOUNCED: set[str] = set()


def noise_air_threshold(projections, sigmas: float = AIR_NOISE_SIGMAS, max_samples: int = 2_000_000) -> tuple[float, float]:
    """Noise-aware air threshold of line integrals.

    Noise makes air pixels scatter symmetrically about 0 while attenuation only
    adds, so the negative values are (half of) the noise in air. Their robust
    scale ``sigma = median(|p|, p < 0) / 0.6745`` (the median of a half-normal)
    ignores a few outliers; the threshold is ``sigmas * sigma``.

    Args:
        projections: [N, nV, nU] line integrals.
        sigmas: how many noise sigmas above 0 still count as air.

    Returns:
        ``(threshold, sigma)``; ``(0.0, 0.0)`` when no value is negative (noise-free data).
    """
    flat = np.asarray(projections).reshape(-1)
    if flat.size > max_samples:
        flat = flat[:: int(math.ceil(flat.size / max_samples))]
    neg = flat[flat < 0].astype(np.float64)
    if neg.size == 0:
        return 0.0, 0.0
    sigma = float(np.median(-neg)) / 0.6745
    return float(sigmas * sigma), sigma


def _announce(msg: str) -> None:
    """Print ``note: msg`` once per process (the prior and main stages build a datamanager each)."""
    if msg in _ANNOUNCED:
        return
    _ANNOUNCED.add(msg)
    from ..cli.common import console

    console.print(f"note: {msg}", soft_wrap=True, markup=False)


@dataclass
class CTDataManagerConfig(InstantiateConfig):
    """Rays per training step.

    Attributes:
        pixel_sampler: ``kneas.samplers`` name of the pixel sampler.
        num_object_rays: rays per step through object pixels (paper 512); None = the preset's.
        num_air_rays: rays per step through air pixels (paper 128); None = the preset's.
    """

    _target = "kneas_method.datamanagers.ct:CTDataManager"
    pixel_sampler: str = "object-air-pixels"
    num_object_rays: Optional[int] = field(default=None, metadata=at_least(0, whole=True))
    num_air_rays: Optional[int] = field(default=None, metadata=at_least(0, whole=True))

    def check(self, prefix: str) -> None:
        check_ranges(self, prefix)
        if self.num_object_rays is not None and self.num_air_rays is not None and self.num_object_rays + self.num_air_rays < 1:
            raise ConfigError(f"--{prefix}num-object-rays and --{prefix}num-air-rays are both 0; give at least one ray per step")


class CTDataManager:
    """Batches of rays for training and the held-out views for evaluation.

    Args:
        config: :class:`CTDataManagerConfig`.
        scene: the scene.
        device: where batches live.
        seed: seeds the sampling generator.
        views: keep this many training views, spread uniformly (``Scene.subsample_views``; None = all).
    """

    def __init__(self, config: CTDataManagerConfig, *, scene: Scene, device="cpu", seed: int = 0, views: Optional[int] = None):
        from ..model import build_component

        self.config = config
        self.scene = scene.subsample_views(views)
        self.geometry = self.scene.geometry
        self.device = torch.device(device)
        options = {}
        if config.num_object_rays is not None:
            options["num_object"] = config.num_object_rays
        if config.num_air_rays is not None:
            options["num_air"] = config.num_air_rays
        sampler_cfg = build_component("samplers", config.pixel_sampler, options)
        train_p = np.asarray(self.scene.train.projections)
        self.air_threshold, self.noise_sigma = noise_air_threshold(train_p)
        self.notes: list[str] = []
        if self.air_threshold > 0:
            negative = float(np.mean(train_p < 0)) * 100
            self.notes.append(
                f"noisy line integrals ({negative:.1f} % of training pixels below 0, min {float(train_p.min()):.3g}): "
                f"air = p <= {self.air_threshold:.3g} (3 x noise sigma {self.noise_sigma:.3g}), object above; "
                "negative values are kept (no method needs them clipped)"
            )
            for note in self.notes:
                _announce(note)
        self.pixel_sampler = sampler_cfg.setup(projections=train_p, air_threshold=self.air_threshold)
        self.train_angles = torch.as_tensor(np.asarray(self.scene.train.angles), dtype=torch.float64)
        self.train_projections = torch.as_tensor(np.asarray(self.scene.train.projections), dtype=torch.float32).to(self.device)
        self.near, self.far = self.geometry.near_far
        self.generator = torch.Generator(device="cpu")
        self.generator.manual_seed(int(seed))
        self.epoch = 0
        self.position = 0
        self.permutation = torch.randperm(self.num_train_views, generator=self.generator)

    @property
    def num_train_views(self) -> int:
        return len(self.scene.train)

    @property
    def steps_per_epoch(self) -> int:
        """One step per training projection."""
        return self.num_train_views

    def next_train(self) -> dict[str, Any]:
        """The next training batch.

        Returns a dict: ``origins`` [R, 3], ``directions`` [R, 3] (model units),
        ``projections`` [R] measured line integrals (air rays may be slightly
        negative on noisy data), ``is_air`` [R] bool (object
        rays first, then air rays), ``pixels`` [R, 2] ``(j, i)``, ``view`` (index
        into the training views), ``epoch``, ``near``, ``far`` (model units).
        """
        if self.position >= len(self.permutation):
            self.epoch += 1
            self.position = 0
            self.permutation = torch.randperm(self.num_train_views, generator=self.generator)
        view = int(self.permutation[self.position])
        epoch = self.epoch
        self.position += 1
        obj, air = self.pixel_sampler.sample(view, self.generator)
        pixels = torch.cat([obj, air], 0)
        origins, directions = self.geometry.rays(self.train_angles[view : view + 1], pixels=pixels[None].to(self.device), device=self.device)
        pj, pi = pixels[:, 0].to(self.device), pixels[:, 1].to(self.device)
        is_air = torch.zeros(len(pixels), dtype=torch.bool, device=self.device)
        is_air[len(obj) :] = True
        return {
            "origins": origins[0],
            "directions": directions[0],
            "projections": self.train_projections[view, pj, pi],
            "is_air": is_air,
            "pixels": pixels.to(self.device),
            "view": view,
            "epoch": epoch,
            "near": self.near,
            "far": self.far,
        }

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict[str, Any]:
        """Sampler state: epoch, position in the permutation, the permutation, generator state."""
        return {
            "epoch": self.epoch,
            "position": self.position,
            "permutation": self.permutation.tolist(),
            "generator": self.generator.get_state(),
            "num_train_views": self.num_train_views,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if int(state.get("num_train_views", -1)) != self.num_train_views:
            raise CheckpointError(
                f"the checkpoint's sampler state is for {state.get('num_train_views')} training views but this run has "
                f"{self.num_train_views}; resume with the same scene and --views"
            )
        self.epoch = int(state["epoch"])
        self.position = int(state["position"])
        self.permutation = torch.as_tensor(state["permutation"], dtype=torch.long)
        self.generator.set_state(torch.as_tensor(state["generator"], dtype=torch.uint8))
