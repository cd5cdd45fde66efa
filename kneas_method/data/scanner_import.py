"""Import a user's cone-beam scan: projection images + RTK geometry XML -> a kneas :class:`Scene`.

Steps (:func:`import_scan`):

1. **Read** the projections through ITK (:func:`read_projections`): one stack
   file, several files (one or more projections each), a folder or a glob, in
   natural name order (``p2`` before ``p10``). Each projection image's origin,
   spacing and direction give RTK's detector coordinates ``(u, v)`` (mm), exactly
   as RTK reads them; ``--pixel-mm`` / ``--centre-detector`` override them for
   formats that carry none (TIFF).
2. **Convert** to line integrals ``p = ∫ mu dl`` (:func:`to_line_integrals`):
   raw counts ``p = -ln((I - dark) / (flat - dark))`` (``flat`` = a flat-field
   image, or one number ``I0`` given with ``--i0`` or estimated from the air
   around the object at the projections' border); normalised intensities
   ``p = -ln(I)``; data that already are line integrals are kept. The kind is
   detected (:func:`detect_kind`) unless given.
3. **Geometry**: RTK's XML is mapped onto kneas's frame by
   :mod:`~kneas_method.data.rtk_geometry` (rows flipped, angles kept, offsets
   moved into ``offDetector``; tilts and the like refused).
4. **Grid**: unless given, a reconstruction grid covering the field of view
   (:func:`default_grid`).
5. The :class:`Scene` has every projection in ``train``, an empty ``val``, no
   ``image``; ``meta`` records the source files, the conversion and the frame map
   (``meta["world_affine_lps"]``: kneas mm -> RTK/ITK LPS world mm).

Units: lengths mm in the files and the NAF keys; line integrals are unitless
(``∫ mu dl``) and kneas reads them as ``mu`` in 1/m times length in m, so a kneas
reconstruction is in 1/m, RTK's of the same data in 1/mm (x1000 apart).
"""

from __future__ import annotations

import glob as globmod
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from ..errors import ConfigError, SceneError
from ..geometry import Geometry
from .rtk_geometry import (
    FRAME_DESCRIPTION,
    WORLD_AFFINE_META,
    DetectorGrid,
    ImportedGeometry,
    normalise_direction,
    read_rtk_geometry,
    rtk_rows_to_kneas,
    rtk_to_kneas,
)
from .itk_io import IMAGE_SUFFIXES
from .naf import check_line_integrals
from .scene import Scene, Views

KINDS = ("auto", "counts", "normalized", "line-integrals")
MIN_RATIO = 1e-6  # (I - dark)/(flat - dark) is clamped here: p <= ln(1e6) = 13.8
BORDER_FRACTION = 0.05  # width of the border strip used to find air, as a fraction of each side
DEFAULT_MAX_VOXELS = 256  # default grid: at most this many voxels along the largest side
IMPORT_META = "import"


# --------------------------------------------------------------------------- files
def _natural_key(path: Path):
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", path.name)]


def _suffix(path: Path) -> str:
    name = path.name.lower()
    return ".nii.gz" if name.endswith(".nii.gz") else path.suffix.lower()


def projection_files(specs: Sequence[str]) -> list[Path]:
    """The image files named by ``specs`` (files, folders, glob patterns), in order.

    Files keep the order given; a folder or a glob contributes its image files
    (:data:`IMAGE_SUFFIXES`) sorted by natural name order.
    """
    out: list[Path] = []
    for spec in specs:
        path = Path(spec).expanduser()
        if path.is_file():
            out.append(path)
        elif path.is_dir():
            files = sorted((p for p in path.iterdir() if p.is_file() and _suffix(p) in IMAGE_SUFFIXES), key=_natural_key)
            if not files:
                raise SceneError(f"{path} holds no projection images ({', '.join(IMAGE_SUFFIXES[:6])}, ...); give the files or a glob")
            out.extend(files)
        elif any(c in str(spec) for c in "*?["):
            files = sorted((Path(p) for p in globmod.glob(str(path)) if Path(p).is_file()), key=_natural_key)
            if not files:
                raise SceneError(f"the pattern {spec!r} matches no files; check the path (quote it so the shell does not expand it)")
            out.extend(files)
        else:
            raise SceneError(f"{spec}: no such file or folder; give projection image files, a folder or a glob")
    return out


# --------------------------------------------------------------------------- reading
@dataclass
class ProjectionStack:
    """Projection images as read.

    Attributes:
        data: [N, nV, nU] float32 raw values, RTK row order, identity direction.
        grid: their detector grid (mm).
        files: the files, in order.
        dtype: the files' pixel type (e.g. ``uint16``).
        notes: remarks for the user.
    """

    data: np.ndarray
    grid: DetectorGrid
    files: list = field(default_factory=list)
    dtype: str = "float32"
    notes: list = field(default_factory=list)


def _as_stack(img, label: str) -> np.ndarray:
    arr = img.array
    if arr.ndim == 2:
        arr = arr[None]
    elif arr.ndim == 4 and arr.shape[0] == 1:
        arr = arr[0]
    if arr.ndim != 3:
        raise SceneError(f"{label} has {arr.ndim} dimensions (shape {arr.shape}); projections must be 2-D images or a 3-D stack")
    if not (np.issubdtype(arr.dtype, np.number) or arr.dtype == np.bool_) or np.iscomplexobj(arr):
        raise SceneError(f"{label} has pixel type {arr.dtype}; projections must be real numbers")
    return arr


def read_projections(specs: Sequence[str], *, pixel_mm: Optional[Sequence[float]] = None, centre: bool = False) -> ProjectionStack:
    """Read projection images through ITK into one stack (see module docstring).

    Args:
        specs: files, folders or glob patterns.
        pixel_mm: override the pixel spacing ``(du, dv)`` or ``(d,)`` in mm.
        centre: put the detector centre at ``u = v = 0`` (origin overridden).

    Raises:
        SceneError: unreadable files, images of different sizes or spacings.
        KneasError: ITK not installed.
    """
    from .itk_io import read_image

    files = projection_files(specs)
    stacks, ref = [], None
    for path in files:
        img = read_image(path)
        arr = _as_stack(img, path.name)
        info = (arr.shape[1:], tuple(np.round(img.spacing[:2], 9)), tuple(np.round(img.origin[:2], 6)),
                tuple(np.round(img.direction[:2, :2].ravel(), 9)))
        if ref is None:
            ref = (info, img)
        elif info[0] != ref[0][0]:
            raise SceneError(f"{path.name} is {info[0][1]}x{info[0][0]} pixels but {files[0].name} is {ref[0][0][1]}x{ref[0][0][0]}; "
                             "all projections must have the same size")
        elif info[1:] != ref[0][1:]:
            raise SceneError(f"{path.name} has another pixel spacing, origin or direction than {files[0].name}; "
                             "all projections must share one detector grid")
        stacks.append(arr)
    first = ref[1]
    dtype = str(stacks[0].dtype)
    data = np.concatenate([s.astype(np.float32, copy=False) for s in stacks], 0) if len(stacks) > 1 else stacks[0].astype(np.float32)
    notes = []
    spacing = np.array(first.spacing[:2], dtype=np.float64)
    origin = np.array(first.origin[:2], dtype=np.float64)
    if pixel_mm is not None:
        pm = [float(v) for v in pixel_mm]
        if len(pm) not in (1, 2) or not all(math.isfinite(v) and v > 0 for v in pm):
            raise ConfigError(f"--pixel-mm {pixel_mm}: give one or two positive pixel sizes in mm")
        spacing = np.array(pm * 2 if len(pm) == 1 else pm)
    label = files[0].name if len(files) == 1 else f"{files[0].name}..{files[-1].name}"
    data, grid = normalise_direction(data, spacing, origin, first.direction, label)
    if centre:
        grid = DetectorGrid.centred(grid.n_u, grid.n_v, grid.spacing_u, grid.spacing_v)
    elif pixel_mm is None and np.allclose(spacing, 1.0) and np.allclose(origin, 0.0) and grid.n_u > 1:
        notes.append("the projections carry pixel spacing 1 mm and origin (0, 0) (no geometry in the files?): the first "
                     "pixel is on the central ray, as RTK would read them; give --pixel-mm and --centre-detector if that is wrong")
    return ProjectionStack(data=np.ascontiguousarray(data), grid=grid, files=[str(f) for f in files], dtype=dtype, notes=notes)


def read_field(spec: str, grid: DetectorGrid, what: str) -> np.ndarray:
    """A flat or dark field ``[nV, nU]`` (float64, RTK row order): the mean of its frames.

    ``spec`` is a file, folder or glob; its images must match the projections' size.
    """
    stack = read_projections([spec])
    data = stack.data
    if data.shape[1:] != (grid.n_v, grid.n_u):
        raise SceneError(f"the {what} field is {data.shape[2]}x{data.shape[1]} pixels but the projections are "
                         f"{grid.n_u}x{grid.n_v}; give a {what} image of the detector's size")
    return data.astype(np.float64).mean(0)


# --------------------------------------------------------------------------- conversion
def border_mask(n_v: int, n_u: int, fraction: float = BORDER_FRACTION) -> np.ndarray:
    """[nV, nU] bool: the outer strip (``fraction`` of each side, at least 1 pixel) of a projection."""
    bv, bu = max(1, int(round(n_v * fraction))), max(1, int(round(n_u * fraction)))
    m = np.zeros((n_v, n_u), bool)
    m[:bv], m[-bv:], m[:, :bu], m[:, -bu:] = True, True, True, True
    return m


def _sample(values: np.ndarray, n: int = 2_000_000) -> np.ndarray:
    flat = np.asarray(values).reshape(-1)
    if flat.size <= n:
        return flat
    return flat[:: int(math.ceil(flat.size / n))]


def detect_kind(data: np.ndarray) -> str:
    """Guess what projection values are: ``"counts"``, ``"normalized"`` or ``"line-integrals"``.

    Air (around the object) is the brightest part of an intensity image and the
    darkest part of a line-integral image. The border strip of the projections
    (:func:`border_mask`) is taken as mostly air: if its median sits at the top of
    the value range the data are intensities (counts when above 2, normalised when
    at most 2), if it sits at the bottom and the values stay below 50 they are
    line integrals.

    Raises:
        SceneError: when it cannot tell (one line naming ``--kind``).
    """
    d = np.asarray(data)
    border = _sample(d[:, border_mask(d.shape[1], d.shape[2])])
    allv = _sample(d)
    b = float(np.median(border))
    lo, hi = (float(v) for v in np.percentile(allv, [1, 99]))
    top = float(np.max(allv))
    span = max(hi - lo, 1e-12)
    if b >= lo + 0.8 * span:
        return "normalized" if top <= 2.0 else "counts"
    if b <= lo + 0.2 * span and top < 50.0:
        return "line-integrals"
    raise SceneError(
        f"cannot tell whether the projections are counts, normalised intensities or line integrals (border median {b:.4g}, "
        f"values {lo:.4g}..{hi:.4g}); say which with --kind counts|normalized|line-integrals"
    )


AIR_MIN_FRACTION = 0.1  # of the border pixels
AIR_MAX_SPREAD = 0.05  # robust relative spread of the air level (noise, source and gain variations)


def estimate_i0(counts: np.ndarray) -> tuple[float, dict]:
    """Unattenuated intensity ``I0`` from the air at the projections' border.

    Takes the border strips (:func:`border_mask`) of every projection, keeps the
    bright cluster (within 10 % of the 99th percentile, then within 3 robust
    sigmas of its median, twice) and returns its median. The cluster must be
    air: at least :data:`AIR_MIN_FRACTION` of the border, and flat (robust
    relative spread at most :data:`AIR_MAX_SPREAD`; a beam that varies more
    across the detector needs a flat field anyway).

    Returns:
        ``(I0, info)``; info has ``air_fraction`` of the border and ``relative_noise``.

    Raises:
        SceneError: when the border holds too little flat air (naming ``--flat`` / ``--i0``).
    """
    border = _sample(np.asarray(counts)[:, border_mask(counts.shape[1], counts.shape[2])]).astype(np.float64)
    hint = ("give a flat field with --flat FLAT (an image taken without the object) or the unattenuated intensity "
            "with --i0 VALUE")
    top = float(np.percentile(border, 99))
    if not top > 0:
        raise SceneError(f"the projections' border is not brighter than 0 (99th percentile {top:.4g}); cannot estimate I0: {hint}")
    air = border[border >= 0.9 * top]
    for _ in range(2):
        med = float(np.median(air))
        sigma = 1.4826 * float(np.median(np.abs(air - med)))
        air = border[np.abs(border - med) <= max(3 * sigma, 1e-6 * med)]
    fraction = air.size / border.size
    i0 = float(np.median(air))
    spread = 1.4826 * float(np.median(np.abs(air - i0))) / i0 if i0 > 0 else math.inf
    if fraction < AIR_MIN_FRACTION or air.size < 20:
        raise SceneError(f"only {100 * fraction:.1f} % of the projections' border looks like air, too little to estimate I0: {hint}")
    if spread > AIR_MAX_SPREAD:
        raise SceneError(f"the brightest part of the projections' border varies by {100 * spread:.1f} % (not a flat air level), "
                         f"so I0 cannot be estimated from it: {hint}")
    return i0, {"air_fraction": round(fraction, 4), "relative_noise": spread}


def check_finite_views(data: np.ndarray) -> None:
    """Refuse projections ``[N, nV, nU]`` with NaN or inf pixels, naming the views (one-line SceneError)."""
    finite = np.isfinite(np.asarray(data)).reshape(len(data), -1)
    bad = np.flatnonzero(~finite.all(axis=1))
    if bad.size:
        listed = ", ".join(str(int(k)) for k in bad[:10]) + (f" and {bad.size - 10} more" if bad.size > 10 else "")
        raise SceneError(f"{int((~finite).sum())} NaN/inf pixels in {bad.size} of {len(data)} projections (indices {listed}, from 0): "
                         "fix those images, or drop them and their <Projection> entries from the geometry")


def check_given_i0(counts: np.ndarray, i0: float, dark=None) -> None:
    """Refuse an ``--i0`` well below the counts of the air at the projections' border (one-line SceneError)."""
    border = _sample(np.asarray(counts)[:, border_mask(counts.shape[1], counts.shape[2])]).astype(np.float64)
    offset = float(np.mean(dark)) if dark is not None else 0.0
    top = float(np.percentile(border, 99)) - offset
    if top > 1.1 * (i0 - offset):
        raise SceneError(f"--i0 {i0:g} is below the counts at the projections' border ({top:.6g} at its 99th percentile, the air): "
                         "I0 is the count without the object; give that, or leave --i0 out to estimate it from the air")


def kind_mismatch(data: np.ndarray, kind: str) -> Optional[str]:
    """A warning where ``--kind`` says ``kind`` but :func:`detect_kind` reads ``data`` as another
    kind (the border is taken as air: an object that fills it can fool the test, so not refused)."""
    try:
        seen = detect_kind(data)
    except SceneError:
        return None
    intensities = ("counts", "normalized")
    if seen == kind or (seen in intensities and kind in intensities):
        return None
    how = ("sits at the top of their values, as air does in intensities" if seen in intensities
           else "sits at the bottom of their values, as air does in line integrals")
    return (f"--kind {kind}, but the projections' border (mostly air) {how}: they read as {seen}; if the border is air, drop "
            f"--kind (or give --kind {seen})")


def to_line_integrals(data: np.ndarray, kind: str = "auto", *, flat: Optional[np.ndarray] = None,
                      dark: Optional[np.ndarray] = None, i0: Optional[float] = None) -> tuple[np.ndarray, dict]:
    """Projection values -> line integrals ``p`` [N, nV, nU] float32.

    Args:
        data: [N, nV, nU] raw values.
        kind: ``"counts"``, ``"normalized"`` (``I/I0``), ``"line-integrals"`` or ``"auto"``
            (:func:`detect_kind`; counts whenever ``flat``/``dark``/``i0`` is given).
        flat, dark: [nV, nU] flat and dark fields (counts only).
        i0: unattenuated intensity (counts, instead of a flat field).

    Returns:
        ``(p, info)``: info records the kind, the formula, I0 and how many pixels were clamped.
    """
    if kind not in KINDS:
        raise ConfigError(f"--kind {kind!r} is not known; use one of {', '.join(KINDS)}")
    warning = None
    if kind == "auto":
        kind = "counts" if (flat is not None or dark is not None or i0 is not None) else detect_kind(data)
        detected = True
    else:
        detected = False
        warning = kind_mismatch(data, kind)
    info: dict = {"kind": kind, "detected": detected}
    if warning:
        info["kind_warning"] = warning
    if kind != "counts" and (flat is not None or dark is not None or i0 is not None):
        raise ConfigError(f"--flat/--dark/--i0 apply to raw counts, but the projections are given as {kind}; drop them or use --kind counts")
    if kind == "line-integrals":
        info["formula"] = "p as given (already line integrals)"
        return np.ascontiguousarray(data, dtype=np.float32), info
    if kind == "normalized":
        ratio = np.asarray(data, dtype=np.float64)
        info["formula"] = "p = -ln(I)  (intensities already normalised by I0)"
        scale = 1.0
        offset = None
    else:
        if i0 is not None and flat is not None:
            raise ConfigError("give either --flat or --i0, not both")
        offset = dark
        if flat is not None:
            scale = np.asarray(flat, dtype=np.float64) - (dark if dark is not None else 0.0)
            bad = int(np.count_nonzero(scale <= 0))
            if bad:
                raise SceneError(f"the flat field minus the dark field is <= 0 in {bad} pixels; check --flat and --dark (swapped?)")
            info["formula"] = "p = -ln((I - dark) / (flat - dark))" if dark is not None else "p = -ln(I / flat)"
        else:
            if i0 is None:
                corrected = np.asarray(data, dtype=np.float64) - (dark if dark is not None else 0.0)
                i0, i0_info = estimate_i0(corrected)
                info["i0_estimated_from"] = "air at the projections' border"
                info.update(i0_info)
            if not (math.isfinite(float(i0)) and float(i0) > 0):
                raise ConfigError(f"--i0 is {i0}; it must be a positive intensity (the counts without the object)")
            if "i0_estimated_from" not in info:
                check_given_i0(data, float(i0), dark)
            scale = float(i0) - (dark if dark is not None else 0.0)
            if np.any(np.asarray(scale) <= 0):
                raise SceneError("I0 minus the dark field is <= 0; check --i0 and --dark")
            info["i0"] = float(i0)
            info["formula"] = "p = -ln((I - dark) / (I0 - dark))" if dark is not None else "p = -ln(I / I0)"
    out = np.empty(np.shape(data), dtype=np.float32)
    clamped = 0
    for k in range(len(data)):  # one projection at a time: bounded memory
        num = np.asarray(data[k], dtype=np.float64)
        if offset is not None:
            num = num - offset
        ratio = num / scale
        low = ratio < MIN_RATIO
        clamped += int(np.count_nonzero(low))
        out[k] = -np.log(np.where(low, MIN_RATIO, ratio))
    info["clamped_pixels"] = clamped
    if clamped:
        info["clamped_note"] = f"{clamped} pixels at or below {MIN_RATIO:g} of the flat were clamped to p = {-math.log(MIN_RATIO):.3g}"
    return out, info


# --------------------------------------------------------------------------- grid
# the detector's width at the isocentre must be at least this fraction of the source's distance
# to it: a CT field of view is about a quarter of it, a micro- or nano-CT's a few percent; pixel
# spacings written in metres instead of mm (the usual mistake) give about 1e-4
MIN_FOV_FRACTION = 1e-3


def check_detector_scale(geo: ImportedGeometry) -> None:
    """Refuse a detector that is too small for its geometry to be real (spacing in metres, not mm).

    Raises:
        SceneError: naming the detector's width, the field of view it gives and ``--pixel-mm``.
    """
    if geo.mode != "cone":
        return
    width = float(geo.n_detector[0] * geo.d_detector[0])
    fov = width * geo.dso / geo.dsd
    if fov < MIN_FOV_FRACTION * geo.dso:
        scaled = " ".join(f"{1000 * d:.4g}" for d in dict.fromkeys(geo.d_detector))
        raise SceneError(
            f"the detector is {width:.4g} mm wide ({geo.d_detector[0]:.4g} mm pixels), a {fov:.4g} mm field of view with the source "
            f"{geo.dso:.6g} mm from the isocentre; the projections' pixel spacing is probably in metres, not mm: "
            f"give --pixel-mm {scaled} (or write the images with their spacing in mm)")


MIN_FOV_PIXELS = 4  # detector pixels (at the isocentre) across the field of view, below which nothing can be reconstructed


def check_field_of_view(geo: ImportedGeometry, notes: Sequence[str] = ()) -> None:
    """Refuse a field of view a few detector pixels across (the central ray at the detector's edge:
    images without a pixel size or origin, a wrong offset); one-line SceneError naming the fix."""
    radius = default_grid(geo)["fov_radius_mm"]
    pixel = geo.d_detector[0] * (geo.dso / geo.dsd if geo.mode == "cone" else 1.0)
    across = 2 * radius / pixel
    if across >= MIN_FOV_PIXELS:
        return
    why = ("the images carry pixel spacing 1 mm and origin (0, 0) (no geometry in the files, as TIFFs), which puts the central ray "
           "at the first pixel: give --pixel-mm and --centre-detector" if any("origin (0, 0)" in n for n in notes)
           else "check the detector's origin and ProjectionOffsetX, or give --centre-detector")
    raise SceneError(f"the field of view every projection sees is {2 * radius:.3g} mm across ({across:.2g} detector pixels at the "
                     f"isocentre): the central ray meets the detector at its edge; {why}")


def default_grid(geo: ImportedGeometry, *, volume_size: Optional[int] = None, voxel_mm: Optional[float] = None) -> dict:
    """A reconstruction grid (NAF keys, mm) covering the field of view.

    The field of view is the cylinder about the rotation axis seen by the
    detector: radius ``DSO sin(atan(u/DSD))`` with ``u`` the detector's farthest
    column from the central ray for a full 360° scan (an offset "half-fan"
    detector covers twice its short side) and its nearest edge for a short scan;
    height the detector's rows scaled to the isocentre. Parallel beam: the
    detector's extent itself. Voxels are cubes: ``voxel_mm``, else the detector
    pixel at the isocentre, coarsened so that the largest side has at most
    ``volume_size`` (default :data:`DEFAULT_MAX_VOXELS`) voxels; with
    ``volume_size`` given the largest side has exactly that many.

    Returns:
        ``{"nVoxel": [nx, ny, nz], "dVoxel": [d, d, d], "offOrigin": [0, 0, oz], "fov_radius_mm": r, "fov_height_mm": h}``.
    """
    (nu, nv), (du, dv), (ou, ov) = geo.n_detector, geo.d_detector, geo.off_detector
    u_lo, u_hi = ou - nu * du / 2, ou + nu * du / 2
    v_lo, v_hi = ov - nv * dv / 2, ov + nv * dv / 2
    a = np.sort(np.mod(geo.angles, 2 * math.pi))
    gaps = np.diff(np.concatenate([a, [a[0] + 2 * math.pi]])) if len(a) > 1 else np.array([2 * math.pi])
    full = len(a) > 1 and float(np.max(gaps)) <= 2 * (2 * math.pi / len(a)) + 1e-9 and float(np.max(gaps)) < math.pi / 4
    reach = [abs(u_lo), abs(u_hi)]
    u_edge = max(reach) if full else (min(reach) if u_lo < 0 < u_hi else max(reach))
    if geo.mode == "cone":
        r = geo.dso * math.sin(math.atan(u_edge / geo.dsd))
        mag = geo.dso / geo.dsd
    else:
        r, mag = u_edge, 1.0
    z_lo, z_hi = -v_hi * mag, -v_lo * mag
    h = z_hi - z_lo
    extent = max(2 * r, h)
    if volume_size is not None and int(volume_size) < 1:
        raise ConfigError(f"--volume-size {volume_size}: give a positive number of voxels")
    if voxel_mm is not None:
        if not (math.isfinite(voxel_mm) and voxel_mm > 0):
            raise ConfigError(f"--voxel-mm {voxel_mm}: give a positive voxel size in mm")
        d = float(voxel_mm)
    elif volume_size is not None:
        d = extent / int(volume_size)
    else:
        d = max(du * mag, extent / DEFAULT_MAX_VOXELS)
    n_max = int(volume_size) if volume_size is not None else max(1, int(math.ceil(extent / d - 1e-9)))
    nx = ny = max(1, min(n_max, int(math.ceil(2 * r / d - 1e-9))))
    nz = max(1, min(n_max, int(math.ceil(h / d - 1e-9))))
    return {"nVoxel": [nx, ny, nz], "dVoxel": [d, d, d], "offOrigin": [0.0, 0.0, 0.5 * (z_lo + z_hi)],
            "fov_radius_mm": r, "fov_height_mm": h, "full_scan": bool(full)}


def angle_notes(geo: ImportedGeometry, full_scan: bool) -> list[str]:
    """Remarks on the projection angles: projections that share an angle, and an arc shorter than
    a short scan's 180° plus the fan angle (limited angle: every method smears along the directions
    not seen). Accepted as given; the user is told."""
    notes = []
    a = np.mod(np.asarray(geo.angles, dtype=np.float64), 2 * math.pi)
    repeats = len(a) - np.unique(np.round(a, 6)).size
    if repeats:
        notes.append(f"{repeats} of the {len(a)} projections repeat another's angle (to 1e-6 rad): check the geometry's "
                     "GantryAngle values if that is not intended")
    if not full_scan and len(a) > 1:
        (nu, _), (du, _), (ou, _) = geo.n_detector, geo.d_detector, geo.off_detector
        u_most = abs(ou) + nu * du / 2
        fan = 2 * math.atan(u_most / geo.dsd) if geo.mode == "cone" else 0.0
        u = np.unique(np.round(a, 6))
        arc = 2 * math.pi - float(np.max(np.diff(np.concatenate([u, [u[0] + 2 * math.pi]]))))  # all but the largest gap
        step = arc / max(len(u) - 1, 1)
        if arc + step < math.pi + fan - 1e-6:
            notes.append(f"the projections span {math.degrees(arc):.1f} deg, less than a short scan's 180 deg plus the fan's "
                         f"{math.degrees(fan):.1f} deg: a limited-angle scan; every method smears the volume along the directions "
                         "no projection saw")
    return notes


# --------------------------------------------------------------------------- the scene
def _files_meta(files: Sequence[str], limit: int = 20) -> dict:
    files = [str(f) for f in files]
    if len(files) <= limit:
        return {"count": len(files), "files": files}
    return {"count": len(files), "first": files[:3], "last": files[-3:]}


def import_scan(
    projections: Sequence[str],
    geometry_xml,
    *,
    flat: Optional[str] = None,
    dark: Optional[str] = None,
    i0: Optional[float] = None,
    kind: str = "auto",
    volume_size: Optional[int] = None,
    voxel_mm: Optional[float] = None,
    pixel_mm: Optional[Sequence[float]] = None,
    centre_detector: bool = False,
    name: Optional[str] = None,
) -> Scene:
    """Build a kneas scene from projection images and RTK's geometry XML (module docstring).

    Args:
        projections: image files, folders or glob patterns (ITK formats).
        geometry_xml: RTK geometry file, one ``<Projection>`` per projection image.
        flat, dark: flat-/dark-field image files (raw counts; several frames are averaged).
        i0: unattenuated intensity instead of a flat field (counts).
        kind: ``auto``, ``counts``, ``normalized`` or ``line-integrals``.
        volume_size: voxels along the largest side of the grid (default: about one
            detector pixel at the isocentre, at most 256).
        voxel_mm: voxel size in mm.
        pixel_mm, centre_detector: override the projections' pixel spacing / origin.
        name: scene name (default: the geometry file's stem).

    Returns:
        Scene with ``train`` = all projections (kneas row order), ``val`` empty,
        ``image`` None, and ``meta`` recording files, conversion and frame map.
    """
    geometry_xml = Path(geometry_xml)
    rtk_geom = read_rtk_geometry(geometry_xml)
    stack = read_projections(projections, pixel_mm=pixel_mm, centre=centre_detector)
    n_img = stack.data.shape[0]
    if n_img != len(rtk_geom):
        hint = "give exactly the projections the geometry was made for, in its order"
        if len(rtk_geom) in stack.data.shape[1:]:
            n_v, n_u = stack.data.shape[1:]
            hint = (f"the stack reads as {n_img} images of {n_u}x{n_v} pixels, and one of the image axes has {len(rtk_geom)} entries: "
                    "write the stack with the projection index as its last ITK axis (numpy order [projection, v, u])")
        raise SceneError(f"{n_img} projection images but {geometry_xml.name} describes {len(rtk_geom)} projections; {hint}")
    check_finite_views(stack.data)
    imported = rtk_to_kneas(rtk_geom, stack.grid, label=geometry_xml.name)
    check_detector_scale(imported)
    check_field_of_view(imported, stack.notes)
    flat_arr = read_field(flat, stack.grid, "flat") if flat is not None else None
    dark_arr = read_field(dark, stack.grid, "dark") if dark is not None else None
    p_rtk, conversion = to_line_integrals(stack.data, kind, flat=flat_arr, dark=dark_arr, i0=i0)

    first = Path(stack.files[0]).name
    check_line_integrals(p_rtk, first if len(stack.files) == 1 else f"{first}..", "imported projections")
    p = rtk_rows_to_kneas(p_rtk)
    grid = default_grid(imported, volume_size=volume_size, voxel_mm=voxel_mm)
    geometry = Geometry.from_mm(
        mode=imported.mode, DSD=imported.dsd, DSO=imported.dso, nDetector=imported.n_detector, dDetector=imported.d_detector,
        nVoxel=grid["nVoxel"], dVoxel=grid["dVoxel"], offOrigin=grid["offOrigin"], offDetector=imported.off_detector,
    )
    angles = imported.angles
    arc = float(np.ptp(angles)) if len(angles) > 1 else 0.0
    notes = list(stack.notes) + list(imported.notes) + angle_notes(imported, grid["full_scan"])
    if conversion.get("clamped_note"):
        notes.append(conversion["clamped_note"])
    conversion.update({"flat": str(flat) if flat else None, "dark": str(dark) if dark else None, "pixel_type": stack.dtype})
    meta = {
        "totalAngle": float(np.degrees(arc)),
        "startAngle": float(np.degrees(angles.min())),
        "noise": 1,
        "randomAngle": False,
        "normalize": False,
        WORLD_AFFINE_META: imported.world_affine.tolist(),
        IMPORT_META: {
            "projections": _files_meta(stack.files),
            "geometry": str(geometry_xml),
            "conversion": conversion,
            "frame": FRAME_DESCRIPTION,
            "detector_rtk": {"size": [stack.grid.n_u, stack.grid.n_v], "spacing_mm": [stack.grid.spacing_u, stack.grid.spacing_v],
                             "origin_mm": [stack.grid.origin_u, stack.grid.origin_v]},
            "rtk": {"sid_mm": imported.dso, "sdd_mm": 0.0 if imported.mode == "parallel" else imported.dsd,
                    "projection_offset_mm": [float(rtk_geom.proj_offset_x[0]), float(rtk_geom.proj_offset_y[0])],
                    "source_offset_y_mm": imported.axis_shift},
            "grid": {"fov_radius_mm": grid["fov_radius_mm"], "fov_height_mm": grid["fov_height_mm"], "full_scan": grid["full_scan"],
                     "chosen": "given" if (volume_size or voxel_mm) else "covers the field of view"},
            "notes": notes,
        },
    }
    empty = Views(np.zeros(0), np.zeros((0,) + p.shape[1:], np.float32))
    return Scene(name=name or geometry_xml.stem, geometry=geometry, train=Views(angles, p), val=empty, image=None, meta=meta,
                 source=f"imported from {geometry_xml}")
