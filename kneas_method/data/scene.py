"""The typed scene every other part of kneas works on."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Callable, Optional

import numpy as np

from ..errors import SceneError
from ..geometry import Geometry


@dataclass
class Views:
    """A set of projections.

    Attributes:
        angles: [N] radians.
        projections: [N, nV, nU] float32 line integrals ``∫ mu_data dl`` (l in m).
    """

    angles: np.ndarray
    projections: np.ndarray

    def __len__(self) -> int:
        return int(len(self.angles))

    def subset(self, index) -> "Views":
        return Views(self.angles[index], self.projections[index])


@dataclass
class Scene:
    """A CT scene: geometry, training and held-out views, and ground truth if known.

    Attributes:
        name: short name (``foot``, or the pickle's stem).
        geometry: scanner/volume geometry in model units.
        train, val: training and held-out views; ``val`` may hold 0 views (measured
            scans from ``kneas-data import``: evaluation then holds out training views).
        image: ground-truth attenuation [nx, ny, nz] in data units (NAF: [0, 1]), or None
            (measured scans have no ground truth).
        labels: ground-truth material labels [nx, ny, nz] (0 = air), built-in scenes only.
        materials: names of the label values 1..M (built-in scenes only).
        membership: ``f(points_model [P, 3]) -> labels [P]`` exact material label at
            points in model units (built-in scenes only; for surface metrics).
        meta: the pickle's other keys (``accuracy``, ``filter``, ``convert``, ...).
        source: where it came from (a path, or ``built-in:foot``).
    """

    name: str
    geometry: Geometry
    train: Views
    val: Views
    image: Optional[np.ndarray] = None
    labels: Optional[np.ndarray] = None
    materials: tuple[str, ...] = ()
    membership: Optional[Callable[[Any], Any]] = None
    meta: dict = field(default_factory=dict)
    source: str = ""

    def subsample_views(self, n: int | None) -> "Scene":
        """Keep ``n`` training views spread uniformly over the training set (the
        paper's 5/10/20/50-view protocol); held-out views (possibly none) are unchanged."""
        total = len(self.train)
        if n is None or n == total:
            return self
        if n < 1 or n > total:
            raise SceneError(f"--views {n} is out of range: the scene has {total} training views; choose 1..{total}")
        index = np.unique(np.round(np.linspace(0, total - 1, n)).astype(int)) if n > 1 else np.array([0])
        if len(index) != n:  # cannot happen for n <= total, kept as a guard
            index = np.arange(0, total, total / n).astype(int)[:n]
        return replace(self, train=self.train.subset(index))
