"""Built-in analytic phantoms (foot, jaw, chest, abdomen) with exact projections.

A phantom is a list of convex analytic primitives -- ellipsoids, finite capped
elliptic cylinders and boxes -- each with a centre and semi-axes (half-sizes) in
**mm**, a rotation, a material label and a priority. A point takes the material
of the highest-priority primitive that contains it; outside every primitive it
is air (label 0, attenuation 0). A primitive may carry label 0 itself to cut an
air cavity (airway, bowel gas) out of lower-priority tissue.

Attenuation is in **data units** on [0, 1] (the normalised scale of the NAF
benchmark volumes, read as 1/m by the projector, SPEC §1). Labels 1..M name the
materials in ascending attenuation.

Coordinates are the scanner's: the scan rotates about z, which is the body's
long axis (the leg for ``foot``, the head's vertical axis for ``jaw``). Every
phantom fits inside the cube [-120, 120]^3 mm centred at the origin.

Projections (:meth:`Phantom.project`) are exact line integrals: each ray is
intersected analytically with every primitive (float64), the interval endpoints
are sorted, and the piecewise-constant attenuation is integrated segment by
segment, the active material being found from a bitmask of the primitives
covering the segment (bit = priority rank, highest set bit wins). No voxel
volume is ever sampled. :meth:`Phantom.project` computes, per view, each
primitive's intersections only for the detector pixels its bounding box
projects onto (conservative culling; :meth:`Phantom.project_rays` is the
unculled path for arbitrary rays and gives the same numbers).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from ..errors import SceneError
from ..geometry import Geometry

PHANTOM_NAMES: tuple[str, ...] = ("foot", "jaw", "chest", "abdomen")

KINDS = ("ellipsoid", "cylinder", "box")
EXTENT_LIMIT_MM = 120.0
_MAX_PRIMITIVES = 52  # priority ranks are bits of a mask that must convert to float64 exactly (< 2^53)


def euler_rotation(euler_deg) -> np.ndarray:
    """Rotation matrix [3, 3] ``Rz(a) @ Ry(b) @ Rx(c)`` for ``euler_deg = (a, b, c)`` in degrees.

    The columns are the primitive's local x, y, z axes in world coordinates.
    """
    a, b, c = (math.radians(float(v)) for v in euler_deg)
    ca, sa, cb, sb, cc, sc = math.cos(a), math.sin(a), math.cos(b), math.sin(b), math.cos(c), math.sin(c)
    rz = np.array([[ca, -sa, 0.0], [sa, ca, 0.0], [0.0, 0.0, 1.0]])
    ry = np.array([[cb, 0.0, sb], [0.0, 1.0, 0.0], [-sb, 0.0, cb]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cc, -sc], [0.0, sc, cc]])
    return rz @ ry @ rx


@dataclass(frozen=True)
class Primitive:
    """One convex analytic solid.

    Attributes:
        kind: ``"ellipsoid"`` (semi-axes ``half``), ``"cylinder"`` (finite capped
            elliptic cylinder along its local z: semi-axes ``half[0], half[1]`` of
            the cross-section, half-length ``half[2]``) or ``"box"`` (half-sizes).
        centre: (x, y, z) in mm.
        half: (3,) semi-axes / half-sizes in mm along the local axes, all > 0.
        material: label 0..M (0 = air: cuts a cavity).
        priority: larger wins where primitives overlap (ties: later in the list wins).
        euler: (a, b, c) degrees, rotation ``Rz(a) @ Ry(b) @ Rx(c)`` local -> world.
        name: free text (anatomy), for descriptions.
    """

    kind: str
    centre: tuple[float, float, float]
    half: tuple[float, float, float]
    material: int
    priority: int
    euler: tuple[float, float, float] = (0.0, 0.0, 0.0)
    name: str = ""

    def __post_init__(self):
        if self.kind not in KINDS:
            raise SceneError(f"primitive kind {self.kind!r} is unknown; use one of {', '.join(KINDS)}")
        if len(self.centre) != 3 or len(self.half) != 3 or len(self.euler) != 3:
            raise SceneError("a primitive needs 3 values each for centre, half and euler")
        if not all(float(h) > 0 for h in self.half):
            raise SceneError(f"primitive {self.name or self.kind!r} has a non-positive size {self.half}")

    @property
    def rotation(self) -> np.ndarray:
        """[3, 3] local -> world rotation (columns = local axes)."""
        return euler_rotation(self.euler)

    def to_local(self, points_mm: np.ndarray) -> np.ndarray:
        """World points [P, 3] mm -> normalised local coordinates [P, 3] (unit shape)."""
        p = np.asarray(points_mm, dtype=np.float64) - np.asarray(self.centre, dtype=np.float64)
        return (p @ self.rotation) / np.asarray(self.half, dtype=np.float64)

    def contains(self, points_mm: np.ndarray) -> np.ndarray:
        """Boolean [P]: points [P, 3] (mm) inside or on the surface."""
        return _inside(self.kind, self.to_local(points_mm))

    def aabb(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounding box ``(lo [3], hi [3])`` in mm (tight for all kinds)."""
        r, h = self.rotation, np.asarray(self.half, dtype=np.float64)
        if self.kind == "ellipsoid":
            ext = np.sqrt(((r * h) ** 2).sum(1))
        elif self.kind == "box":
            ext = (np.abs(r) * h).sum(1)
        else:  # elliptic cross-section swept along local z
            ext = np.sqrt((r[:, 0] * h[0]) ** 2 + (r[:, 1] * h[1]) ** 2) + np.abs(r[:, 2]) * h[2]
        c = np.asarray(self.centre, dtype=np.float64)
        return c - ext, c + ext

    def volume_mm3(self) -> float:
        """Exact volume in mm^3."""
        a, b, c = (float(v) for v in self.half)
        return {"ellipsoid": 4.0 / 3.0 * math.pi * a * b * c, "cylinder": math.pi * a * b * 2 * c, "box": 8 * a * b * c}[self.kind]


def _inside(kind: str, q: np.ndarray) -> np.ndarray:
    """Unit-shape membership for normalised local coordinates q [..., 3]."""
    if kind == "ellipsoid":
        return (q * q).sum(-1) <= 1.0
    if kind == "cylinder":
        return (q[..., 0] ** 2 + q[..., 1] ** 2 <= 1.0) & (np.abs(q[..., 2]) <= 1.0)
    return np.abs(q).max(-1) <= 1.0


def _slab(o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Entry/exit parameters of the slab |o + t d| <= 1 (arrays of equal shape)."""
    zero = d == 0.0
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / np.where(zero, 1.0, d)
        ta = (-1.0 - o) * inv
        tb = (1.0 - o) * inv
    inside = np.abs(o) <= 1.0
    lo = np.where(zero, np.where(inside, -np.inf, np.inf), np.minimum(ta, tb))
    hi = np.where(zero, np.where(inside, np.inf, -np.inf), np.maximum(ta, tb))
    return lo, hi


def _quadric(o, d) -> tuple[np.ndarray, np.ndarray]:
    """Entry/exit of sum_j (o_j + t d_j)^2 <= 1 for component tuples ``o``, ``d`` (arrays [R, k]).

    Used for ellipsoids (3 components) and cylinder cross-sections (2). Rays with
    all ``d_j = 0`` (parallel to a cylinder's axis) give (-inf, inf) when inside,
    else an empty interval (``t0 = inf``, ``t1 = -inf``).
    """
    a = sum(dj * dj for dj in d)
    b = sum(oj * dj for oj, dj in zip(o, d))
    c = sum(oj * oj for oj in o) - 1.0
    degenerate = a <= 1e-300
    if degenerate.any():
        a = np.where(degenerate, 1.0, a)
    disc = b * b - a * c
    miss = disc <= 0.0
    sq = np.sqrt(np.maximum(disc, 0.0, out=disc), out=disc)
    t0 = (-b - sq) / a
    t1 = (sq - b) / a
    t0[miss] = np.inf
    t1[miss] = -np.inf
    if degenerate.any():
        inside = c <= 0.0
        t0 = np.where(degenerate, np.where(inside, -np.inf, np.inf), t0)
        t1 = np.where(degenerate, np.where(inside, np.inf, -np.inf), t1)
    return t0, t1


@dataclass
class Phantom:
    """An analytic phantom: named materials and prioritised primitives (see module docs).

    Attributes:
        name: short name (``foot``).
        description: one sentence on what it depicts.
        materials: names of labels 1..M.
        levels: attenuation of labels 1..M, data units (1/m, NAF-normalised, on [0, 1]).
        primitives: the solids; label 0 primitives cut air cavities.
    """

    name: str
    description: str
    materials: tuple[str, ...]
    levels: tuple[float, ...]
    primitives: tuple[Primitive, ...] = field(default_factory=tuple)

    def __post_init__(self):
        self.materials = tuple(self.materials)
        self.levels = tuple(float(v) for v in self.levels)
        self.primitives = tuple(self.primitives)
        if len(self.materials) != len(self.levels):
            raise SceneError(f"phantom {self.name!r}: {len(self.materials)} materials but {len(self.levels)} levels")
        if not self.primitives:
            raise SceneError(f"phantom {self.name!r} has no primitives")
        if len(self.primitives) > _MAX_PRIMITIVES:
            raise SceneError(f"phantom {self.name!r} has {len(self.primitives)} primitives; at most {_MAX_PRIMITIVES} are supported")
        if any(v < 0 for v in self.levels):
            raise SceneError(f"phantom {self.name!r}: attenuation levels must be >= 0, got {self.levels}")
        for p in self.primitives:
            if not 0 <= p.material <= len(self.materials):
                raise SceneError(f"phantom {self.name!r}: primitive {p.name!r} has label {p.material}, outside 0..{len(self.materials)}")
        # Rank primitives by (priority, list position): rank r is bit r of the mask.
        order = sorted(range(len(self.primitives)), key=lambda i: (self.primitives[i].priority, i))
        self._ranked = tuple(self.primitives[i] for i in order)
        self._level_lut = np.concatenate([[0.0], np.asarray(self.levels, dtype=np.float64)])  # label -> mu
        prim = self._ranked
        self._rot = np.stack([p.rotation for p in prim])  # [K,3,3]
        self._half = np.array([p.half for p in prim], dtype=np.float64)  # [K,3]
        self._centre = np.array([p.centre for p in prim], dtype=np.float64)  # [K,3]
        self._labels = np.array([p.material for p in prim], dtype=np.int64)  # [K]
        self._mu = self._level_lut[self._labels]  # [K] data units
        # Projection layout: columns grouped by kind; per group one [3, 3k] matrix so that
        # o @ m - off gives local coordinates component-major ([R, k] x, then y, then z).
        self._col, self._groups = [], []
        for kind in KINDS:
            idx = [r for r, p in enumerate(prim) if p.kind == kind]
            if not idx:
                continue
            m = self._rot[idx] / self._half[idx][:, None, :]  # [k, 3(world i), 3(local j)]
            mat = m.transpose(1, 2, 0).reshape(3, 3 * len(idx))  # [i, j*k + p]
            off = np.einsum("pi,pij->jp", self._centre[idx], m).reshape(-1)
            self._groups.append((kind, slice(len(self._col), len(self._col) + len(idx)), mat, off))
            self._col.extend(idx)
        self._col_rank = np.asarray(self._col, dtype=np.int64)  # column -> priority rank
        # per ranked primitive: world -> local map (x @ m - off) and its AABB corners (culling)
        self._local_maps = []
        corners = []
        for p in prim:
            m = p.rotation / np.asarray(p.half, dtype=np.float64)[None, :]
            self._local_maps.append((m, np.asarray(p.centre, dtype=np.float64) @ m))
            lo, hi = p.aabb()
            corners.append([[(lo, hi)[a][0], (lo, hi)[b][1], (lo, hi)[c][2]] for a in (0, 1) for b in (0, 1) for c in (0, 1)])
        self._corners = np.asarray(corners, dtype=np.float64)  # [K, 8, 3] mm

    # ------------------------------------------------------------- properties
    @property
    def n_materials(self) -> int:
        return len(self.materials)

    def bounds_mm(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounding box ``(lo [3], hi [3])`` of all non-air primitives, mm."""
        boxes = [p.aabb() for p in self.primitives if p.material != 0] or [p.aabb() for p in self.primitives]
        return np.min([b[0] for b in boxes], 0), np.max([b[1] for b in boxes], 0)

    def describe(self) -> str:
        """One line: materials with their levels (data units) and primitive count."""
        mats = ", ".join(f"{m} {v:.2f}" for m, v in zip(self.materials, self.levels))
        return f"{self.description} Materials (data units): {mats}; {len(self.primitives)} primitives."

    # ----------------------------------------------------------------- points
    def label_at(self, points_mm: np.ndarray) -> np.ndarray:
        """Material label [P] int64 (0 = air) at points [P, 3] in mm."""
        pts = np.asarray(points_mm, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[-1] != 3:
            raise SceneError(f"points must have shape [P, 3], got {pts.shape}")
        out = np.zeros(len(pts), dtype=np.int64)
        for p in self._ranked:  # ascending priority: later assignments win
            lo, hi = p.aabb()
            cand = np.nonzero(np.all((pts >= lo) & (pts <= hi), axis=1))[0]
            if len(cand):
                inside = p.contains(pts[cand])
                out[cand[inside]] = p.material
        return out

    def mu_at(self, points_mm: np.ndarray) -> np.ndarray:
        """Attenuation [P] float64 in data units at points [P, 3] in mm."""
        return self._level_lut[self.label_at(points_mm)]

    # ------------------------------------------------------------------- grids
    def _label_grid(self, xs: np.ndarray, ys: np.ndarray, zs: np.ndarray) -> np.ndarray:
        """Labels [nx, ny, nz] uint8 on the rectilinear grid of increasing axes (mm).

        Each primitive is evaluated only inside its bounding box, in ascending
        priority, so the highest-priority container wins.
        """
        out = np.zeros((len(xs), len(ys), len(zs)), dtype=np.uint8)
        axes = (xs, ys, zs)
        for p in self._ranked:
            lo, hi = p.aabb()
            sl = []
            for ax, a, b in zip(axes, lo, hi):
                i0, i1 = np.searchsorted(ax, a, "left"), np.searchsorted(ax, b, "right")
                sl.append(slice(int(i0), int(i1)))
            if any(s.stop <= s.start for s in sl):
                continue
            x = axes[0][sl[0]] - p.centre[0]
            y = axes[1][sl[1]] - p.centre[1]
            z = axes[2][sl[2]] - p.centre[2]
            r, h = p.rotation, np.asarray(p.half, dtype=np.float64)
            q = []
            for j in range(3):
                q.append((x * (r[0, j] / h[j]))[:, None, None] + (y * (r[1, j] / h[j]))[None, :, None] + (z * (r[2, j] / h[j]))[None, None, :])
            if p.kind == "ellipsoid":
                inside = q[0] * q[0] + q[1] * q[1] + q[2] * q[2] <= 1.0
            elif p.kind == "cylinder":
                inside = (q[0] * q[0] + q[1] * q[1] <= 1.0) & (np.abs(q[2]) <= 1.0)
            else:
                inside = (np.abs(q[0]) <= 1.0) & (np.abs(q[1]) <= 1.0) & (np.abs(q[2]) <= 1.0)
            block = out[sl[0], sl[1], sl[2]]
            block[inside] = p.material
        return out

    @staticmethod
    def _axes_mm(geometry: Geometry) -> list[np.ndarray]:
        return [a.numpy() * geometry.mm_per_unit for a in geometry.voxel_axes(dtype=torch.float64)]

    def labels(self, geometry: Geometry) -> np.ndarray:
        """Material labels [nx, ny, nz] uint8 at ``geometry``'s voxel centres (0 = air)."""
        xs, ys, zs = self._axes_mm(geometry)
        return self._label_grid(xs, ys, zs)

    def volume(self, geometry: Geometry, supersample: int = 3, max_points: int = 4_000_000) -> np.ndarray:
        """Attenuation volume [nx, ny, nz] float32 in data units at ``geometry``'s voxels.

        Each voxel is the mean over ``supersample``^3 sub-voxel points (cell-centred
        in the voxel), so partial-volume voxels get intermediate values. Processed
        in slabs along x of at most about ``max_points`` points.
        """
        s = int(supersample)
        if s < 1:
            raise SceneError(f"supersample must be >= 1, got {supersample}")
        axes = self._axes_mm(geometry)
        dmm = [d * geometry.mm_per_unit for d in geometry.d_voxel]
        offs = [d * ((np.arange(s) + 0.5) / s - 0.5) for d in dmm]
        sub = [(a[:, None] + o[None, :]).reshape(-1) for a, o in zip(axes, offs)]  # increasing
        nx, ny, nz = (len(a) for a in axes)
        out = np.empty((nx, ny, nz), dtype=np.float32)
        lut = self._level_lut.astype(np.float32)
        step = max(1, int(max_points // max(1, ny * nz * s**3)))
        for i0 in range(0, nx, step):
            i1 = min(nx, i0 + step)
            lab = self._label_grid(sub[0][i0 * s:i1 * s], sub[1], sub[2])
            mu = lut[lab].reshape(i1 - i0, s, ny, s, nz, s)
            out[i0:i1] = mu.mean(axis=(1, 3, 5), dtype=np.float64)
        return out

    # -------------------------------------------------------------- projection
    @staticmethod
    def _kind_intervals(kind: str, o, d) -> tuple[np.ndarray, np.ndarray]:
        """Entry/exit parameters for unit shapes; ``o``, ``d``: local (x, y, z) component arrays."""
        if kind == "ellipsoid":
            return _quadric(o, d)
        if kind == "cylinder":
            a, b = _quadric(o[:2], d[:2])
            za, zb = _slab(o[2], d[2])
            return np.maximum(a, za, out=a), np.minimum(b, zb, out=b)
        a, b = _slab(o[0], d[0])
        for oc, dc in zip(o[1:], d[1:]):
            lo, hi = _slab(oc, dc)
            np.maximum(a, lo, out=a)
            np.minimum(b, hi, out=b)
        return a, b

    def _intervals(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Entry/exit ray parameters [R, K] for rays o, d [R, 3] (mm) vs all primitives.

        Columns follow ``self._col`` (primitives grouped by kind; ``self._col_rank``
        gives each column's priority rank). Empty intervals have ``t0 >= t1``.
        """
        t0 = np.empty((len(o), len(self._col)))
        t1 = np.empty_like(t0)
        for kind, sl, m, off in self._groups:
            ol = o @ m - off  # [R, 3k]: local coordinates, component-major
            dl = d @ m
            k = sl.stop - sl.start
            comps = lambda x: (x[:, :k], x[:, k:2 * k], x[:, 2 * k:])  # noqa: E731
            t0[:, sl], t1[:, sl] = self._kind_intervals(kind, comps(ol), comps(dl))
        return t0, t1

    def _integrate(self, t0: np.ndarray, t1: np.ndarray, ranks: np.ndarray, near: float, far: float) -> np.ndarray:
        """Exact ``∫ mu dt`` [R] (data units x ray parameter) from intervals [R, U].

        ``ranks`` [U] are the columns' priority ranks (distinct). Intervals are
        clipped to ``[near, far]``; the attenuation on each segment between sorted
        endpoints is that of the highest-ranked primitive covering it.
        """
        t0 = np.maximum(t0, near)
        t1 = np.minimum(t1, far)
        empty = t1 <= t0
        t0[empty] = near  # empty -> zero length at near
        t1[empty] = near
        return self._integrate_events(np.concatenate([t0, t1], axis=1), ranks, ~empty)

    def _integrate_events(self, events: np.ndarray, ranks: np.ndarray, hit: np.ndarray) -> np.ndarray:
        """``∫ mu dt`` [R] from clipped interval endpoints ``events`` [R, 2U] (entries then exits;
        empty intervals zero-length), column ranks [U] and the hit mask [R, U]."""
        u = len(ranks)
        out = np.zeros(len(events))
        used = np.nonzero(hit.any(0))[0]
        rows = np.nonzero(hit.any(1))[0]
        if len(used) == 0:
            return out
        if len(rows) < len(events):
            events = events[rows]
        if len(used) < u:
            events = events[:, np.concatenate([used, used + u])]
        r = ranks[used]
        bits = np.left_shift(np.int64(1), np.argsort(np.argsort(r)).astype(np.int64))  # 1 << rank among used
        lut = np.concatenate([[0.0], self._mu[np.sort(r)]])  # (highest bit + 1) -> mu
        events_b = np.concatenate([bits, -bits])  # [2U]
        order = np.argsort(events, axis=1)
        ts = np.take_along_axis(events, order, axis=1)
        mask = np.cumsum(events_b[order], axis=1)[:, :-1]  # set of primitives active after each event
        seg = np.diff(ts, axis=1)  # [R', 2U-1] >= 0
        # Highest set bit = frexp exponent - 1 (exact for ints < 2^53); mask 0 -> 0 (air).
        # Only zero-length segments inside a tie can carry a transient (even negative) mask.
        np.maximum(mask, 0, out=mask)
        _, e = np.frexp(mask.astype(np.float64))
        np.minimum(e, len(used), out=e)
        out[rows] = np.einsum("ij,ij->i", lut[e], seg)
        return out

    def project_rays(self, origins_mm: np.ndarray, directions_mm: np.ndarray, near: float = 0.0,
                     far: float = np.inf, chunk: int = 32768) -> np.ndarray:
        """Exact line integrals [R] for arbitrary rays, no culling.

        Args:
            origins_mm, directions_mm: [R, 3] in mm; ``directions_mm`` need not be unit.
            near, far: ray-parameter range (``x = o + t d``).
        Returns:
            ``∫ mu_data dl`` [R] float64, l in metres.
        """
        o = np.asarray(origins_mm, dtype=np.float64).reshape(-1, 3)
        d = np.asarray(directions_mm, dtype=np.float64).reshape(-1, 3)
        out = np.empty(len(o))
        for r0 in range(0, len(o), max(1, int(chunk))):
            r1 = min(len(o), r0 + int(chunk))
            t0, t1 = self._intervals(o[r0:r1], d[r0:r1])
            out[r0:r1] = self._integrate(t0, t1, self._col_rank, near, far)
        return out * np.sqrt((d * d).sum(1)) / 1000.0  # |d| is mm per unit t -> metres

    def _detector_boxes(self, geometry: Geometry, rot: np.ndarray, src_mm: np.ndarray) -> np.ndarray:
        """Conservative detector pixel ranges [K, 4] ``(j0, j1, i0, i1)`` (half-open) of each ranked
        primitive for one view (rotation ``rot`` [3, 3], source ``src_mm`` [3])."""
        k = geometry.mm_per_unit
        (nu, nv), (du, dv), (ou, ov) = geometry.n_detector, geometry.d_detector, geometry.off_detector
        local = (self._corners - src_mm) @ rot  # [K, 8, 3] in the source frame
        if geometry.mode == "cone":
            z = local[..., 2]
            ok = (z > 1e-9).all(1)
            zs = np.where(z > 1e-9, z, 1.0)
            u = geometry.dsd * k * local[..., 0] / zs
            v = geometry.dsd * k * local[..., 1] / zs
        else:
            ok = np.ones(len(local), dtype=bool)
            u, v = local[..., 0], local[..., 1]
        fi_lo = (u.min(1) - ou * k) / (du * k) + nu / 2 - 0.5
        fi_hi = (u.max(1) - ou * k) / (du * k) + nu / 2 - 0.5
        fj_lo = (v.min(1) - ov * k) / (dv * k) + nv / 2 - 0.5
        fj_hi = (v.max(1) - ov * k) / (dv * k) + nv / 2 - 0.5
        box = np.stack([np.floor(fj_lo) - 1, np.ceil(fj_hi) + 2, np.floor(fi_lo) - 1, np.ceil(fi_hi) + 2], 1)
        box = np.clip(np.nan_to_num(box), 0, [nv, nv, nu, nu]).astype(np.int64)
        box[~ok] = (0, nv, 0, nu)  # source inside a bounding box: no culling
        return box

    def project(self, geometry: Geometry, angles, chunk: int = 65536) -> np.ndarray:
        """Exact line integrals [N, nV, nU] float32 of ``mu_data`` with lengths in metres.

        Rays come from ``geometry.rays(angles)`` (cone or parallel), limited to the
        parameter range ``geometry.near_far`` (the volume's span; a phantom that
        fits in the volume lies wholly inside it). Each ray is intersected
        analytically with every primitive whose bounding box projects onto its
        pixel (a conservative per-view culling), then integrated exactly.

        Args:
            geometry: scanner geometry (model units; converted to mm here).
            angles: [N] view angles in radians.
            chunk: at most this many rays per batch inside a view (bounds memory to
                roughly ``chunk * n_primitives * 100`` bytes).
        """
        angles = np.asarray(angles, dtype=np.float64).reshape(-1)
        nu, nv = geometry.n_detector
        out = np.zeros((len(angles), nv, nu), dtype=np.float32)
        near, far = geometry.near_far
        kmm = geometry.mm_per_unit
        rots = geometry.rotations(torch.as_tensor(angles)).numpy()
        srcs = geometry.source_positions(torch.as_tensor(angles)).numpy() * kmm
        rows_per_batch = max(1, int(chunk) // max(1, nu))
        kk = len(self._ranked)
        ranks = np.arange(kk)
        for n in range(len(angles)):
            o, d = geometry.rays(torch.as_tensor(angles[n:n + 1]), dtype=torch.float64)
            o = o.numpy()[0] * kmm  # [nV, nU, 3]
            d = d.numpy()[0] * kmm
            boxes = self._detector_boxes(geometry, rots[n], srcs[n])
            for j0 in range(0, nv, rows_per_batch):
                j1 = min(nv, j0 + rows_per_batch)
                events = np.full((j1 - j0, nu, 2 * kk), near)  # entries [..., :K], exits [..., K:]
                hit = np.zeros((j1 - j0, nu, kk), dtype=bool)
                for r, p in enumerate(self._ranked):
                    bj0, bj1, bi0, bi1 = boxes[r]
                    bj0, bj1 = max(bj0, j0), min(bj1, j1)
                    if bj1 <= bj0 or bi1 <= bi0:
                        continue
                    ob = o[bj0:bj1, bi0:bi1].reshape(-1, 3)
                    db = d[bj0:bj1, bi0:bi1].reshape(-1, 3)
                    m, off = self._local_maps[r]
                    ol, dl = ob @ m - off, db @ m
                    a, b = self._kind_intervals(p.kind, (ol[:, 0], ol[:, 1], ol[:, 2]), (dl[:, 0], dl[:, 1], dl[:, 2]))
                    np.maximum(a, near, out=a)
                    np.minimum(b, far, out=b)
                    full = b > a
                    a[~full] = near
                    b[~full] = near
                    shape = (bj1 - bj0, bi1 - bi0)
                    events[bj0 - j0:bj1 - j0, bi0:bi1, r] = a.reshape(shape)
                    events[bj0 - j0:bj1 - j0, bi0:bi1, kk + r] = b.reshape(shape)
                    hit[bj0 - j0:bj1 - j0, bi0:bi1, r] = full.reshape(shape)
                res = self._integrate_events(events.reshape(-1, 2 * kk), ranks, hit.reshape(-1, kk))
                dn = np.sqrt((d[j0:j1] ** 2).sum(-1)).reshape(-1)
                out[n, j0:j1] = (res * dn / 1000.0).reshape(j1 - j0, nu)
        return out


# ---------------------------------------------------------------------------
# Phantom definitions (all lengths mm, euler degrees)
# ---------------------------------------------------------------------------

E, C, B = "ellipsoid", "cylinder", "box"


def _P(kind, centre, half, material, priority, euler=(0.0, 0.0, 0.0), name=""):
    return Primitive(kind, tuple(float(v) for v in centre), tuple(float(v) for v in half), int(material), int(priority),
                     tuple(float(v) for v in euler), name)


def _bone(prims: list, idx: int, kind, centre, half, shell, euler=(0.0, 0.0, 0.0), name="", cortical=3, marrow=2,
          marrow_centre=None, marrow_half=None):
    """Append a bone: cortical primitive and, inside it, marrow (higher priority, lower mu)."""
    prims.append(_P(kind, centre, half, cortical, 10 + 2 * idx, euler, f"{name} cortex"))
    mh = marrow_half if marrow_half is not None else tuple(max(h - shell, 0.5) for h in half)
    mc = marrow_centre if marrow_centre is not None else centre
    prims.append(_P(kind, mc, mh, marrow, 11 + 2 * idx, euler, f"{name} marrow"))


def _foot() -> Phantom:
    # x: heel (-) to toes (+), y: lateral (-) / medial (+), z: up the leg.
    ST, MARROW, CORT = 1, 2, 3
    p = [
        _P(C, (-48, 0, 45), (44, 40, 65), ST, 1, (0, 4, 0), "lower leg"),
        _P(E, (-50, 0, -30), (50, 42, 45), ST, 2, (0, 0, 0), "ankle and heel"),
        _P(E, (5, 2, -50), (112, 46, 32), ST, 3, (3, 6, 0), "foot"),
    ]
    # tibia and fibula shafts: marrow shorter at the distal end so cortex caps them
    _bone(p, 0, C, (-42, 6, 50), (20, 17, 60), 4, (0, 5, 0), "tibia",
          marrow_centre=(-41.5, 6, 55), marrow_half=(15, 12, 55))
    _bone(p, 1, C, (-48, -30, 48), (8, 7.5, 58), 3, (0, 5, 0), "fibula",
          marrow_centre=(-47.8, -30, 51), marrow_half=(5, 4.5, 55))
    _bone(p, 2, E, (-40, 2, -26), (30, 22, 15), 4, (10, -8, 0), "talus")
    _bone(p, 3, E, (-72, 0, -55), (35, 20, 19), 4, (5, 18, 0), "calcaneus")
    _bone(p, 4, E, (-6, 10, -42), (12, 18, 11), 3, (15, 0, 0), "navicular")
    _bone(p, 5, B, (-18, -22, -56), (14, 12, 10), 3, (-10, 8, 0), "cuboid")
    _bone(p, 6, B, (14, 8, -46), (10, 17, 9), 3, (8, 5, 0), "cuneiforms")
    for j in range(5):  # metatarsals, fanning out, sloping down to the toes
        yk = 20 - 11 * j
        r = 6.5 if j == 0 else 5.0
        _bone(p, 7 + j, C, (55, yk + (2 - j) * 2.5, -57), (r, r, 27), 2.5, ((2 - j) * 4, 98, 0), f"metatarsal {j + 1}")
    _bone(p, 12, C, (92, 18, -64), (5.5, 5, 11), 2, (4, 95, 0), "hallux phalanx")
    return Phantom(
        "foot",
        "Foot and ankle: soft tissue around tibia, fibula, tarsals and metatarsals, each bone a cortical shell around marrow.",
        ("soft tissue", "marrow", "cortical bone"),
        (0.28, 0.50, 0.90),
        tuple(p),
    )


def _arch(ax: float, ay: float, cy: float, phi_deg: float) -> tuple[float, float, float]:
    """Point (x, y) on the dental arch x = ax sin(phi), y = cy + ay cos(phi) and tangent angle (deg)."""
    ph = math.radians(phi_deg)
    x, y = ax * math.sin(ph), cy + ay * math.cos(ph)
    psi = math.degrees(math.atan2(-ay * math.sin(ph), ax * math.cos(ph)))
    return x, y, psi


def _jaw() -> Phantom:
    # z: up (head axis), y: front of the face, x: left/right. Arches open towards -y.
    ST, BONE, TOOTH = 1, 2, 3
    p = [
        _P(E, (0, -5, -5), (64, 70, 58), ST, 1, (0, 0, 0), "lower face soft tissue"),
        _P(C, (0, -50, -5), (10, 7, 55), 0, 2, (0, 0, 0), "airway"),
        _P(E, (0, 2, -4), (28, 24, 4), 0, 2, (0, 0, 0), "oral cavity"),
    ]
    # mandible body: elliptic cylinders laid along the arch (local x vertical, y across, z along the arch)
    for phi in (-70, -35, 0, 35, 70):
        x, y, psi = _arch(42, 50, -15, phi)
        p.append(_P(C, (x, y, -36), (15, 7, 17), BONE, 5, (psi, 90, 0), "mandible"))
    for sgn in (-1, 1):  # rami, rising at the back to the condyles
        p.append(_P(B, (sgn * 44, -22, -8), (5, 13, 30), BONE, 5, (sgn * 8, 0, -14), "ramus"))
    for phi in (-62, 0, 62):  # maxillary alveolar arch
        x, y, psi = _arch(44, 52, -15, phi)
        p.append(_P(C, (x, y, 22), (9, 8, 26 if phi else 24), BONE, 5, (psi, 90, 0), "maxilla"))
    p.append(_P(E, (0, 0, 29), (36, 40, 5), BONE, 5, (0, 0, 0), "palate"))
    # teeth: 2 incisors, canine, 2 premolars, molar per side, both arches (roots sit in bone)
    sizes = ((7, 3.0, 2.6), (20, 3.2, 2.7), (33, 3.8, 3.6), (46, 4.0, 4.0), (60, 5.0, 4.8), (75, 5.4, 5.0))
    for phi, a, b in sizes:  # (arch angle deg, semi-axis along the arch, across it)
        for sgn in (-1, 1):
            x, y, psi = _arch(42, 50, -15, sgn * phi)
            p.append(_P(C, (x, y, -20), (a, b, 12.5), TOOTH, 8, (psi, 0, 0), "lower tooth"))
            x, y, psi = _arch(44, 52, -15, sgn * phi)
            p.append(_P(C, (x, y, 14), (a, b, 12), TOOTH, 8, (psi, 0, 0), "upper tooth"))
    return Phantom(
        "jaw",
        "Jaw: mandible and maxilla with dense teeth in little soft tissue, airway and oral cavity as air (high contrast).",
        ("soft tissue", "bone", "enamel"),
        (0.18, 0.62, 1.0),
        tuple(p),
    )


def _chest() -> Phantom:
    # z: head (+) to feet, y: anterior (+), x: left/right.
    LUNG, FAT, ST, BLOOD, BONE = 1, 2, 3, 4, 5
    p = [
        _P(C, (0, 0, 0), (112, 80, 100), FAT, 1, (0, 0, 0), "subcutaneous fat"),
        _P(C, (0, 0, 0), (105, 73, 100), ST, 2, (0, 0, 0), "chest wall and mediastinum"),
    ]
    for zc in (-72, -36, 0, 36, 72):  # rib hoops, sloping down anteriorly: bone ring = outer disc minus inner disc
        p.append(_P(C, (0, 0, zc), (98, 67, 3.5), BONE, 3, (0, 0, -18), "ribs"))
        p.append(_P(C, (0, 0, zc), (92, 61, 4.5), ST, 4, (0, 0, -18), "inside rib cage"))
    p += [
        _P(E, (-50, 0, 8), (40, 44, 86), LUNG, 5, (-8, 0, 0), "right lung"),
        _P(E, (52, -2, 8), (38, 42, 84), LUNG, 5, (10, 0, 0), "left lung"),
        _P(E, (14, 18, -28), (42, 33, 38), BLOOD, 6, (30, 10, 20), "heart"),
        _P(C, (18, -30, 0), (10, 10, 99), BLOOD, 7, (0, 0, 0), "descending aorta"),
        _P(C, (0, -48, 0), (16, 14, 98), BONE, 8, (0, 0, 0), "vertebral bodies"),
        _P(B, (0, -67, 0), (10, 4, 98), BONE, 8, (0, 0, 0), "laminae"),
        _P(C, (0, -58, 0), (6.5, 5.5, 99), ST, 9, (0, 0, 0), "spinal canal"),
        _P(B, (0, 64, -5), (11, 4, 60), BONE, 8, (0, 0, -8), "sternum"),
        _P(B, (-60, -55, 25), (24, 3.5, 45), BONE, 8, (-30, 0, 0), "right scapula"),
        _P(B, (60, -55, 25), (24, 3.5, 45), BONE, 8, (30, 0, 0), "left scapula"),
    ]
    return Phantom(
        "chest",
        "Chest: fat and soft-tissue body, low-attenuation lungs, heart and aorta, rib cage, sternum, scapulae and spine.",
        ("lung", "fat", "soft tissue", "blood", "bone"),
        (0.04, 0.17, 0.25, 0.29, 0.75),
        tuple(p),
    )


def _abdomen() -> Phantom:
    # z: head (+) to feet, y: anterior (+), x: patient left (+) / right (-).
    FAT, MUSCLE, LIVER, KIDNEY, CANC, CORT = 1, 2, 3, 4, 5, 6
    p = [
        _P(C, (0, 0, 0), (112, 82, 96), FAT, 1, (0, 0, 0), "subcutaneous fat"),
        _P(C, (0, -1, 0), (104, 74, 96), MUSCLE, 2, (0, 0, 0), "abdominal wall muscle"),
        _P(C, (0, 3, 0), (95, 64, 97), FAT, 3, (0, 0, 0), "visceral fat"),
        _P(E, (-32, -42, -10), (15, 13, 85), MUSCLE, 4, (0, 0, 0), "right psoas"),
        _P(E, (32, -42, -10), (15, 13, 85), MUSCLE, 4, (0, 0, 0), "left psoas"),
        _P(E, (-30, -63, 0), (22, 11, 96), MUSCLE, 4, (0, 0, 0), "right erector spinae"),
        _P(E, (30, -63, 0), (22, 11, 96), MUSCLE, 4, (0, 0, 0), "left erector spinae"),
        _P(E, (-42, 10, 30), (55, 45, 52), LIVER, 5, (-20, 10, 0), "liver"),
        _P(E, (66, -12, 40), (20, 30, 34), LIVER, 5, (30, 0, 0), "spleen"),
        _P(E, (35, 32, 45), (34, 22, 26), MUSCLE, 5, (35, 0, 15), "stomach"),
        _P(E, (10, 32, -45), (50, 26, 32), MUSCLE, 5, (15, 0, 0), "bowel"),
        _P(C, (12, -22, 0), (9.5, 9.5, 97), MUSCLE, 6, (0, 0, 0), "aorta"),
        _P(C, (-18, -20, 0), (12, 8.5, 97), MUSCLE, 6, (0, 0, 0), "inferior vena cava"),
        _P(E, (-56, -34, -8), (20, 14, 40), KIDNEY, 6, (25, -12, 0), "right kidney"),
        _P(E, (58, -32, 2), (20, 14, 40), KIDNEY, 6, (-25, 12, 0), "left kidney"),
        _P(E, (-48, -30, -8), (7, 5, 14), FAT, 7, (25, -12, 0), "right renal sinus"),
        _P(E, (50, -28, 2), (7, 5, 14), FAT, 7, (-25, 12, 0), "left renal sinus"),
        _P(E, (38, 40, 60), (18, 11, 8), 0, 7, (35, 0, 0), "gastric air"),
        _P(E, (-5, 40, -50), (10, 8, 6), 0, 7, (0, 0, 0), "bowel gas"),
        _P(E, (28, 30, -35), (8, 7, 5), 0, 7, (0, 0, 0), "bowel gas"),
        _P(C, (0, -38, 0), (18, 15, 94), CORT, 8, (0, 0, 0), "vertebral body cortex"),
        _P(C, (0, -38, 0), (15, 12, 94), CANC, 9, (0, 0, 0), "vertebral body cancellous bone"),
        _P(B, (0, -69, 0), (6, 6, 94), CORT, 8, (0, 0, 0), "laminae and spinous process"),
        _P(C, (0, -58, 0), (7, 5, 95), MUSCLE, 10, (0, 0, 0), "spinal canal"),
    ]
    return Phantom(
        "abdomen",
        "Abdomen: fat, muscle wall, liver and spleen, kidneys, stomach and bowel with gas, aorta, spine (four soft levels plus bone).",
        ("fat", "muscle", "liver/spleen", "kidney", "cancellous bone", "cortical bone"),
        (0.15, 0.25, 0.29, 0.33, 0.50, 0.85),
        tuple(p),
    )


_BUILDERS = {"foot": _foot, "jaw": _jaw, "chest": _chest, "abdomen": _abdomen}


def get_phantom(name: str) -> Phantom:
    """The built-in phantom ``name`` (one of :data:`PHANTOM_NAMES`)."""
    key = str(name).strip().lower()
    if key not in _BUILDERS:
        import difflib

        close = difflib.get_close_matches(key, PHANTOM_NAMES, n=1, cutoff=0.6)
        raise SceneError(f"unknown built-in phantom {name!r}" + (f"; did you mean {close[0]}?" if close else "")
                         + f" (choose one of: {', '.join(PHANTOM_NAMES)})")
    return _BUILDERS[key]()
