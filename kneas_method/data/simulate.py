"""Simulate NAF-style cone-beam scenes from built-in phantoms or user volumes.

Conventions follow NAF's data generator: training angles evenly spaced over the
scan range (endpoint excluded), held-out angles uniformly random in it (seeded),
optional Poisson + Gaussian detector noise, the geometry written as NAF/TIGRE keys
in mm and the projections as line integrals with lengths in metres.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass
from typing import Any, Callable, Optional, Sequence, Union

import numpy as np

from ..errors import ConfigError, SceneError
from ..geometry import Geometry
from .scene import Scene, Views

# Bumped whenever the simulator's output for a given config changes (scene caches key on it).
SIMULATOR_VERSION = 2  # 2: simulate_from_volume projects with the Joseph projector of kneas_method.classical
# Bumped when the noise model's output changes; only scenes simulated with noise key on it.
# 2: negative line integrals in air are kept (as TIGRE's noise gives), no longer clipped at 0.
NOISE_MODEL_VERSION = 2
DETECTOR_MARGIN = 0.04  # fraction of the magnified volume extent added to the detector
DEFAULT_N_DETECTOR = 128

Progress = Optional[Callable[[str], None]]


@dataclass
class SimulationConfig:
    """How to simulate a scene (lengths in mm, angles in degrees).

    Attributes:
        n_voxel: volume grid size per axis (int for a cube, or (nx, ny, nz)); for
            :func:`simulate_from_volume` the volume's own shape wins.
        voxel_mm: voxel size [mm] (float or (dx, dy, dz)).
        dsd_mm, dso_mm: source-detector and source-origin distances [mm].
        n_detector: detector pixels per side (square); None = 128.
        detector_mm: detector pixel size [mm]; None = just large enough to see the
            whole volume box from every angle (plus a small margin).
        n_train, n_val: number of training and held-out views.
        total_angle_deg, start_angle_deg: scan range [degrees].
        random_val_angles: held-out angles uniformly random in the scan range (as NAF);
            otherwise evenly spaced halfway between training angles.
        noise: add Poisson (``photons`` per pixel) + Gaussian (``electronic_sigma``
            counts) noise, as NAF's generator does.
        seed: random seed (held-out angles, noise).
        mode: ``"cone"`` or ``"parallel"``.
    """

    n_voxel: Union[int, Sequence[int]] = 128
    voxel_mm: Union[float, Sequence[float]] = 2.0
    dsd_mm: float = 1500.0
    dso_mm: float = 1000.0
    n_detector: Optional[int] = None
    detector_mm: Optional[float] = None
    n_train: int = 50
    n_val: int = 50
    total_angle_deg: float = 180.0
    start_angle_deg: float = 0.0
    random_val_angles: bool = True
    noise: bool = False
    photons: float = 1e5
    electronic_sigma: float = 10.0
    seed: int = 0
    mode: str = "cone"

    def validate(self) -> None:
        """Raise ConfigError (one line) for an impossible setting."""
        if self.mode not in ("cone", "parallel"):
            raise ConfigError(f"mode is {self.mode!r}; choose 'cone' or 'parallel'")
        for name in ("n_train", "n_val"):
            if int(getattr(self, name)) < 1:
                raise ConfigError(f"{name} is {getattr(self, name)}; it must be at least 1")
        nv = np.atleast_1d(np.asarray(self.n_voxel))
        if nv.size not in (1, 3) or np.any(nv < 1):
            raise ConfigError(f"n_voxel is {self.n_voxel}; give one positive size or three")
        vm = np.atleast_1d(np.asarray(self.voxel_mm, dtype=float))
        if vm.size not in (1, 3) or np.any(~np.isfinite(vm)) or np.any(vm <= 0):
            raise ConfigError(f"voxel_mm is {self.voxel_mm}; give one positive size in mm or three")
        if not (self.dso_mm > 0 and self.dsd_mm > 0):
            raise ConfigError(f"dsd_mm={self.dsd_mm} and dso_mm={self.dso_mm} must both be positive")
        if self.mode == "cone" and self.dsd_mm <= self.dso_mm:
            raise ConfigError(f"dsd_mm ({self.dsd_mm}) must be larger than dso_mm ({self.dso_mm}): the detector sits behind the rotation axis")
        if self.n_detector is not None and int(self.n_detector) < 1:
            raise ConfigError(f"n_detector is {self.n_detector}; it must be a positive pixel count")
        if self.detector_mm is not None and not self.detector_mm > 0:
            raise ConfigError(f"detector_mm is {self.detector_mm}; it must be a positive pixel size in mm")
        if not self.total_angle_deg > 0:
            raise ConfigError(f"total_angle_deg is {self.total_angle_deg}; it must be positive")
        if self.noise and not self.photons > 0:
            raise ConfigError(f"photons is {self.photons}; it must be positive when noise is on")
        if self.electronic_sigma < 0:
            raise ConfigError(f"electronic_sigma is {self.electronic_sigma}; it must be >= 0")

    def to_dict(self) -> dict:
        """Plain-data dict (lists for sequences) for scene metadata and cache keys."""
        out = asdict(self)
        for k, v in out.items():
            if isinstance(v, (tuple, list, np.ndarray)):
                out[k] = [x.item() if hasattr(x, "item") else x for x in v]
        return out


def _triple(value, kind) -> tuple:
    arr = np.atleast_1d(np.asarray(value)).reshape(-1)
    if arr.size == 1:
        arr = np.repeat(arr, 3)
    return tuple(kind(v) for v in arr)


def magnified_extent_mm(cfg: SimulationConfig, n_voxel=None, voxel_mm=None) -> float:
    """Side [mm] of the smallest centred square detector that sees the whole volume box
    from every angle of a circular orbit about z (before the margin).

    The box's xy footprint sweeps a disc of radius ``r`` (its xy half-diagonal); the
    tangents from the source reach ``u = DSD·r/√(DSO²−r²)`` and the top face, at most
    ``r`` nearer the source, reaches ``v = DSD·h_z/(DSO−r)``.
    """
    n = np.asarray(_triple(n_voxel if n_voxel is not None else cfg.n_voxel, int), dtype=float)
    d = np.asarray(_triple(voxel_mm if voxel_mm is not None else cfg.voxel_mm, float), dtype=float)
    half = n * d / 2
    r = float(math.hypot(half[0], half[1]))
    if cfg.mode == "parallel":
        return 2 * max(r, float(half[2]))
    if r >= cfg.dso_mm:
        raise ConfigError(f"the volume (radius {r:.0f} mm about the axis) reaches the source at dso_mm={cfg.dso_mm}; increase dso_mm or shrink the volume")
    u = cfg.dsd_mm * r / math.sqrt(cfg.dso_mm**2 - r**2)
    v = cfg.dsd_mm * float(half[2]) / (cfg.dso_mm - r)
    return 2 * max(u, v)


def make_geometry(cfg: SimulationConfig, *, n_voxel=None, voxel_mm=None) -> Geometry:
    """Geometry for ``cfg``: a square detector that sees the whole volume box from every angle.

    Args:
        cfg: the simulation settings.
        n_voxel, voxel_mm: override ``cfg.n_voxel`` / ``cfg.voxel_mm`` (e.g. a user volume's shape).
    """
    cfg.validate()
    nv = _triple(n_voxel if n_voxel is not None else cfg.n_voxel, int)
    dv = _triple(voxel_mm if voxel_mm is not None else cfg.voxel_mm, float)
    n_det = int(cfg.n_detector) if cfg.n_detector is not None else DEFAULT_N_DETECTOR
    if cfg.detector_mm is not None:
        d_det = float(cfg.detector_mm)
    else:
        d_det = magnified_extent_mm(cfg, nv, dv) * (1 + DETECTOR_MARGIN) / n_det
    return Geometry.from_mm(
        mode=cfg.mode, DSD=float(cfg.dsd_mm), DSO=float(cfg.dso_mm), nDetector=(n_det, n_det), dDetector=(d_det, d_det),
        nVoxel=nv, dVoxel=dv, offOrigin=(0.0, 0.0, 0.0), offDetector=(0.0, 0.0),
    )


def make_angles(cfg: SimulationConfig) -> tuple[np.ndarray, np.ndarray]:
    """Training and held-out angles [radians], float64 ``[n_train]`` and ``[n_val]``.

    Training: ``start + linspace(0, total, n_train, endpoint=False)``. Held-out: sorted
    uniform random angles in ``[start, start + total)`` (seeded) when
    ``random_val_angles``, else evenly spaced halfway between the training angles' grid.
    """
    start, total = math.radians(cfg.start_angle_deg), math.radians(cfg.total_angle_deg)
    train = start + np.linspace(0.0, total, int(cfg.n_train), endpoint=False)
    if cfg.random_val_angles:
        rng = np.random.default_rng([int(cfg.seed), 1])
        val = start + np.sort(rng.uniform(0.0, total, int(cfg.n_val)))
    else:
        val = start + (np.arange(int(cfg.n_val)) + 0.5) * total / int(cfg.n_val)
    return train.astype(np.float64), val.astype(np.float64)


def add_noise(projections: np.ndarray, photons: float = 1e5, electronic_sigma: float = 10.0, rng=None) -> np.ndarray:
    """TIGRE/NAF detector noise on line integrals ``p`` [N, nV, nU].

    ``counts = Poisson(photons·exp(−p)) + Normal(0, electronic_sigma)``, then
    ``p = −log(clip(counts, 1, ∞) / photons)``. As with TIGRE's noise model (and a
    real detector), air pixels fluctuate around 0, so some line integrals are
    slightly negative; they are kept (only counts below 1 are clipped, so that
    the logarithm exists). Returns float32.
    """
    rng = rng if rng is not None else np.random.default_rng()
    p = np.asarray(projections, dtype=np.float64)
    counts = rng.poisson(photons * np.exp(-p)).astype(np.float64)
    if electronic_sigma > 0:
        counts += rng.normal(0.0, electronic_sigma, size=counts.shape)
    return (-np.log(np.clip(counts, 1.0, None) / photons)).astype(np.float32)


def _meta(cfg: SimulationConfig, **extra) -> dict:
    meta: dict[str, Any] = {
        "accuracy": 0.5,
        "filter": None,
        "totalAngle": float(cfg.total_angle_deg),
        "startAngle": float(cfg.start_angle_deg),
        "numTrain": int(cfg.n_train),
        "numVal": int(cfg.n_val),
        "convert": False,
        "rescale_slope": 1.0,
        "rescale_intercept": 0.0,
        "normalize": True,
        "noise": int(bool(cfg.noise)),
        "randomAngle": bool(cfg.random_val_angles),
        "simulation": {"version": SIMULATOR_VERSION, **cfg.to_dict()},
    }
    if cfg.noise:
        meta["simulation"]["noise_model"] = NOISE_MODEL_VERSION
    meta.update(extra)
    return meta


def finish_projections(cfg: SimulationConfig, train_p: np.ndarray, val_p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The training and held-out projections as a scene keeps them (float32, contiguous), with ``cfg``'s
    detector noise added where it asks for it (drawn from ``cfg.seed``: the same draws for any scene)."""
    if cfg.noise:
        rng = np.random.default_rng([int(cfg.seed), 2])
        train_p = add_noise(train_p, cfg.photons, cfg.electronic_sigma, rng)
        val_p = add_noise(val_p, cfg.photons, cfg.electronic_sigma, rng)
    return np.ascontiguousarray(train_p, dtype=np.float32), np.ascontiguousarray(val_p, dtype=np.float32)


def _say(progress: Progress, msg: str) -> None:
    if progress is not None:
        progress(msg)


def simulate_phantom(phantom, cfg: SimulationConfig | None = None, *, progress: Progress = None) -> Scene:
    """Simulate a scene of a built-in phantom with exact (analytic) projections.

    Args:
        phantom: a built-in phantom name (``foot``, ``jaw``, ``chest``, ``abdomen``) or a
            Phantom-like object (``name, materials, project, volume, labels, label_at``).
        cfg: simulation settings (default :class:`SimulationConfig`).
        progress: optional ``progress(message)`` called before each stage.

    Returns:
        Scene with exact projections [N, nV, nU] (metres), the ground-truth volume
        [nx, ny, nz] (data units), labels, material names, the exact membership
        function and NAF meta keys (plus ``phantom`` and ``simulation``).
    """
    cfg = cfg or SimulationConfig()
    if isinstance(phantom, str):
        from .phantoms import get_phantom

        phantom = get_phantom(phantom)
    geometry = make_geometry(cfg)
    train_a, val_a = make_angles(cfg)
    t0 = time.perf_counter()
    _say(progress, f"projecting {len(train_a)} training views")
    train_p = np.asarray(phantom.project(geometry, train_a), dtype=np.float32)
    _say(progress, f"projecting {len(val_a)} held-out views")
    val_p = np.asarray(phantom.project(geometry, val_a), dtype=np.float32)
    train_p, val_p = finish_projections(cfg, train_p, val_p)
    _say(progress, "ground-truth volume and labels")
    image = np.ascontiguousarray(np.asarray(phantom.volume(geometry), dtype=np.float32))
    labels = np.ascontiguousarray(np.asarray(phantom.labels(geometry), dtype=np.uint8))
    meta = _meta(cfg, phantom=str(phantom.name), simulation_seconds=round(time.perf_counter() - t0, 3))
    meta["simulation"]["phantom"] = phantom.describe() if hasattr(phantom, "describe") else str(phantom.name)
    scene = Scene(
        name=str(phantom.name), geometry=geometry, train=Views(train_a, train_p), val=Views(val_a, val_p),
        image=image, labels=labels, materials=tuple(phantom.materials), meta=meta,
        source=f"built-in phantom {phantom.name} (simulated)",
    )
    scene.membership = lambda pts_model: phantom.label_at(geometry.model_to_mm(np.asarray(pts_model, dtype=np.float64)))
    return scene


def simulate_from_volume(
    volume,
    cfg: SimulationConfig | None = None,
    *,
    voxel_mm=None,
    name: str = "volume",
    meta: dict | None = None,
    device=None,
    progress: Progress = None,
) -> Scene:
    """Simulate a scene from a voxel volume with the Joseph projector (:func:`kneas_method.classical.projector.forward`).

    Args:
        volume: [nx, ny, nz] attenuation in data units (1/m; NAF: normalised to [0, 1]).
        cfg: simulation settings; ``n_voxel`` is taken from the volume's shape.
        voxel_mm: voxel size [mm] (float or 3), overriding ``cfg.voxel_mm``.
        name: scene name.
        meta: extra meta keys (e.g. ``convert``/``rescale_*``/``normalize`` from
            :func:`~kneas_method.data.volume_io.load_volume`).
        device: torch device for the projector.

    Returns:
        Scene whose ``image`` is ``volume`` (float32) and projections [N, nV, nU] (metres).
    """
    from ..classical.projector import forward

    cfg = cfg or SimulationConfig()
    vol = np.asarray(volume, dtype=np.float32)
    if vol.ndim != 3:
        raise SceneError(f"the volume has shape {vol.shape}; it must be 3-D [nx, ny, nz]")
    if not np.all(np.isfinite(vol)):
        raise SceneError("the volume contains NaN or inf; clean it before simulating")
    if np.any(vol < 0):
        raise SceneError(f"the volume has negative attenuation (min {float(vol.min()):.4g}); convert HU with --convert or clip it to 0")
    geometry = make_geometry(cfg, n_voxel=vol.shape, voxel_mm=voxel_mm if voxel_mm is not None else cfg.voxel_mm)
    train_a, val_a = make_angles(cfg)
    t0 = time.perf_counter()
    _say(progress, f"projecting {len(train_a)} training views")
    train_p = forward(vol, geometry, train_a, device=device)
    _say(progress, f"projecting {len(val_a)} held-out views")
    val_p = forward(vol, geometry, val_a, device=device)
    train_p, val_p = finish_projections(cfg, train_p, val_p)
    all_meta = _meta(cfg, simulation_seconds=round(time.perf_counter() - t0, 3))
    all_meta["simulation"]["n_voxel"] = list(vol.shape)
    all_meta["simulation"]["voxel_mm"] = list(_triple(voxel_mm if voxel_mm is not None else cfg.voxel_mm, float))
    all_meta.update(meta or {})
    return Scene(
        name=name, geometry=geometry, train=Views(train_a, train_p), val=Views(val_a, val_p),
        image=np.ascontiguousarray(vol), meta=all_meta, source=f"simulated from volume {name}",
    )
