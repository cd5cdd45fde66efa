"""Iterative reconstruction: SART, OS-SART, CGLS and ASD-POCS (SPEC §7), torch, CPU and CUDA.

Plain TIGRE-style functions of ``(projections, geometry, angles, ...)``:

* ``projections`` [N, nV, nU]: line integrals ``b = ∫ mu_data dl`` (l in metres),
  numpy or torch, indexed ``[view, row j, column i]``; small negative values
  (noisy data) are fine.
* ``geometry``: the scan :class:`~kneas_method.geometry.Geometry`; the volume is
  reconstructed on its voxel grid.
* ``angles`` [N]: view angles in radians.

Each returns the volume ``x`` [nx, ny, nz] in data units (1/m), float32 numpy
(or a tensor on ``device`` with ``return_tensor=True``). ``A`` is the Joseph
forward projector of :mod:`kneas_method.classical.projector`.

Back-projector (``backprojector=``):

* ``"matched"``: ``Aᵀ``, the exact adjoint of ``A`` (textbook CGLS needs it; see :func:`cgls`).
* ``"voxel"``: voxel-driven back-projection (bilinear on the detector at each
  voxel's projection; :class:`~kneas_method.classical.projector.VoxelBackprojector`),
  not the adjoint, as RTK's defaults.
* ``"auto"`` (default): chosen from the geometry by :func:`choose_backprojector`.
  When detector pixels at the isocentre are at least a voxel wide (the built-in
  scenes: 1.5 voxels) rays are sparser than voxels and the ray-driven adjoint
  leaves a ray-spacing pattern in each update; the voxel-driven one avoids it
  (matched SART stops 0.7-0.9 dB lower on all four built-in scenes). When pixels
  are finer than voxels the adjoint is smooth and exact, while point-sampling the
  detector at voxel centres drops data: on a held-out head phantom with a 256²
  detector (0.74 voxels per pixel) CGLS falls from 26.8 to 23.4 dB (below FDK) and
  ASD-POCS from 36.6 to 35.6 dB with the voxel-driven one (``benchmarks/heldout.py``).

Every algorithm accepts ``progress(iteration, total, residual)``, called after
each iteration with the relative data residual ``‖A x − b‖ / ‖b‖``: exact for
CGLS; for the SART family it is the residual each view (subset) had just before
its own update in that sweep, which costs nothing extra and trails the exact
residual of the returned volume by at most one sweep. ``iterates(iteration, x)`` receives
the current volume tensor after each iteration (read it, do not change it; ASD-POCS's and
CGLS's iterate is clamped at 0 only on return), so one run scores every iteration count
(``benchmarks/classical.py --trace``).

Weights: ``W = 1 / A 1`` per ray (rays that cross less than half a voxel of the
volume get weight 0, as in TIGRE) is computed once per call; the per-view or
per-subset ``V = Aᵀ 1`` (or its voxel-driven counterpart) is kept in memory when
all of them fit ``NORMALISER_CACHE_BYTES`` and otherwise back-projected together
with each update as a second channel, which costs little.
"""

from __future__ import annotations

import math
from typing import Callable, Optional

import numpy as np
import torch

from ..errors import ConfigError, KneasError
from ..geometry import Geometry
from ..device import resolve_device
from .projector import Projector, VoxelBackprojector, _angles, check_projections, check_volume

__all__ = ["sart", "os_sart", "cgls", "asd_pocs", "choose_backprojector", "pixels_per_voxel", "spread_order",
           "view_order", "interleaved_subsets", "total_variation", "tv_gradient", "ALGORITHMS"]

Progress = Optional[Callable[[int, int, float], None]]
# ``iterates(iteration, x)`` after each iteration, ``x`` the current volume tensor (read it, do not change it)
Iterates = Optional[Callable[[int, torch.Tensor], None]]

# Per-view / per-subset normalisers Aᵀ1 are stored when they take at most this many bytes.
NORMALISER_CACHE_BYTES = 1 << 30
TV_EPSILON = 1e-8  # data units; smooths |∇x| where the volume is flat


# ----------------------------------------------------------------- orders
def spread_order(n: int) -> np.ndarray:
    """A permutation of ``range(n)`` that keeps consecutive entries far apart
    (bit-reversal order, skipping values ``>= n``): 0, n/2, n/4, 3n/4, ...

    Applied to angle-sorted views it gives each update a view far from the last ones.
    """
    if n < 1:
        return np.zeros(0, dtype=np.int64)
    bits = max(1, math.ceil(math.log2(n)))
    rev = np.array([int(format(i, f"0{bits}b")[::-1], 2) for i in range(1 << bits)], dtype=np.int64)
    return rev[rev < n]


ORDERS = ("spread", "sequential", "random")


def view_order(angles, order: str = "spread") -> np.ndarray:
    """Indices of ``angles`` [N] in update order: ``"spread"`` (:func:`spread_order` of the
    angle-sorted views), ``"sequential"`` (by angle) or ``"random"`` (seeded shuffle)."""
    a = np.asarray(angles, dtype=np.float64).reshape(-1)
    by_angle = np.argsort(a, kind="stable")
    if order == "spread":
        return by_angle[spread_order(len(a))]
    if order == "sequential":
        return by_angle
    if order == "random":
        return np.random.default_rng(0).permutation(len(a))
    raise ConfigError(f"order is {order!r}; choose one of {', '.join(ORDERS)}")


def interleaved_subsets(angles, subsets: int) -> list[np.ndarray]:
    """Split views into ``subsets`` interleaved subsets (each spanning the whole arc),
    listed in :func:`spread_order`. Returns a list of index arrays into ``angles``."""
    a = np.asarray(angles, dtype=np.float64).reshape(-1)
    if not 1 <= int(subsets) <= len(a):
        raise ConfigError(f"subsets is {subsets}; choose 1..{len(a)} (the number of views)")
    by_angle = np.argsort(a, kind="stable")
    parts = [by_angle[j::int(subsets)] for j in range(int(subsets))]
    return [parts[j] for j in spread_order(len(parts))]


# --------------------------------------------------------------------- TV
def _forward_diffs(x: torch.Tensor) -> list[torch.Tensor]:
    """Forward differences of ``x`` [nx, ny, nz] along each axis, zero on the last plane (Neumann)."""
    out = []
    for ax in range(3):
        d = torch.zeros_like(x)
        n = x.shape[ax]
        if n > 1:
            d.narrow(ax, 0, n - 1).copy_(x.narrow(ax, 1, n - 1) - x.narrow(ax, 0, n - 1))
        out.append(d)
    return out


def total_variation(x, eps: float = 0.0) -> float:
    """Isotropic 3-D total variation ``Σ sqrt(|∇x|² + eps²)`` (forward differences), x [nx, ny, nz]."""
    x = torch.as_tensor(np.asarray(x) if not isinstance(x, torch.Tensor) else x).double()
    dx, dy, dz = _forward_diffs(x)
    return float(torch.sqrt(dx * dx + dy * dy + dz * dz + eps * eps).sum())


def tv_gradient(x: torch.Tensor, eps: float = TV_EPSILON) -> torch.Tensor:
    """Gradient [nx, ny, nz] of :func:`total_variation` (with ``eps``) at ``x`` [nx, ny, nz]."""
    diffs = _forward_diffs(x)
    mag = torch.sqrt(diffs[0] ** 2 + diffs[1] ** 2 + diffs[2] ** 2 + eps * eps)
    grad = torch.zeros_like(x)
    for ax, d in enumerate(diffs):
        q = d / mag  # ∂/∂(d) of the magnitude
        grad -= q
        n = x.shape[ax]
        if n > 1:
            grad.narrow(ax, 1, n - 1).add_(q.narrow(ax, 0, n - 1))
    return grad


def _tv_descent(x: torch.Tensor, step: float, n_steps: int) -> torch.Tensor:
    """``n_steps`` steepest-descent steps of length ``step`` (data units, L2 over the volume) on TV."""
    for _ in range(n_steps):
        g = tv_gradient(x)
        norm = float(torch.linalg.vector_norm(g))
        if norm == 0.0 or not math.isfinite(norm):
            break
        x = x - (step / norm) * g
    return x


# ------------------------------------------------------------------ setup
def _check_iterations(name: str, value: int) -> int:
    if int(value) != value or int(value) < 1:
        raise ConfigError(f"{name} is {value}; it must be a positive whole number")
    return int(value)


def _check_positive(name: str, value: float, upper: Optional[float] = None) -> float:
    v = float(value)
    if not math.isfinite(v) or v <= 0 or (upper is not None and v > upper):
        bound = f" and at most {upper}" if upper is not None else ""
        raise ConfigError(f"{name} is {value}; it must be positive{bound}")
    return v


def _setup(projections, geometry: Geometry, angles, device, init):
    """Projector, data ``b`` [N, nV, nU] and start volume ``x`` [nx, ny, nz] on the work device (float32)."""
    if not isinstance(geometry, Geometry):
        raise KneasError(f"expected a Geometry as the second argument, got {type(geometry).__name__}; "
                         "pass scene.geometry")
    dev = resolve_device(device, projections)
    ang = _angles(angles)
    b = check_projections(projections, geometry, len(ang), device=dev, dtype=torch.float32)
    proj = Projector(geometry, ang, device=dev, dtype=torch.float32)
    if init is None:
        x = torch.zeros(geometry.n_voxel, device=dev, dtype=torch.float32)
    elif isinstance(init, str):
        if init != "fdk":
            raise ConfigError(f"init is {init!r}; give a volume [nx, ny, nz], 'fdk' or None (zeros)")
        from .fdk import fdk_reconstruct

        x = fdk_reconstruct(geometry, ang, b, device=dev, return_tensor=True).to(torch.float32)
    else:
        x = check_volume(init, geometry, device=dev, dtype=torch.float32).clone()
    return proj, b, x


def _norm(t: torch.Tensor) -> float:
    return float(torch.linalg.vector_norm(t.reshape(-1), dtype=torch.float64))


def _finish(x: torch.Tensor, return_tensor: bool):
    return x if return_tensor else x.detach().cpu().numpy().astype(np.float32, copy=False)


BACKPROJECTORS = ("auto", "matched", "voxel")


def pixels_per_voxel(geometry: Geometry) -> float:
    """Detector pixel size at the isocentre (cone beam: ``d_detector · dso / dsd``) over the voxel
    size, the finer detector axis against the coarser voxel axis."""
    magnification = geometry.dsd / geometry.dso if geometry.mode == "cone" else 1.0
    return min(geometry.d_detector) / magnification / max(geometry.d_voxel)


def choose_backprojector(backprojector: str, geometry: Geometry) -> str:
    """``"matched"`` or ``"voxel"``: ``backprojector`` itself, or for ``"auto"`` the voxel-driven one when
    detector pixels at the isocentre are at least a voxel wide (:func:`pixels_per_voxel` ≥ 1) and the
    matched adjoint when they are finer (see the module docstring)."""
    if backprojector not in BACKPROJECTORS:
        raise ConfigError(f"backprojector is {backprojector!r}; choose one of {', '.join(BACKPROJECTORS)}")
    if backprojector == "auto":
        return "voxel" if pixels_per_voxel(geometry) >= 1.0 else "matched"
    return backprojector


class _SartKernel:
    """The SART update for one subset of views at a time, with weights computed once.

    ``W = 1 / A 1`` [N, nV, nU] (0 on rays crossing less than half a voxel). The
    normaliser ``V_s = B 1`` (``B`` the back-projector) per subset ``s`` is stored when all
    of them fit :data:`NORMALISER_CACHE_BYTES`, else back-projected with each update (as a
    second channel, at little extra cost).
    """

    def __init__(self, proj: Projector, b: torch.Tensor, subsets: list[np.ndarray], backprojector: str = "matched"):
        backprojector = choose_backprojector(backprojector, proj.geometry)
        self.proj, self.b, self.subsets = proj, b, subsets
        ones = torch.ones(proj.geometry.n_voxel, device=proj.device, dtype=torch.float32)
        length = proj.forward(ones)  # [N, nV, nU] metres
        min_len = 0.5 * min(proj.geometry.d_voxel) / proj.geometry.scale
        self.w = torch.where(length > min_len, 1.0 / length.clamp_min(min_len), torch.zeros_like(length))
        self.v: Optional[list[torch.Tensor]] = None
        if backprojector == "voxel":
            self.back = VoxelBackprojector(proj.geometry, proj.angles, device=proj.device).back
        else:
            self.back = proj.back
        vol_bytes = ones.numel() * ones.element_size()
        if len(subsets) * vol_bytes <= NORMALISER_CACHE_BYTES:
            self.v = [self._inverse(self.back(torch.ones_like(b[s]), s)) for s in subsets]
        self.b_norm = max(_norm(b), 1e-30)

    @staticmethod
    def _inverse(v: torch.Tensor) -> torch.Tensor:
        """``1 / V``; where no ray of the subset reaches a voxel (``V = 0``) its numerator is 0 as well
        (the same weights), so the huge value there multiplies an exact 0."""
        return 1.0 / v.clamp_min(1e-12)

    def sweep(self, x: torch.Tensor, relaxation: float, positivity: bool) -> tuple[torch.Tensor, float]:
        """One pass over all subsets; returns ``(x, relative sweep residual)``."""
        sq = 0.0
        for k, s in enumerate(self.subsets):
            r = self.b[s] - self.proj.forward(x, s)  # [k, nV, nU]
            sq += float(torch.sum(r.double() ** 2))
            if self.v is not None:
                x.addcmul_(self.back(r * self.w[s], s), self.v[k], value=relaxation)
            else:
                num, den = self.back(torch.stack([r * self.w[s], torch.ones_like(r)]), s)
                x.addcdiv_(num, den.clamp_min_(1e-12), value=relaxation)
            if positivity:
                x.clamp_(min=0.0)
        return x, math.sqrt(sq) / self.b_norm


def _run_sart(projections, geometry, angles, subsets_of, *, iterations, relaxation, positivity, backprojector, init,
              device, progress, return_tensor, iterates=None):
    iterations = _check_iterations("iterations", iterations)
    relaxation = _check_positive("relaxation (lambda)", relaxation, upper=2.0)
    proj, b, x = _setup(projections, geometry, angles, device, init)
    kernel = _SartKernel(proj, b, subsets_of(proj.angles), backprojector)
    if positivity:
        x.clamp_(min=0.0)
    for it in range(iterations):
        x, res = kernel.sweep(x, relaxation, positivity)
        if progress is not None:
            progress(it + 1, iterations, res)
        if iterates is not None:
            iterates(it + 1, x)
    return _finish(x, return_tensor)


# -------------------------------------------------------------- algorithms
def sart(projections, geometry: Geometry, angles, *, iterations: int = 10, relaxation: float = 0.5,
         positivity: bool = True, order: str = "spread", backprojector: str = "auto", init=None, device=None,
         progress: Progress = None, return_tensor: bool = False, iterates: Iterates = None):
    """SART (Andersen & Kak 1984): one update per view, views in a spread order.

    For each view ``v``: ``x ← max(0, x + λ · Bᵥ(W ⊙ (bᵥ − Aᵥx)) / Bᵥ1)`` with ``W = 1 / A1``
    and ``B`` the back-projector (``Aᵀ`` for ``backprojector="matched"``).

    Args:
        projections: [N, nV, nU] line integrals (metres · data units).
        geometry: scan geometry; angles: [N] radians.
        iterations: sweeps over all views (default 10).
        relaxation: ``λ`` in (0, 2] (default 0.5).
        positivity: clamp ``x`` at 0 after every update (default on).
        order: view order, ``"spread"`` (bit-reversal over the angle-sorted views, default),
            ``"sequential"`` (by angle) or ``"random"`` (a fixed seeded shuffle).
        backprojector: ``"auto"`` (default: from the geometry, :func:`choose_backprojector`),
            ``"voxel"`` (voxel-driven, like RTK) or ``"matched"`` (``Aᵀ``); see the module docstring.
        init: start volume [nx, ny, nz] (data units), ``"fdk"``, or None for zeros.
        device: torch device (default: the projections', if a tensor, else CPU).
        progress: ``progress(iteration, total, residual)`` after each sweep.
        return_tensor: return a tensor on ``device`` instead of numpy.
        iterates: ``iterates(iteration, x)`` after each sweep with the current volume tensor
            (read-only; e.g. to score every iteration count in one run).

    Returns:
        [nx, ny, nz] float32 attenuation in data units (1/m).
    """
    def each_view(a):
        return [np.array([i]) for i in view_order(a, order)]

    return _run_sart(projections, geometry, angles, each_view, iterations=iterations, relaxation=relaxation,
                     positivity=positivity, backprojector=backprojector, init=init, device=device, progress=progress,
                     return_tensor=return_tensor, iterates=iterates)


def os_sart(projections, geometry: Geometry, angles, *, subsets: int = 10, iterations: int = 10,
            relaxation: float = 1.0, positivity: bool = True, backprojector: str = "auto", init=None, device=None,
            progress: Progress = None, return_tensor: bool = False, iterates: Iterates = None):
    """OS-SART: the SART update applied to ``subsets`` interleaved subsets of views
    (one update per subset, subsets in a spread order); ``subsets = N`` is SART and
    ``subsets = 1`` is SIRT.

    Args:
        subsets: number of subsets (default 10, at most the number of views).
        iterations: sweeps over all subsets (default 10).
        relaxation: ``λ`` in (0, 2] (default 1: each update averages several views already).
        Others as :func:`sart`.

    Returns:
        [nx, ny, nz] float32 attenuation in data units (1/m).
    """
    n_views = len(_angles(angles))
    if int(subsets) != subsets or not 1 <= int(subsets) <= n_views:
        raise ConfigError(f"subsets is {subsets}; choose 1..{n_views} (the number of views)")
    return _run_sart(projections, geometry, angles, lambda a: interleaved_subsets(a, int(subsets)),
                     iterations=iterations, relaxation=relaxation, positivity=positivity, backprojector=backprojector,
                     init=init, device=device, progress=progress, return_tensor=return_tensor, iterates=iterates)


def cgls(projections, geometry: Geometry, angles, *, iterations: int = 30, backprojector: str = "auto", init=None,
         device=None, progress: Progress = None, return_tensor: bool = False, iterates: Iterates = None):
    """CGLS: conjugate gradients on the normal equations ``BA x = Bb`` (no positivity;
    stopping early is the regulariser).

    With ``backprojector="matched"`` ``B = Aᵀ`` and this is textbook CGLS. With ``"voxel"``
    (what ``"auto"`` picks when detector pixels are at least a voxel wide) ``B = c · V``, the
    voxel-driven back-projector scaled to ``Aᵀ``'s magnitude (``c = ΣAᵀ1 / ΣV1``), as RTK's
    conjugate-gradient filter does with its default voxel-based back-projector: the recursions no longer minimise exactly, but the result is smoother
    (the ray-spacing pattern of ``Aᵀ`` is the same one that costs SART, see the module
    docstring). Foot, 30 iterations: voxel 32.6 dB, matched 29.0 dB (RTK: 32.5 dB).

    Args:
        iterations: CG iterations (default 30); each costs one forward and one back projection.
        backprojector: ``"auto"`` (default, :func:`choose_backprojector`), ``"voxel"`` or ``"matched"``.
        init: start volume [nx, ny, nz], ``"fdk"``, or None for zeros.
        Others as :func:`sart`.

    Returns:
        [nx, ny, nz] float32 attenuation in data units (1/m).
    """
    iterations = _check_iterations("iterations", iterations)
    proj, b, x = _setup(projections, geometry, angles, device, init)
    backprojector = choose_backprojector(backprojector, proj.geometry)
    back = proj.back
    if backprojector == "voxel":
        voxel = VoxelBackprojector(proj.geometry, proj.angles, device=proj.device).back
        ones = torch.ones_like(b)
        scale = float(proj.back(ones).sum(dtype=torch.float64) / voxel(ones).sum(dtype=torch.float64).clamp_min(1e-30))

        def back(y):
            return voxel(y).mul_(scale)
    b_norm = max(_norm(b), 1e-30)
    r = b - proj.forward(x) if init is not None else b.clone()
    p = back(r)
    gamma = _norm(p) ** 2
    for it in range(iterations):
        if gamma == 0.0:  # exact solution reached (or zero data)
            res = _norm(r) / b_norm
        else:
            q = proj.forward(p)
            qq = _norm(q) ** 2
            if qq == 0.0:
                res = _norm(r) / b_norm
            else:
                alpha = gamma / qq
                x.add_(p, alpha=alpha)
                r.sub_(q, alpha=alpha)
                s = back(r)
                gamma_new = _norm(s) ** 2
                p = s.add_(p, alpha=gamma_new / gamma)
                gamma = gamma_new
                res = _norm(r) / b_norm
        if progress is not None:
            progress(it + 1, iterations, res)
        if iterates is not None:
            iterates(it + 1, x)
    return _finish(x, return_tensor)


def asd_pocs(projections, geometry: Geometry, angles, *, iterations: int = 10, n_tv: int = 20, alpha: float = 0.01,
             alpha_red: float = 0.95, r_max: float = 0.95, relaxation: float = 1.0, relaxation_red: float = 0.99,
             subsets: Optional[int] = None, epsilon: Optional[float] = None, backprojector: str = "auto", init=None,
             device=None, progress: Progress = None, return_tensor: bool = False, iterates: Iterates = None):
    """ASD-POCS (Sidky & Pan 2008): a SART sweep + positivity, then ``n_tv`` steepest-descent
    steps on the isotropic 3-D total variation whose length adapts to the data step.

    Per iteration: ``x_d = SART sweep(x)``; ``dp = ‖x_d − x‖``; on the first iteration
    the TV step is set to ``dtvg = alpha · dp``; ``n_tv`` steps ``x ← x − dtvg · ∇TV/‖∇TV‖``
    give ``dg = ‖x − x_d‖``; when ``dg > r_max · dp`` (and the residual exceeds
    ``epsilon``) ``dtvg ← alpha_red · dtvg``; the SART relaxation decays as
    ``λ ← relaxation_red · λ``. The returned volume is clamped at 0.

    Args:
        iterations: outer iterations (default 10).
        n_tv: TV descent steps per iteration (default 20).
        alpha: first TV step as a fraction of the first data step (default 0.01; TIGRE uses
            0.002, which on the built-in scenes leaves ASD-POCS only ~0.5 dB above SART).
        alpha_red: TV step reduction factor (default 0.95).
        r_max: largest allowed ratio of the TV change to the data change (default 0.95).
        relaxation, relaxation_red: SART ``λ`` (default 1) and its decay per iteration (0.99).
        subsets: None for SART (one view per update) or a number of OS-SART subsets.
        epsilon: relative residual below which the TV step is no longer reduced (None: always test ``r_max``).
        Others as :func:`sart`.

    Returns:
        [nx, ny, nz] float32 attenuation in data units (1/m).
    """
    iterations = _check_iterations("iterations", iterations)
    n_tv = int(n_tv)
    if n_tv < 0:
        raise ConfigError(f"n_tv is {n_tv}; it must be 0 or more TV steps per iteration")
    alpha = _check_positive("alpha", alpha)
    alpha_red = _check_positive("alpha_red", alpha_red, upper=1.0)
    r_max = _check_positive("r_max", r_max)
    relaxation = _check_positive("relaxation (lambda)", relaxation, upper=2.0)
    relaxation_red = _check_positive("relaxation_red", relaxation_red, upper=1.0)
    proj, b, x = _setup(projections, geometry, angles, device, init)
    if subsets is None:
        by_angle = np.argsort(proj.angles, kind="stable")
        parts = [by_angle[i:i + 1] for i in spread_order(proj.n_views)]
    else:
        parts = interleaved_subsets(proj.angles, subsets)
    kernel = _SartKernel(proj, b, parts, backprojector)
    x.clamp_(min=0.0)
    dtvg = None
    lam = relaxation
    for it in range(iterations):
        before = x.clone()
        x, res = kernel.sweep(x, lam, True)
        dp = _norm(x - before)
        if dtvg is None:
            dtvg = alpha * dp
        data = x.clone()
        x = _tv_descent(x, dtvg, n_tv)
        dg = _norm(x - data)
        if dg > r_max * dp and (epsilon is None or res > epsilon):
            dtvg *= alpha_red
        lam *= relaxation_red
        if progress is not None:
            progress(it + 1, iterations, res)
        if iterates is not None:
            iterates(it + 1, x)
    return _finish(x.clamp_(min=0.0), return_tensor)


ALGORITHMS: dict[str, Callable] = {"sart": sart, "os-sart": os_sart, "cgls": cgls, "asd-pocs": asd_pocs}
