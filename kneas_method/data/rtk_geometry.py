"""RTK's circular projection geometry, its XML file, and the exact map to kneas's frame.

RTK (``rtk::ThreeDCircularProjectionGeometry``, read from RTK's own sources
``rtkThreeDCircularProjectionGeometry.cxx`` and the XML reader/writer) describes
projection ``i`` by nine numbers: ``SourceToIsocenterDistance`` (SID, mm),
``SourceToDetectorDistance`` (SDD, mm; 0 means parallel beam), ``GantryAngle``
``g``, ``OutOfPlaneAngle``, ``InPlaneAngle`` (degrees in the XML),
``ProjectionOffsetX/Y`` (``px``, ``py``, mm) and ``SourceOffsetX/Y`` (``sx``,
``sy``, mm). In RTK's world frame (ITK physical space, LPS, mm):

* world -> rotated frame: ``x' = Rz(-inplane) Rx(-outofplane) Ry(-g) x`` (ITK's
  Euler ZXY rotation; ``Ry(a) = [[cos a, 0, sin a], [0, 1, 0], [-sin a, 0, cos a]]``),
  so the gantry turns about the world **y** axis and at ``g = 0`` the source sits on +z;
* in the rotated frame the source is at ``(sx, sy, SID)`` and the projection
  pixel whose physical coordinates (from the projection image's origin, spacing
  and direction) are ``(u, v)`` sits at ``(u + px, v + py, SID - SDD)``;
* the 3x4 projection matrix is ``T2(sx - px, sy - py) . K . T3(-sx, -sy, 0) . R``
  with ``K = [[-SDD, 0, 0, 0], [0, -SDD, 0, 0], [0, 0, 1, -SID]]``
  (:func:`projection_matrix`).

kneas (SPEC §1) turns about **z**, puts the source at ``(DSO cos θ, DSO sin θ, 0)``
and its detector axes at ``u = (-sin θ, cos θ, 0)``, ``v = (0, 0, -1)``. The two
detector frames have opposite handedness (kneas ``u × v`` points from the
source to the detector, RTK's points back to the source), so one detector axis
must flip for the object not to be mirrored. With the rows (``v``) flipped the
map is a proper rotation, a cyclic permutation of the axes::

    world_LPS = (y_k, z_k + sy, x_k)        [mm; A = KNEAS_TO_RTK, det +1]
    θ = g                                  (radians; no sign change, no offset)
    kneas row j  <->  RTK row nV - 1 - j    (kneas v = -(RTK v + py - sy))
    kneas column i <-> RTK column i         (kneas u = RTK u + px)

(``sy``, a source offset along the rotation axis, is the same as shifting the
world along that axis; it goes into the affine.) :func:`rtk_to_kneas` applies
it, :func:`kneas_to_rtk` inverts it, :func:`kneas_to_world_affine` is the 4x4
affine from kneas's volume frame (mm) to RTK/ITK LPS world (mm) that imported
scenes store in ``meta["world_affine_lps"]``.

What kneas cannot represent is refused with a one-line :class:`SceneError`:
in-plane/out-of-plane detector tilts, a source offset across the rotation axis
(``sx``: the detector is then not perpendicular to the central ray), a
cylindrical detector, and SID/SDD/offsets that differ between projections.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from ..errors import SceneError
from .naf import atomic_write_bytes

RTK_XML_VERSION = 3
# kneas (x, y, z) -> RTK world LPS: x_w = y_k, y_w = z_k, z_w = x_k (a proper rotation).
KNEAS_TO_RTK = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
WORLD_AFFINE_META = "world_affine_lps"


def scanner_world_affine(scene) -> Optional[np.ndarray]:
    """The ``[4, 4]`` map from kneas's frame (mm) to the scanner's RTK/ITK world (LPS, mm) of an
    imported scene (``scene.meta["world_affine_lps"]``), or None for scenes without a scanner world."""
    stored = scene.meta.get(WORLD_AFFINE_META) if scene is not None else None
    if stored is None:
        return None
    a = np.asarray(stored, dtype=np.float64)
    if a.shape != (4, 4) or not np.all(np.isfinite(a)) or not np.allclose(a[3], [0, 0, 0, 1]):
        raise SceneError(f"the scene's {WORLD_AFFINE_META} is not a 4x4 affine; re-import the scan with kneas-data import")
    return a
FRAME_DESCRIPTION = (
    "RTK/ITK LPS world (mm) = (y_k, z_k + SourceOffsetY, x_k) of kneas's frame (mm); kneas angle = RTK GantryAngle; "
    "kneas detector row j = RTK row nV-1-j (kneas v = -(RTK v + ProjectionOffsetY - SourceOffsetY)); "
    "kneas column i = RTK column i (kneas u = RTK u + ProjectionOffsetX)"
)
# Tolerances for "the same value in every projection" and "zero".
LENGTH_TOL_MM = 1e-6
ANGLE_TOL_DEG = 1e-6
MATRIX_TOL = 1e-3  # RTK's own reader check
_PER_PROJECTION = (
    ("sid", "SourceToIsocenterDistance"),
    ("sdd", "SourceToDetectorDistance"),
    ("source_offset_x", "SourceOffsetX"),
    ("source_offset_y", "SourceOffsetY"),
    ("proj_offset_x", "ProjectionOffsetX"),
    ("proj_offset_y", "ProjectionOffsetY"),
    ("in_plane_deg", "InPlaneAngle"),
    ("out_of_plane_deg", "OutOfPlaneAngle"),
)


# --------------------------------------------------------------------------- RTK's matrices
def _rx(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _ry(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rz(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rotation_zxy(angle_x: float, angle_y: float, angle_z: float) -> np.ndarray:
    """ITK's Euler ZXY rotation ``Rz(az) Rx(ax) Ry(ay)`` [3, 3] (radians)."""
    return _rz(angle_z) @ _rx(angle_x) @ _ry(angle_y)


def world_to_rotated(gantry_deg: float, out_of_plane_deg: float = 0.0, in_plane_deg: float = 0.0) -> np.ndarray:
    """RTK's rotation [3, 3] from world to the projection's rotated frame."""
    r = math.radians
    return rotation_zxy(-r(out_of_plane_deg), -r(gantry_deg), -r(in_plane_deg))


def projection_matrix(sid: float, sdd: float, gantry_deg: float, proj_offset_x: float = 0.0, proj_offset_y: float = 0.0,
                      out_of_plane_deg: float = 0.0, in_plane_deg: float = 0.0, source_offset_x: float = 0.0,
                      source_offset_y: float = 0.0) -> np.ndarray:
    """RTK's 3x4 projection matrix (world mm -> projection-image mm, homogeneous), as RTK computes it."""
    t2 = np.eye(3)
    t2[0, 2], t2[1, 2] = source_offset_x - proj_offset_x, source_offset_y - proj_offset_y
    k = np.zeros((3, 4))
    if sdd == 0.0:  # parallel
        k[0, 0] = k[1, 1] = 1.0
        k[2, 3] = 1.0
    else:
        k[0, 0] = k[1, 1] = -sdd
        k[2, 2] = 1.0
        k[2, 3] = -sid
    t3 = np.eye(4)
    t3[0, 3], t3[1, 3] = -source_offset_x, -source_offset_y
    rot = np.eye(4)
    rot[:3, :3] = world_to_rotated(gantry_deg, out_of_plane_deg, in_plane_deg)
    return t2 @ k @ t3 @ rot


# --------------------------------------------------------------------------- the geometry object
@dataclass
class RTKGeometry:
    """RTK's per-projection parameters (all arrays ``[N]``; lengths mm, angles degrees).

    ``matrices`` [N, 3, 4] are the matrices read from a file (None when built in code);
    ``radius_cylindrical_detector`` (mm, 0 = flat panel) is global.
    """

    gantry_deg: np.ndarray
    sid: np.ndarray
    sdd: np.ndarray
    proj_offset_x: np.ndarray
    proj_offset_y: np.ndarray
    out_of_plane_deg: np.ndarray
    in_plane_deg: np.ndarray
    source_offset_x: np.ndarray
    source_offset_y: np.ndarray
    radius_cylindrical_detector: float = 0.0
    matrices: Optional[np.ndarray] = None
    collimation: dict = field(default_factory=dict)

    @classmethod
    def circular(cls, gantry_deg, sid: float, sdd: float, proj_offset_x: float = 0.0, proj_offset_y: float = 0.0,
                 source_offset_x: float = 0.0, source_offset_y: float = 0.0) -> "RTKGeometry":
        """A circular orbit with the same SID/SDD/offsets for every gantry angle (degrees)."""
        g = np.asarray(gantry_deg, dtype=np.float64).reshape(-1)

        def full(v):
            return np.full(len(g), float(v))

        return cls(gantry_deg=g, sid=full(sid), sdd=full(sdd), proj_offset_x=full(proj_offset_x),
                   proj_offset_y=full(proj_offset_y), out_of_plane_deg=full(0.0), in_plane_deg=full(0.0),
                   source_offset_x=full(source_offset_x), source_offset_y=full(source_offset_y))

    def __len__(self) -> int:
        return int(len(self.gantry_deg))

    def matrix(self, i: int) -> np.ndarray:
        """The projection matrix [3, 4] of projection ``i`` computed from its parameters."""
        return projection_matrix(self.sid[i], self.sdd[i], self.gantry_deg[i], self.proj_offset_x[i], self.proj_offset_y[i],
                                 self.out_of_plane_deg[i], self.in_plane_deg[i], self.source_offset_x[i], self.source_offset_y[i])

    def source_position(self, i: int) -> np.ndarray:
        """World position (mm) of the source of projection ``i`` (cone beam)."""
        rot = world_to_rotated(self.gantry_deg[i], self.out_of_plane_deg[i], self.in_plane_deg[i])
        return rot.T @ np.array([self.source_offset_x[i], self.source_offset_y[i], self.sid[i]])


# --------------------------------------------------------------------------- XML reading
def _number(text: Optional[str], tag: str, label: str) -> float:
    try:
        value = float((text or "").strip())
    except ValueError:
        raise SceneError(f"{label}: <{tag}> holds {(text or '').strip()[:30]!r}, not a number; fix the geometry file") from None
    if not math.isfinite(value):
        raise SceneError(f"{label}: <{tag}> is {value}; every geometry value must be finite")
    return value


def read_rtk_geometry(path) -> RTKGeometry:
    """Read an RTK geometry XML file (``RTKThreeDCircularGeometry`` version 2 or 3).

    Follows RTK's reader: a value given before the first ``<Projection>`` (or in
    a previous one) holds for every later projection until it is given again;
    each projection's ``<Matrix>``, when present, must agree with the matrix
    computed from its parameters (RTK's tolerance, 0.001).

    Raises:
        SceneError: unreadable or malformed file, one line.
    """
    path = Path(path)
    label = path.name
    if not path.is_file():
        raise SceneError(f"{path}: no such geometry file; give RTK's geometry XML with --geometry")
    state = {name: 0.0 for name, _ in _PER_PROJECTION}
    state["gantry_deg"] = 0.0
    tag_to_key = {tag.lower(): name for name, tag in _PER_PROJECTION}
    tag_to_key["gantryangle"] = "gantry_deg"
    tag_to_key["angle"] = "gantry_deg"  # RTK's backward-compatible name
    collimation_tags = {"collimationuinf", "collimationusup", "collimationvinf", "collimationvsup"}
    collimation_state = {t: math.inf for t in collimation_tags}
    rows: dict[str, list[float]] = {name: [] for name in list(state)}
    collimation: dict[str, list[float]] = {t: [] for t in collimation_tags}
    matrices: list[Optional[np.ndarray]] = []
    current_matrix: Optional[np.ndarray] = None
    radius = 0.0
    root_seen = False
    try:
        for event, elem in ET.iterparse(str(path), events=("start", "end")):
            tag = elem.tag.lower() if isinstance(elem.tag, str) else ""
            if event == "start":
                if not root_seen:
                    root_seen = True
                    if tag != "rtkthreedcirculargeometry":
                        raise SceneError(f"{label}: the root element is <{elem.tag}>, not <RTKThreeDCircularGeometry>; "
                                         "give RTK's geometry XML (rtksimulatedgeometry, rtkvarianobigeometry, ... write one)")
                    version = elem.attrib.get("version")
                    if version not in ("2", "3"):
                        raise SceneError(f"{label}: RTK geometry version {version!r} is not supported (2 or 3); "
                                         "re-generate the file with a current RTK")
                if tag == "projection":
                    current_matrix = None
                continue
            if tag in tag_to_key:
                state[tag_to_key[tag]] = _number(elem.text, elem.tag, label)
            elif tag in collimation_tags:
                collimation_state[tag] = _number(elem.text, elem.tag, label)
            elif tag == "radiuscylindricaldetector":
                radius = _number(elem.text, elem.tag, label)
            elif tag == "matrix":
                values = (elem.text or "").split()
                try:
                    m = np.array([float(v) for v in values], dtype=np.float64)
                except ValueError:
                    raise SceneError(f"{label}: a <Matrix> holds text that is not numbers; fix the geometry file") from None
                if m.size != 12 or not np.all(np.isfinite(m)):
                    raise SceneError(f"{label}: a <Matrix> has {m.size} values; RTK writes 12 (3 rows of 4)")
                current_matrix = m.reshape(3, 4)
            elif tag == "projection":
                for name in rows:
                    rows[name].append(state[name])
                for t in collimation_tags:
                    collimation[t].append(collimation_state[t])
                matrices.append(current_matrix)
                elem.clear()
    except ET.ParseError as exc:
        raise SceneError(f"{label} is not readable XML ({exc}); give RTK's geometry XML file") from None
    except OSError as exc:
        raise SceneError(f"{path}: cannot read it ({exc.strerror or exc}); check the file") from None
    n = len(rows["gantry_deg"])
    if n == 0:
        raise SceneError(f"{label} holds no <Projection>; an RTK geometry needs one per projection image")
    arrays = {name: np.asarray(v, dtype=np.float64) for name, v in rows.items()}
    geom = RTKGeometry(
        gantry_deg=arrays["gantry_deg"], sid=arrays["sid"], sdd=arrays["sdd"], proj_offset_x=arrays["proj_offset_x"],
        proj_offset_y=arrays["proj_offset_y"], out_of_plane_deg=arrays["out_of_plane_deg"], in_plane_deg=arrays["in_plane_deg"],
        source_offset_x=arrays["source_offset_x"], source_offset_y=arrays["source_offset_y"], radius_cylindrical_detector=radius,
        collimation={t: np.asarray(v) for t, v in collimation.items() if np.any(np.isfinite(v))},
    )
    if all(m is not None for m in matrices):
        geom.matrices = np.stack(matrices)
    for i, m in enumerate(matrices):
        if m is not None:
            diff = float(np.max(np.abs(m - geom.matrix(i))))
            if diff > MATRIX_TOL:
                raise SceneError(f"{label}: the <Matrix> of projection {i} disagrees with its parameters (max difference {diff:.3g}); "
                                 "the file is inconsistent, re-generate it with RTK")
    return geom


# --------------------------------------------------------------------------- XML writing
def _fmt(v: float) -> str:
    return repr(float(v)) if float(v) != int(v) or abs(v) >= 1e15 else str(int(v))


def rtk_geometry_xml(geom: RTKGeometry) -> str:
    """RTK's XML text for ``geom`` (the layout of RTK's own writer, version 3)."""
    lines = ['<?xml version="1.0"?>', "<!DOCTYPE RTKGEOMETRY>", f'<RTKThreeDCircularGeometry version="{RTK_XML_VERSION}">']
    globals_: dict[str, bool] = {}
    for name, tag in _PER_PROJECTION:
        arr = np.asarray(getattr(geom, name), dtype=np.float64)
        same = bool(np.all(arr == arr[0]))
        globals_[name] = same
        if same and (arr[0] != 0.0 or name in ("sid", "sdd")):
            lines.append(f"  <{tag}>{_fmt(arr[0])}</{tag}>")
    if geom.radius_cylindrical_detector:
        lines.append(f"  <RadiusCylindricalDetector>{_fmt(geom.radius_cylindrical_detector)}</RadiusCylindricalDetector>")
    for i in range(len(geom)):
        lines.append("  <Projection>")
        lines.append(f"    <GantryAngle>{_fmt(geom.gantry_deg[i])}</GantryAngle>")
        for name, tag in _PER_PROJECTION:
            if not globals_[name]:
                lines.append(f"    <{tag}>{_fmt(getattr(geom, name)[i])}</{tag}>")
        m = geom.matrix(i)
        lines.append("    <Matrix>")
        for row in m:
            lines.append("      " + " ".join(f"{v:.17g}" for v in row))
        lines.append("    </Matrix>")
        lines.append("  </Projection>")
    lines.append("</RTKThreeDCircularGeometry>")
    return "\n".join(lines) + "\n"


def write_rtk_geometry(geom: RTKGeometry, path) -> Path:
    """Write ``geom`` as RTK's geometry XML (atomically). Returns the path."""
    path = Path(path)
    atomic_write_bytes(path, rtk_geometry_xml(geom).encode())
    return path


# --------------------------------------------------------------------------- detector grid
@dataclass(frozen=True)
class DetectorGrid:
    """A projection image's pixel grid in RTK's projection coordinates (mm).

    Pixel ``(i, j)`` (column, row) has physical coordinates
    ``u = origin_u + i * spacing_u``, ``v = origin_v + j * spacing_v`` (after
    :func:`normalise_direction` has turned any axis flips into array flips).
    """

    n_u: int
    n_v: int
    spacing_u: float
    spacing_v: float
    origin_u: float
    origin_v: float

    @property
    def centre_u(self) -> float:
        return self.origin_u + 0.5 * (self.n_u - 1) * self.spacing_u

    @property
    def centre_v(self) -> float:
        return self.origin_v + 0.5 * (self.n_v - 1) * self.spacing_v

    @classmethod
    def centred(cls, n_u: int, n_v: int, spacing_u: float, spacing_v: float) -> "DetectorGrid":
        """A grid whose centre is at ``(0, 0)`` (what :func:`kneas_to_rtk` writes)."""
        return cls(n_u, n_v, spacing_u, spacing_v, -0.5 * (n_u - 1) * spacing_u, -0.5 * (n_v - 1) * spacing_v)


def normalise_direction(stack: np.ndarray, spacing, origin, direction, label: str) -> tuple[np.ndarray, DetectorGrid]:
    """Turn a projection stack with an ITK direction into one with identity direction.

    Args:
        stack: ``[N, nV, nU]`` (ITK's numpy order: row ``j`` = index along the
            image's second axis, column ``i`` along its first).
        spacing, origin: the image's first two spacings/origins (mm).
        direction: the image's direction matrix (at least 2x2); each of its first
            two axes must lie along ±u or ±v without rotation.

    Returns:
        ``(stack, grid)`` with flipped axes reversed in the array.
    """
    d = np.asarray(direction, dtype=np.float64)[:2, :2]
    if abs(d[0, 1]) > 1e-6 or abs(d[1, 0]) > 1e-6 or abs(abs(d[0, 0]) - 1) > 1e-6 or abs(abs(d[1, 1]) - 1) > 1e-6:
        raise SceneError(f"{label}: the projection images are rotated in their plane (direction {d.round(4).tolist()}); "
                         "kneas reads only axis-aligned projections: resample them (e.g. with ITK) to an identity direction")
    n_v, n_u = stack.shape[1], stack.shape[2]
    su, sv = float(spacing[0]), float(spacing[1])
    ou, ov = float(origin[0]), float(origin[1])
    if not (su > 0 and sv > 0):
        raise SceneError(f"{label}: projection pixel spacing is ({su}, {sv}) mm; it must be positive (give --pixel-mm)")
    if d[0, 0] < 0:
        stack = stack[:, :, ::-1]
        ou = ou - (n_u - 1) * su
    if d[1, 1] < 0:
        stack = stack[:, ::-1, :]
        ov = ov - (n_v - 1) * sv
    return stack, DetectorGrid(n_u, n_v, su, sv, ou, ov)


# --------------------------------------------------------------------------- angles
def arc_normalise(angles_rad) -> np.ndarray:
    """Angles [N] (rad, any order) moved by multiples of 2π into one shortest arc.

    The arc leaves out the largest gap between neighbouring angles, so a short
    scan that crosses 0° stays contiguous (RTK stores gantry angles in
    [0°, 360°)). When the angles unwrapped in acquisition order already form
    such an arc they are kept that way (the first angle moved into [0, 2π));
    otherwise (views in another order) the arc starts after the largest gap.
    The order of the views is kept either way.
    """
    a = np.asarray(angles_rad, dtype=np.float64).reshape(-1)
    two_pi = 2 * math.pi
    if len(a) == 0:
        return a
    m = np.mod(a, two_pi)
    if len(a) == 1:
        return m
    s = np.sort(m)
    gaps = np.diff(np.concatenate([s, [s[0] + two_pi]]))
    shortest = two_pi - float(np.max(gaps))
    u = np.unwrap(m)
    u = u - two_pi * math.floor(u[0] / two_pi)
    if float(np.ptp(u)) <= shortest + 1e-9:
        return u
    start = s[(int(np.argmax(gaps)) + 1) % len(s)]
    return start + np.mod(m - start, two_pi)


# --------------------------------------------------------------------------- the mapping
def kneas_to_world_affine(axis_shift_mm: float = 0.0) -> np.ndarray:
    """4x4 affine from kneas's frame (mm) to RTK/ITK LPS world (mm): ``[KNEAS_TO_RTK | (0, shift, 0)]``."""
    aff = np.eye(4)
    aff[:3, :3] = KNEAS_TO_RTK
    aff[1, 3] = float(axis_shift_mm)
    return aff


def axis_shift_of(affine) -> float:
    """The rotation-axis shift (mm) of an affine made by :func:`kneas_to_world_affine`.

    Raises SceneError when ``affine`` is not of that form (only such frames map back onto RTK's geometry).
    """
    a = np.asarray(affine, dtype=np.float64)
    if a.shape != (4, 4) or not np.all(np.isfinite(a)):
        raise SceneError(f"the scene's {WORLD_AFFINE_META} is not a finite 4x4 matrix; re-import the scan")
    expected = kneas_to_world_affine(a[1, 3])
    if not np.allclose(a, expected, atol=1e-9):
        raise SceneError(f"the scene's {WORLD_AFFINE_META} is not kneas's RTK frame map (a permutation plus a shift along the "
                         "rotation axis); it cannot be written as an RTK geometry")
    return float(a[1, 3])


@dataclass
class ImportedGeometry:
    """kneas geometry values (mm, radians) from an RTK geometry + detector grid.

    Attributes:
        mode: ``"cone"`` or ``"parallel"``.
        dso, dsd: mm (parallel: ``dsd`` = 2 ``dso``, unused by kneas).
        angles: [N] kneas angles (rad), in the file's order, moved into one arc.
        n_detector, d_detector, off_detector: ``(nU, nV)``, ``(dU, dV)`` mm, ``(offU, offV)`` mm.
        axis_shift: SourceOffsetY (mm) folded into the world affine (cone beam).
        world_affine: [4, 4] kneas mm -> LPS mm.
        notes: things the user should know (ignored collimation, ...).
    """

    mode: str
    dso: float
    dsd: float
    angles: np.ndarray
    n_detector: tuple[int, int]
    d_detector: tuple[float, float]
    off_detector: tuple[float, float]
    axis_shift: float
    world_affine: np.ndarray
    notes: list = field(default_factory=list)


def _one_value(arr: np.ndarray, what: str, tag: str, label: str, tol: float) -> float:
    arr = np.asarray(arr, dtype=np.float64)
    if float(np.ptp(arr)) > tol:
        i = int(np.argmax(np.abs(arr - arr[0])))
        raise SceneError(f"{label}: {tag} differs between projections ({arr[0]:.6g} in projection 0, {arr[i]:.6g} in projection {i}); "
                         f"kneas needs one {what} for the whole scan")
    return float(np.mean(arr))


def _wrapped_deg(values: np.ndarray) -> np.ndarray:
    return (np.asarray(values, dtype=np.float64) + 180.0) % 360.0 - 180.0


def rtk_to_kneas(geom: RTKGeometry, grid: DetectorGrid, label: str = "geometry") -> ImportedGeometry:
    """Map an RTK geometry and its projections' pixel grid onto kneas's conventions (module docstring).

    The projections themselves must be reordered with :func:`rtk_rows_to_kneas`.

    Raises:
        SceneError: for what kneas cannot represent (tilts, ``SourceOffsetX``,
            cylindrical detectors, values that differ between projections).
    """
    if geom.radius_cylindrical_detector:
        raise SceneError(f"{label}: RadiusCylindricalDetector is {geom.radius_cylindrical_detector:g} mm; kneas models flat "
                         "panels only (cylindrical detectors are not supported)")
    for arr, tag in ((geom.in_plane_deg, "InPlaneAngle"), (geom.out_of_plane_deg, "OutOfPlaneAngle")):
        w = _wrapped_deg(arr)
        if np.any(np.abs(w) > ANGLE_TOL_DEG):
            raise SceneError(f"{label}: {tag} is {w[np.argmax(np.abs(w))]:.6g} deg; kneas supports only untilted detectors "
                             f"({tag} 0): correct the tilt in RTK (resample the projections) or use RTK for this scan")
    sid = _one_value(geom.sid, "source-isocentre distance", "SourceToIsocenterDistance", label, LENGTH_TOL_MM)
    sdd = _one_value(geom.sdd, "source-detector distance", "SourceToDetectorDistance", label, LENGTH_TOL_MM)
    px = _one_value(geom.proj_offset_x, "detector offset", "ProjectionOffsetX", label, LENGTH_TOL_MM)
    py = _one_value(geom.proj_offset_y, "detector offset", "ProjectionOffsetY", label, LENGTH_TOL_MM)
    parallel = sdd == 0.0
    notes = []
    if parallel:
        mode, sy = "parallel", 0.0
        if sid <= 0:
            raise SceneError(f"{label}: SourceToIsocenterDistance is {sid:g} mm; it must be positive")
        dso, dsd = sid, 2.0 * sid
        if np.any(geom.source_offset_x != 0) or np.any(geom.source_offset_y != 0):
            notes.append("parallel beam: RTK's source offsets do not move parallel rays and were ignored")
    else:
        mode = "cone"
        sx = _one_value(geom.source_offset_x, "source offset", "SourceOffsetX", label, LENGTH_TOL_MM)
        sy = _one_value(geom.source_offset_y, "source offset", "SourceOffsetY", label, LENGTH_TOL_MM)
        if abs(sx) > LENGTH_TOL_MM:
            raise SceneError(f"{label}: SourceOffsetX is {sx:g} mm; kneas needs the source on the line through the rotation axis "
                             "perpendicular to the detector (SourceOffsetX 0); a sideways source offset tilts the detector "
                             "relative to the central ray, which kneas does not model")
        if not (sid > 0 and sdd > sid):
            raise SceneError(f"{label}: SourceToIsocenterDistance {sid:g} mm and SourceToDetectorDistance {sdd:g} mm; kneas needs "
                             "0 < SID < SDD (the detector behind the rotation axis)")
        dso, dsd = sid, sdd
    if geom.collimation:
        notes.append("RTK collimation limits were ignored (kneas uses every detector pixel)")
    angles = arc_normalise(np.radians(geom.gantry_deg))
    py_eff = py - sy
    off_u = grid.centre_u + px
    off_v = -(grid.centre_v + py_eff)
    return ImportedGeometry(
        mode=mode, dso=dso, dsd=dsd, angles=angles, n_detector=(grid.n_u, grid.n_v),
        d_detector=(grid.spacing_u, grid.spacing_v), off_detector=(off_u, off_v), axis_shift=sy,
        world_affine=kneas_to_world_affine(sy), notes=notes,
    )


def rtk_rows_to_kneas(stack: np.ndarray) -> np.ndarray:
    """RTK projection stack ``[N, nV, nU]`` (identity direction) -> kneas's ``[N, nV, nU]``: rows reversed.
    The same flip maps kneas's stack back to RTK's."""
    return np.ascontiguousarray(np.asarray(stack)[:, ::-1, :])


kneas_rows_to_rtk = rtk_rows_to_kneas


def kneas_to_rtk(geometry, angles, axis_shift_mm: float = 0.0, geometry_mm: Optional[dict] = None) -> tuple[RTKGeometry, DetectorGrid]:
    """The RTK geometry and a centred detector grid for a kneas :class:`Geometry` and angles [N] (rad).

    Inverse of :func:`rtk_to_kneas` (up to where the offsets sit: this puts the
    detector's centre at the projection origin and every offset into
    ``ProjectionOffsetX/Y``). The projections go through :func:`kneas_rows_to_rtk`.
    ``geometry_mm``: the exact NAF values (mm) of ``geometry`` when known (a
    loaded scene's), to write them without the model-unit round trip.
    """
    g = geometry_mm if geometry_mm is not None else geometry.to_mm()
    g = {k: np.asarray(v, dtype=np.float64) if k != "mode" else v for k, v in g.items()}
    (nu, nv), (du, dv), (ou, ov) = geometry.n_detector, g["dDetector"], g["offDetector"]
    grid = DetectorGrid.centred(int(nu), int(nv), float(du), float(dv))
    angles_deg = np.degrees(np.asarray(angles, dtype=np.float64).reshape(-1))
    if geometry.mode == "parallel":
        geom = RTKGeometry.circular(angles_deg, sid=float(g["DSO"]), sdd=0.0, proj_offset_x=float(ou), proj_offset_y=float(-ov))
    else:
        geom = RTKGeometry.circular(angles_deg, sid=float(g["DSO"]), sdd=float(g["DSD"]), proj_offset_x=float(ou),
                                    proj_offset_y=float(-ov + axis_shift_mm), source_offset_y=float(axis_shift_mm))
    return geom, grid


def world_grid_of(geometry, world_affine) -> dict:
    """The kneas voxel grid as an axis-aligned ITK image grid in world LPS (mm).

    Returns ``{"size": (n0, n1, n2), "spacing": (...), "origin": (...), "order": (a0, a1, a2)}``
    where world axis ``w`` runs along kneas axis ``order[w]`` (the volume array
    ``vol[x, y, z]`` becomes ``np.transpose(vol, order)`` indexed ``[w0, w1, w2]``).
    Only signed-permutation affines (as :func:`kneas_to_world_affine`) are accepted.
    """
    import torch

    a = np.asarray(world_affine, dtype=np.float64)
    rot = a[:3, :3]
    order, signs = [], []
    for w in range(3):
        k = int(np.argmax(np.abs(rot[w])))
        if abs(abs(rot[w, k]) - 1) > 1e-9 or np.count_nonzero(np.abs(rot[w]) > 1e-9) != 1:
            raise SceneError("the scene's world affine is not an axis permutation; cannot write an axis-aligned image")
        order.append(k)
        signs.append(1.0 if rot[w, k] > 0 else -1.0)
    mm = geometry.mm_per_unit
    axes = [ax.numpy() * mm for ax in geometry.voxel_axes(dtype=torch.float64)]
    spacing = [float(geometry.d_voxel[k]) * mm for k in order]
    size = [int(geometry.n_voxel[k]) for k in order]
    first_k = np.array([axes[0][0], axes[1][0], axes[2][0]])
    last_k = np.array([axes[0][-1], axes[1][-1], axes[2][-1]])
    origin = []
    for w in range(3):
        k = order[w]
        value = first_k[k] if signs[w] > 0 else last_k[k]
        origin.append(float(signs[w] * value + a[w, 3]))
    return {"size": tuple(size), "spacing": tuple(spacing), "origin": tuple(origin), "order": tuple(order), "signs": tuple(signs)}


def volume_to_world_array(volume: np.ndarray, grid: dict) -> np.ndarray:
    """kneas ``vol[x, y, z]`` -> ``[w0, w1, w2]`` on :func:`world_grid_of`'s grid (flips included)."""
    out = np.transpose(np.asarray(volume), grid["order"])
    for w, s in enumerate(grid["signs"]):
        if s < 0:
            out = np.flip(out, axis=w)
    return np.ascontiguousarray(out)


def world_array_to_volume(array: np.ndarray, grid: dict) -> np.ndarray:
    """Inverse of :func:`volume_to_world_array`: ``[w0, w1, w2]`` -> kneas ``vol[x, y, z]``."""
    out = np.asarray(array)
    for w, s in enumerate(grid["signs"]):
        if s < 0:
            out = np.flip(out, axis=w)
    return np.ascontiguousarray(np.transpose(out, np.argsort(grid["order"])))


def itk_array_of_world(array_w: np.ndarray) -> np.ndarray:
    """``[w0, w1, w2]`` (world axis order) -> ITK's numpy order ``[w2, w1, w0]``."""
    return np.ascontiguousarray(np.transpose(np.asarray(array_w), (2, 1, 0)))
