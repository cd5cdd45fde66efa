"""Cone- and parallel-beam CT geometry (SPEC §1), in torch, CPU and CUDA.

Units
-----
NAF/TIGRE pickles give lengths in **mm**. On load every length is divided by
1000 (mm -> m) and then multiplied by ``scale`` = 1 / (half-diagonal of the
volume box in m), so the volume fits the unit sphere. Those scaled lengths are
called **model units** here. Attenuation relates as
``mu_data [1/m] = mu_model [1/model unit] * scale``.

Pose for angle ``theta``: ``R = Rz(theta) @ Rz(pi/2) @ Rx(-pi/2)``, source at
``t = (DSO cos theta, DSO sin theta, 0)``. Detector pixel column ``i`` and row
``j`` sit at ``u = (i + 0.5 - nU/2) dU + offU``, ``v = (j + 0.5 - nV/2) dV + offV``;
the cone-beam ray is ``origin = t``, ``direction = R @ (u/DSD, v/DSD, 1)`` (not
normalised, so the ray parameter is the distance along the central axis).
Projection arrays are indexed ``[view, j, i]``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import torch

from .errors import KneasError, SceneError

MM_PER_M = 1000.0
NEAR_FAR_TOLERANCE = 0.005  # model units, as SPEC §1 (and NAF) use


def _rot_z(a: torch.Tensor) -> torch.Tensor:
    """Rotation about z by angles ``a`` [N] -> [N, 3, 3]."""
    c, s = torch.cos(a), torch.sin(a)
    z, o = torch.zeros_like(a), torch.ones_like(a)
    return torch.stack([torch.stack([c, -s, z], -1), torch.stack([s, c, z], -1), torch.stack([z, z, o], -1)], -2)


# Rz(pi/2) @ Rx(-pi/2), exact.
_BASE_ROTATION = ((0.0, 0.0, -1.0), (1.0, 0.0, 0.0), (0.0, -1.0, 0.0))


@dataclass(frozen=True)
class Geometry:
    """Scanner and volume geometry in model units (see module docstring).

    Attributes:
        mode: ``"cone"`` or ``"parallel"``.
        dsd, dso: source-detector and source-origin distances [model units].
        n_detector: ``(nU, nV)`` pixel counts (columns, rows).
        d_detector: ``(dU, dV)`` pixel sizes [model units].
        off_detector: ``(offU, offV)`` detector offsets [model units].
        n_voxel: ``(nx, ny, nz)`` volume grid size.
        d_voxel: ``(dx, dy, dz)`` voxel size [model units].
        off_origin: ``(ox, oy, oz)`` volume offset [model units].
        scale: model units per metre (``s`` of SPEC §1).
    """

    mode: str
    dsd: float
    dso: float
    n_detector: tuple[int, int]
    d_detector: tuple[float, float]
    off_detector: tuple[float, float]
    n_voxel: tuple[int, int, int]
    d_voxel: tuple[float, float, float]
    off_origin: tuple[float, float, float]
    scale: float

    # ------------------------------------------------------------------ build
    @classmethod
    def from_mm(
        cls,
        *,
        mode: str,
        DSD: float,
        DSO: float,
        nDetector,
        dDetector,
        nVoxel,
        dVoxel,
        offOrigin=(0.0, 0.0, 0.0),
        offDetector=(0.0, 0.0),
    ) -> "Geometry":
        """Build from TIGRE/NAF values in mm (the pickle's keys)."""
        if mode not in ("cone", "parallel"):
            raise SceneError(f"geometry 'mode' is {mode!r}; it must be 'cone' or 'parallel'")
        n_voxel = tuple(int(v) for v in np.asarray(nVoxel).reshape(-1))
        d_voxel_m = np.asarray(dVoxel, dtype=np.float64).reshape(-1) / MM_PER_M
        s_voxel_m = np.asarray(n_voxel, dtype=np.float64) * d_voxel_m
        scale = 1.0 / (0.5 * float(np.linalg.norm(s_voxel_m)))
        k = scale / MM_PER_M  # mm -> model units
        return cls(
            mode=mode,
            dsd=float(DSD) * k,
            dso=float(DSO) * k,
            n_detector=tuple(int(v) for v in np.asarray(nDetector).reshape(-1)[:2]),
            d_detector=tuple(float(v) * k for v in np.asarray(dDetector, dtype=np.float64).reshape(-1)[:2]),
            off_detector=tuple(float(v) * k for v in np.asarray(offDetector, dtype=np.float64).reshape(-1)[:2]),
            n_voxel=n_voxel,
            d_voxel=tuple(float(v) * scale for v in d_voxel_m),
            off_origin=tuple(float(v) * k for v in np.asarray(offOrigin, dtype=np.float64).reshape(-1)[:3]),
            scale=scale,
        )

    def to_mm(self) -> dict:
        """The geometry back in TIGRE/NAF keys and mm (inverse of :meth:`from_mm`)."""
        k = MM_PER_M / self.scale
        return {
            "mode": self.mode,
            "DSD": self.dsd * k,
            "DSO": self.dso * k,
            "nDetector": np.array(self.n_detector, dtype=np.int64),
            "dDetector": np.array(self.d_detector) * k,
            "offDetector": np.array(self.off_detector) * k,
            "nVoxel": np.array(self.n_voxel, dtype=np.int64),
            "dVoxel": np.array(self.d_voxel) * k,
            "offOrigin": np.array(self.off_origin) * k,
            "sVoxel": np.array(self.n_voxel) * np.array(self.d_voxel) * k,
            "sDetector": np.array(self.n_detector) * np.array(self.d_detector) * k,
        }

    def with_detector(self, n_detector: tuple[int, int]) -> "Geometry":
        """Same detector extent, resampled to ``n_detector`` pixels."""
        size = [n * d for n, d in zip(self.n_detector, self.d_detector)]
        return replace(self, n_detector=tuple(n_detector), d_detector=tuple(s / n for s, n in zip(size, n_detector)))

    def refined(self, factor: int) -> "Geometry":
        """The same volume box with every voxel split into ``factor^3`` cells (``factor`` >= 1)."""
        factor = int(factor)
        if factor < 1:
            raise KneasError(f"grid factor must be a positive integer, got {factor}")
        if factor == 1:
            return self
        return self.on_grid(tuple(n * factor for n in self.n_voxel))

    def on_grid(self, n_voxel) -> "Geometry":
        """The same volume box divided into ``n_voxel`` (3 positive integers) cells."""
        n_voxel = tuple(int(n) for n in n_voxel)
        if len(n_voxel) != 3 or min(n_voxel) < 1:
            raise KneasError(f"a grid needs 3 positive voxel counts, got {n_voxel}")
        box = [n * d for n, d in zip(self.n_voxel, self.d_voxel)]
        return replace(self, n_voxel=n_voxel, d_voxel=tuple(b / n for b, n in zip(box, n_voxel)))

    # ------------------------------------------------------------ conversions
    @property
    def mm_per_unit(self) -> float:
        """Millimetres per model unit."""
        return MM_PER_M / self.scale

    def model_to_mm(self, points):
        """Points in model units -> mm (same frame; works on numpy and torch)."""
        return points * self.mm_per_unit

    # ---------------------------------------------------------------- near/far
    @property
    def near_far(self) -> tuple[float, float]:
        """Ray-parameter range covering the volume [model units along the unnormalised d]."""
        sx, sy = self.n_voxel[0] * self.d_voxel[0], self.n_voxel[1] * self.d_voxel[1]
        ox, oy = self.off_origin[0], self.off_origin[1]
        r = max(math.hypot(ox + a * sx / 2, oy + b * sy / 2) for a in (-1, 1) for b in (-1, 1))
        if self.mode == "parallel":
            near, far = self.dso - r - NEAR_FAR_TOLERANCE, self.dso + r + NEAR_FAR_TOLERANCE
            return max(0.0, near), far
        return max(0.0, self.dso - r - NEAR_FAR_TOLERANCE), min(2 * self.dso, self.dso + r + NEAR_FAR_TOLERANCE)

    # ------------------------------------------------------------------- poses
    def rotations(self, angles: torch.Tensor) -> torch.Tensor:
        """Source rotations ``R(theta)`` [N, 3, 3] for angles [N] (radians)."""
        base = torch.tensor(_BASE_ROTATION, dtype=angles.dtype, device=angles.device)
        return _rot_z(angles) @ base

    def source_positions(self, angles: torch.Tensor) -> torch.Tensor:
        """Source positions ``t`` [N, 3] in model units."""
        z = torch.zeros_like(angles)
        return torch.stack([self.dso * torch.cos(angles), self.dso * torch.sin(angles), z], -1)

    def detector_uv(self, device=None, dtype=torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
        """Detector coordinates ``u`` [nV, nU] and ``v`` [nV, nU] in model units."""
        (nu, nv), (du, dv), (ou, ov) = self.n_detector, self.d_detector, self.off_detector
        i = torch.arange(nu, device=device, dtype=torch.float64)
        j = torch.arange(nv, device=device, dtype=torch.float64)
        u = (i + 0.5 - nu / 2) * du + ou
        v = (j + 0.5 - nv / 2) * dv + ov
        vv, uu = torch.meshgrid(v, u, indexing="ij")
        return uu.to(dtype), vv.to(dtype)

    def rays(
        self,
        angles,
        pixels: torch.Tensor | None = None,
        device=None,
        dtype=torch.float32,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Ray origins and (unnormalised) directions.

        Args:
            angles: view angles [N] in radians (array-like or tensor).
            pixels: optional integer tensor [N, M, 2] of ``(j, i)`` (row, column)
                pixel indices per view; default all pixels.

        Returns:
            ``(origins, directions)``, each [N, nV, nU, 3] for all pixels or
            [N, M, 3] when ``pixels`` is given, in model units.
        """
        angles = torch.as_tensor(angles, dtype=torch.float64, device=device).reshape(-1)
        rot = self.rotations(angles)  # [N,3,3]
        t = self.source_positions(angles)  # [N,3]
        u, v = self.detector_uv(device=device, dtype=torch.float64)
        if pixels is not None:
            pj, pi = pixels[..., 0].long(), pixels[..., 1].long()
            u, v = u[pj, pi], v[pj, pi]  # [N, M]
            rot_b = rot[:, None]
            t_b = t[:, None]
        else:
            u, v = u.expand(len(angles), *u.shape), v.expand(len(angles), *v.shape)
            rot_b = rot[:, None, None]
            t_b = t[:, None, None]
        ones, zeros = torch.ones_like(u), torch.zeros_like(u)
        if self.mode == "cone":
            local = torch.stack([u / self.dsd, v / self.dsd, ones], -1)
            dirs = (rot_b @ local[..., None])[..., 0]
            origins = t_b.expand_as(dirs)
        else:
            local_dir = torch.stack([zeros, zeros, ones], -1)
            dirs = (rot_b @ local_dir[..., None])[..., 0]
            offset = (rot_b @ torch.stack([u, v, zeros], -1)[..., None])[..., 0]
            origins = t_b + offset
        return origins.to(dtype).contiguous(), dirs.to(dtype).contiguous()

    # ------------------------------------------------------------------ volume
    def voxel_axes(self, device=None, dtype=torch.float32) -> list[torch.Tensor]:
        """Voxel-centre coordinates per axis, ``[nx]``, ``[ny]``, ``[nz]``, model units."""
        axes = []
        for n, d, o in zip(self.n_voxel, self.d_voxel, self.off_origin):
            size = n * d
            axes.append(torch.linspace(-size / 2 + d / 2, size / 2 - d / 2, n, dtype=torch.float64, device=device).add(o).to(dtype))
        return axes

    def voxel_centres(self, device=None, dtype=torch.float32) -> torch.Tensor:
        """Voxel centres [nx, ny, nz, 3]; ``image[a, b, c]`` sits at ``(x_a, y_b, z_c)``."""
        x, y, z = self.voxel_axes(device=device, dtype=dtype)
        return torch.stack(torch.meshgrid(x, y, z, indexing="ij"), -1)

    @property
    def volume_half_size(self) -> tuple[float, float, float]:
        """Half the volume box's side lengths [model units]."""
        return tuple(n * d / 2 for n, d in zip(self.n_voxel, self.d_voxel))
