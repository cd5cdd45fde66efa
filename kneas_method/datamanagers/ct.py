"""CT datamanager: a scene -> training batches on the device (SPEC §3).

One step = one training projection. Each epoch visits the training views in a
fresh random permutation; for the current view it draws ``num_object`` object
pixels (``p > 0``) and ``num_air`` air pixels (``p == 0``) without replacement
(``samplers.pixels``) and builds their rays with ``geometry.rays``. All
randomness comes from one seeded ``torch.Generator`` (CPU), and
:meth:`CTDataManager.state_dict` / :meth:`load_state_dict` capture it, so a
resumed run draws exactly the batches a straight run would.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Optional

import numpy as np
import torch

from ..config import InstantiateConfig
from ..errors import CheckpointError
from ..data.scene import Scene


@dataclass
class CTDataManagerConfig(InstantiateConfig):
    """Attributes:
    pixel_sampler: ``kneas.samplers`` name of the pixel sampler.
    num_object_rays / num_air_rays: rays per step from object / air pixels
        (paper 512 / 128); None = the preset's.
    """

    _target = "kneas_method.datamanagers.ct:CTDataManager"
    pixel_sampler: str = "object-air-pixels"
    num_object_rays: Optional[int] = None
    num_air_rays: Optional[int] = None


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
        self.pixel_sampler = sampler_cfg.setup(projections=self.scene.train.projections)
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
        ``projections`` [R] measured line integrals, ``is_air`` [R] bool (object
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
