"""NAF / TIGRE scene pickles (SPEC §1): safe loading, validation, atomic saving.

A scene pickle is a plain dict (see SPEC §1 for the keys). Unpickling can run
arbitrary code, so :func:`load_naf` uses a restricted unpickler that resolves
only the handful of numpy names needed to rebuild arrays, dtypes and scalars,
and refuses every other global *before* anything is called.

Units: the file holds lengths in mm and projections as line integrals with
lengths in metres; :class:`~kneas_method.geometry.Geometry` converts to model
units. ``scene.image`` stays in data units.

Scenes without ground truth (measured scans, ``kneas-data import``) are valid:
``image`` may be absent and ``val`` may hold 0 views (or be absent); ``train``
needs at least one view. Noisy line integrals may dip below 0 (noise in air, as
TIGRE's noise model and real detectors give): they are kept as they are;
only values that are clearly not line integrals are refused
(:func:`check_line_integrals`).
"""

from __future__ import annotations

import io
import math
import pickle
from pathlib import Path
from typing import Any

import numpy as np

from ..atomic import atomic_write
from ..errors import SceneError
from ..geometry import Geometry
from .itk_io import IMAGE_SUFFIXES
from .scene import Scene, Views

# Geometry keys (mm) that Geometry.from_mm takes.
GEOMETRY_KEYS = ("mode", "DSD", "DSO", "nDetector", "dDetector", "nVoxel", "dVoxel", "offOrigin", "offDetector")
REQUIRED_KEYS = ("mode", "DSD", "DSO", "nDetector", "dDetector", "nVoxel", "dVoxel", "train")
# Keys handled explicitly (everything else goes to scene.meta).
_STRUCTURAL_KEYS = set(GEOMETRY_KEYS) | {"train", "val", "image", "labels", "sVoxel", "sDetector"}
# scene.meta key holding the file's exact geometry values, so save(load(f)) writes them back bit for bit.
GEOMETRY_MM_META = "geometry_mm"
# Default values of the "how it was generated" keys, written when a scene lacks them.
DEFAULT_META = {
    "accuracy": 0.5,
    "filter": None,
    "totalAngle": 180.0,
    "startAngle": 0.0,
    "convert": False,
    "rescale_slope": 1.0,
    "rescale_intercept": 0.0,
    "normalize": True,
    "noise": 0,
    "randomAngle": True,
}


# --------------------------------------------------------------------------- safe unpickling
def _allowed_globals() -> dict[tuple[str, str], Any]:
    """The only globals a scene pickle may name: what numpy needs for arrays, dtypes and scalars."""
    import codecs

    try:  # numpy >= 2
        from numpy._core import multiarray as _ma
        from numpy._core import numeric as _num
    except ImportError:  # pragma: no cover - numpy 1.x
        from numpy.core import multiarray as _ma
        from numpy.core import numeric as _num

    def _encode(obj, encoding="utf-8", errors="strict"):
        # Protocol 0-2 pickles of bytes use _codecs.encode(text, 'latin1'); allow only that.
        if not isinstance(obj, str) or encoding not in ("latin1", "latin-1", "iso-8859-1"):
            raise SceneError("_codecs.encode may only re-encode latin-1 text")
        return codecs.encode(obj, encoding, errors)

    table: dict[tuple[str, str], Any] = {("numpy", "ndarray"): np.ndarray, ("numpy", "dtype"): np.dtype, ("_codecs", "encode"): _encode}
    for mod in ("numpy.core.multiarray", "numpy._core.multiarray"):
        table[(mod, "_reconstruct")] = _ma._reconstruct
        table[(mod, "scalar")] = _ma.scalar
    if hasattr(_num, "_frombuffer"):  # protocol 5, in-band buffers
        for mod in ("numpy.core.numeric", "numpy._core.numeric"):
            table[(mod, "_frombuffer")] = _num._frombuffer
    try:
        import numpy.dtypes as _dtypes

        for name in dir(_dtypes):
            obj = getattr(_dtypes, name)
            if name.endswith("DType") and isinstance(obj, type) and issubclass(obj, np.dtype):
                table[("numpy.dtypes", name)] = obj
    except ImportError:  # pragma: no cover - numpy < 1.25
        pass
    return table


class _SafeUnpickler(pickle.Unpickler):
    """Unpickler that resolves only plain-data numpy globals; anything else raises SceneError."""

    def __init__(self, file, label: str):
        super().__init__(file)
        self._label = label
        self._table = _allowed_globals()

    def find_class(self, module: str, name: str):  # noqa: D401 - pickle API
        obj = self._table.get((module, name))
        if obj is None:
            raise SceneError(
                f"{self._label} is not a plain-data scene pickle: it asks for {module}.{name}, "
                "which kneas refuses to load because unpickling it could run code"
            )
        return obj

    def persistent_load(self, pid):
        raise SceneError(f"{self._label} is not a plain-data scene pickle: it uses persistent ids, which kneas refuses to load")


# The first bytes of files that are sometimes given where a scene pickle belongs (none is a valid pickle start).
FILE_SIGNATURES = ((b"\x89PNG", "PNG image"), (b"\xff\xd8\xff", "JPEG image"), (b"II*\x00", "TIFF image"), (b"MM\x00*", "TIFF image"),
                   (b"\x1f\x8b", "gzip (e.g. .nii.gz)"), (b"PK\x03\x04", "zip (e.g. .npz)"), (b"\x93NUMPY", "NumPy .npy"),
                   (b"\x89HDF", "HDF5"), (b"%PDF", "PDF"))


def safe_load_pickle(path) -> Any:
    """Unpickle ``path`` allowing only plain data (dicts, lists, numbers, strings, numpy arrays/dtypes/scalars)."""
    path = Path(path)
    label = path.name
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise SceneError(f"{path}: no such file; check the path") from None
    except IsADirectoryError:
        raise SceneError(f"{path} is a directory, not a scene pickle; give the .pickle file inside it") from None
    except OSError as exc:
        raise SceneError(f"{path}: cannot read it ({exc.strerror or exc}); check the file's permissions") from None
    try:
        return _SafeUnpickler(io.BytesIO(data), label).load()
    except Exception as exc:  # UnpicklingError, EOFError, ValueError, a refused global, ...
        kind = next((k for magic, k in FILE_SIGNATURES if data.startswith(magic)), None)
        if kind is not None:  # another kind of file renamed or mistaken for a scene
            raise SceneError(f"{label} is a {kind} file, not a scene pickle; give a NAF scene .pickle, or make one from a scan: "
                             "kneas-data import PROJECTIONS --geometry geometry.xml -o scan.pickle") from None
        if isinstance(exc, SceneError):
            raise
        msg = " ".join(str(exc).split()) or type(exc).__name__
        if path.name.lower().endswith(IMAGE_SUFFIXES + (".xml", ".raw")):
            raise SceneError(f"{label} is not a scene pickle but an image or geometry file; make a scene from a scan first: "
                             f"kneas-data import PROJECTIONS --geometry geometry.xml -o scan.pickle") from None
        raise SceneError(f"{label} is not a readable scene pickle ({msg}); re-create it or re-download it") from None


# --------------------------------------------------------------------------- validation helpers
def _fail(label: str, msg: str) -> SceneError:
    return SceneError(f"{label}: {msg}")


def _show(value: Any, limit: int = 80) -> str:
    """``repr(value)`` on one line, cut to ``limit`` characters (arrays repr over several lines)."""
    try:
        text = " ".join(repr(value).split())
    except Exception:  # a hostile or broken __repr__
        text = f"<{type(value).__name__}>"
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _positive_vector(d: dict, key: str, n: int, label: str, integer: bool) -> np.ndarray:
    try:
        arr = np.asarray(d[key], dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise _fail(label, f"{key} is {_show(d[key])}; it must be {n} {'integers' if integer else 'numbers'}") from None
    if arr.size != n:
        raise _fail(label, f"{key} has {arr.size} entries; it must have {n}")
    if not np.all(np.isfinite(arr)) or np.any(arr <= 0):
        raise _fail(label, f"{key} is {tuple(arr.tolist())}; every entry must be a finite positive value")
    if integer and np.any(arr != np.round(arr)):
        raise _fail(label, f"{key} is {tuple(arr.tolist())}; every entry must be a whole number")
    return arr


def _finite_vector(d: dict, key: str, n: int, label: str) -> np.ndarray:
    if key not in d or d[key] is None:
        return np.zeros(n)
    try:
        arr = np.asarray(d[key], dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise _fail(label, f"{key} is {_show(d[key])}; it must be {n} numbers (mm)") from None
    if arr.size != n or not np.all(np.isfinite(arr)):
        raise _fail(label, f"{key} is {_show(d[key])}; it must be {n} finite numbers (mm)")
    return arr


def _positive_scalar(d: dict, key: str, label: str) -> float:
    try:
        arr = np.asarray(d[key], dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise _fail(label, f"{key} is {_show(d[key])}; it must be a positive number (mm)") from None
    if arr.size != 1 or not math.isfinite(float(arr[0])) or float(arr[0]) <= 0:
        raise _fail(label, f"{key} is {_show(d[key])}; it must be one finite positive number (mm)")
    return float(arr[0])


def _numeric_array(value, key: str, label: str) -> np.ndarray:
    arr = np.asarray(value)
    if arr.dtype == object or not (np.issubdtype(arr.dtype, np.number) or arr.dtype == np.bool_):
        raise _fail(label, f"{key} has dtype {arr.dtype}; it must be a numeric array")
    return arr


# Line integrals of noisy data dip a little below 0 in air; these limits catch what is clearly not line integrals.
NEGATIVE_MEDIAN_LIMIT = -0.1  # median below this: log-intensities (sign flipped) or a wrong I0
NEGATIVE_PERCENTILE_LIMIT = -1.0  # 1st percentile below this: over 1 % of pixels brighter than e x I0


def _strided_sample(arr: np.ndarray, n: int = 1_000_000) -> np.ndarray:
    flat = np.asarray(arr).reshape(-1)
    return flat if flat.size <= n else flat[:: int(math.ceil(flat.size / n))]


def check_line_integrals(proj: np.ndarray, label: str, key: str) -> None:
    """Refuse projection values that are clearly not line integrals ``∫ mu dl`` (one-line SceneError).

    Small negative values (noise in air, as TIGRE's and real detectors' noise
    gives) are accepted and kept. Refused: NaN/inf, all zero, a median below
    :data:`NEGATIVE_MEDIAN_LIMIT` (log-intensities or intensities with the sign
    flipped, a wrong I0) or a 1st percentile below :data:`NEGATIVE_PERCENTILE_LIMIT`.
    """
    proj = np.asarray(proj)
    if proj.size == 0:
        return
    if not np.all(np.isfinite(proj)):
        bad = int(np.count_nonzero(~np.isfinite(proj)))
        raise _fail(label, f"{key} contains {bad} NaN/inf values; fix or drop those views")
    if not np.any(proj):
        raise _fail(label, f"{key} are all zero: there is nothing to reconstruct; check that the right data were written")
    sample = _strided_sample(proj).astype(np.float64)
    median = float(np.median(sample))
    if median < NEGATIVE_MEDIAN_LIMIT:
        raise _fail(label, f"{key} have median {median:.4g}, far below 0: they are not line integrals -ln(I/I0) "
                           "(log-intensities ln(I/I0) have the opposite sign; a wrong I0 shifts them); negate or re-convert them "
                           "(kneas-data import converts raw counts)")
    low = float(np.percentile(sample, 1))
    if low < NEGATIVE_PERCENTILE_LIMIT:
        raise _fail(label, f"{key} are wildly negative (1st percentile {low:.4g}: over 1 % of pixels brighter than e x I0); "
                           "check the flat field / I0 used to make them")


def _views(d: dict, key: str, n_u: int, n_v: int, label: str, allow_empty: bool = False) -> Views:
    if key not in d and allow_empty:
        return Views(angles=np.zeros(0), projections=np.zeros((0, n_v, n_u), np.float32))
    part = d[key]
    if not isinstance(part, dict):
        raise _fail(label, f"{key} is a {type(part).__name__}; it must be a dict with 'angles' and 'projections'")
    for sub in ("angles", "projections"):
        if sub not in part:
            raise _fail(label, f"{key}.{sub} is missing; a NAF scene needs {key} = {{'angles': [N], 'projections': [N, nV, nU]}}")
    angles = _numeric_array(part["angles"], f"{key}.angles", label).astype(np.float64).reshape(-1)
    proj = _numeric_array(part["projections"], f"{key}.projections", label)
    if proj.ndim == 2 and len(angles) == 1:
        proj = proj[None]
    n = len(angles)
    if n == 0 and proj.size == 0:
        proj = proj.reshape(0, n_v, n_u)
    if proj.ndim != 3 or proj.shape[1:] != (n_v, n_u):
        raise _fail(
            label,
            f"{key}.projections has shape {tuple(proj.shape)} but nDetector is ({n_u}, {n_v}); "
            f"expected ({proj.shape[0] if proj.ndim >= 1 else n}, {n_v}, {n_u})",
        )
    if proj.shape[0] != n:
        raise _fail(label, f"{key} has {n} angles but {proj.shape[0]} projections; they must match one to one")
    if n == 0 and not allow_empty:
        raise _fail(label, f"{key} has no views; it needs at least one angle and projection")
    if not np.all(np.isfinite(angles)):
        raise _fail(label, f"{key}.angles contains NaN or inf; every angle must be a finite number of radians")
    proj = proj.astype(np.float32, copy=False)
    check_line_integrals(proj, label, f"{key}.projections")
    return Views(angles=angles, projections=np.ascontiguousarray(proj))


def _attach_phantom(scene: Scene) -> None:
    """Give a built-in scene its material labels, names and exact membership function."""
    name = scene.meta.get("phantom")
    if not isinstance(name, str):
        return
    try:
        from .phantoms import PHANTOM_NAMES, get_phantom
    except ImportError:  # phantoms not available in this build
        return
    if name not in PHANTOM_NAMES:
        return
    phantom = get_phantom(name)
    geometry = scene.geometry
    if scene.labels is None:
        scene.labels = np.asarray(phantom.labels(geometry), dtype=np.uint8)
    scene.materials = tuple(phantom.materials)
    scene.membership = lambda pts_model: phantom.label_at(geometry.model_to_mm(np.asarray(pts_model, dtype=np.float64)))


# keys of a scene whose labels are thresholds of its own volume (a real CT's tissues): the
# attenuations (data units, ascending) where labels 1..M start, and the names of those labels
LABEL_THRESHOLDS_KEY, MATERIALS_KEY = "label_thresholds", "materials"


def threshold_labels(values, thresholds) -> np.ndarray:
    """Labels (uint8, same shape as ``values``): how many of ``thresholds`` (ascending) each value reaches."""
    return np.digitize(values, np.asarray(thresholds, dtype=np.float64)).astype(np.uint8)


def threshold_membership(image: np.ndarray, thresholds, geometry):
    """``f(points_model [P, 3]) -> labels [P]``: how many of ``thresholds`` (ascending, data units) the
    trilinear interpolation of ``image`` [nx, ny, nz] exceeds at each point; at the voxel centres it
    is the labels the thresholds give the volume itself."""
    from scipy.ndimage import map_coordinates

    image = np.asarray(image, dtype=np.float32)
    levels = np.asarray(thresholds, dtype=np.float64)
    step = np.asarray(geometry.d_voxel, dtype=np.float64)
    first = np.array([-n * d / 2 + d / 2 + o for n, d, o in zip(geometry.n_voxel, geometry.d_voxel, geometry.off_origin)])  # as voxel_axes

    def membership(points):
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        coords = ((p - first) / step).T
        # a float32 voxel centre lands a hair off its index; snapping it keeps the volume's own labels
        # where a voxel sits exactly on a threshold (integer HU against integer thresholds)
        nearest = np.round(coords)
        coords = np.where(np.abs(coords - nearest) < 1e-4, nearest, coords)
        return threshold_labels(map_coordinates(image, coords, order=1, mode="nearest"), levels)

    return membership


def attach_threshold_labels(scene: Scene, label: str) -> None:
    """A scene (not built in) whose labels are thresholds of its volume: its material names and a
    membership function (:func:`threshold_membership`), so that surfaces can be scored on it."""
    thresholds, names = scene.meta.get(LABEL_THRESHOLDS_KEY), scene.meta.get(MATERIALS_KEY)
    if thresholds is None or scene.labels is None or scene.image is None or scene.membership is not None:
        return
    try:
        levels = np.asarray(thresholds, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise _fail(label, f"{LABEL_THRESHOLDS_KEY} must be a list of numbers (the attenuations where labels 1..M start)") from None
    if levels.size < 1 or not np.all(np.isfinite(levels)) or np.any(np.diff(levels) <= 0):
        raise _fail(label, f"{LABEL_THRESHOLDS_KEY} must be finite and ascending, got {levels.tolist()}")
    if int(scene.labels.max(initial=0)) > levels.size:
        raise _fail(label, f"labels go up to {int(scene.labels.max())} but {LABEL_THRESHOLDS_KEY} gives {levels.size} thresholds")
    if names is not None:
        if not (isinstance(names, (list, tuple)) and len(names) == levels.size and all(isinstance(n, str) for n in names)):
            raise _fail(label, f"{MATERIALS_KEY} must be {levels.size} names, one per threshold of {LABEL_THRESHOLDS_KEY}")
        scene.materials = tuple(names)
    else:
        scene.materials = tuple(f"label {k}" for k in range(1, levels.size + 1))
    scene.membership = threshold_membership(scene.image, levels, scene.geometry)


# --------------------------------------------------------------------------- public API
def scene_from_dict(d: Any, label: str, *, name: str = "scene", source: str = "") -> Scene:
    """Validate a NAF scene dict and build a :class:`Scene` (raises one-line SceneError)."""
    if not isinstance(d, dict):
        raise _fail(label, f"the pickle holds a {type(d).__name__}, not a dict; a NAF scene is a dict with keys DSD, DSO, nDetector, ..., train, val")
    for key in REQUIRED_KEYS:
        if key not in d:
            raise _fail(label, f"key '{key}' is missing; a NAF scene needs {', '.join(REQUIRED_KEYS)}")
    mode = d["mode"]
    if not isinstance(mode, str) or mode not in ("cone", "parallel"):
        raise _fail(label, f"mode is {_show(mode)}; it must be 'cone' or 'parallel'")
    dsd = _positive_scalar(d, "DSD", label)
    dso = _positive_scalar(d, "DSO", label)
    n_det = _positive_vector(d, "nDetector", 2, label, integer=True).astype(np.int64)
    d_det = _positive_vector(d, "dDetector", 2, label, integer=False)
    n_vox = _positive_vector(d, "nVoxel", 3, label, integer=True).astype(np.int64)
    d_vox = _positive_vector(d, "dVoxel", 3, label, integer=False)
    off_origin = _finite_vector(d, "offOrigin", 3, label)
    off_det = _finite_vector(d, "offDetector", 2, label)
    if mode == "cone" and dsd <= dso:
        raise _fail(label, f"DSD ({dsd:g} mm) must be larger than DSO ({dso:g} mm): the detector sits behind the rotation axis")
    geometry_mm = {
        "mode": mode, "DSD": d["DSD"], "DSO": d["DSO"], "nDetector": d["nDetector"], "dDetector": d["dDetector"],
        "nVoxel": d["nVoxel"], "dVoxel": d["dVoxel"],
        "offOrigin": d.get("offOrigin", off_origin), "offDetector": d.get("offDetector", off_det),
    }
    geometry = Geometry.from_mm(
        mode=mode, DSD=dsd, DSO=dso, nDetector=n_det, dDetector=d_det, nVoxel=n_vox, dVoxel=d_vox,
        offOrigin=off_origin, offDetector=off_det,
    )
    n_u, n_v = int(n_det[0]), int(n_det[1])
    train = _views(d, "train", n_u, n_v, label)
    val = _views(d, "val", n_u, n_v, label, allow_empty=True)

    image = d.get("image")
    if image is not None:
        image = _numeric_array(image, "image", label)
        if tuple(image.shape) != tuple(int(v) for v in n_vox):
            raise _fail(label, f"image has shape {tuple(image.shape)} but nVoxel is {tuple(int(v) for v in n_vox)}; they must be equal")
        image = np.ascontiguousarray(image.astype(np.float32, copy=False))
        if not np.all(np.isfinite(image)):
            raise _fail(label, "image contains NaN or inf; the ground-truth volume must be finite")
    labels = d.get("labels")
    if labels is not None:
        labels = _numeric_array(labels, "labels", label)
        if tuple(labels.shape) != tuple(int(v) for v in n_vox):
            raise _fail(label, f"labels has shape {tuple(labels.shape)} but nVoxel is {tuple(int(v) for v in n_vox)}; they must be equal")
        if labels.min(initial=0) < 0 or labels.max(initial=0) > 255:
            raise _fail(label, "labels must be integers in 0..255 (0 = air)")
        labels = np.ascontiguousarray(labels.astype(np.uint8))

    meta = {k: v for k, v in d.items() if k not in _STRUCTURAL_KEYS}
    meta[GEOMETRY_MM_META] = geometry_mm
    scene = Scene(name=name, geometry=geometry, train=train, val=val, image=image, labels=labels, meta=meta, source=source)
    _attach_phantom(scene)
    attach_threshold_labels(scene, label)
    return scene


def load_naf(path, *, name: str | None = None) -> Scene:
    """Load a NAF/TIGRE scene pickle safely.

    Args:
        path: the ``.pickle`` file.
        name: scene name (default: the file's stem).

    Returns:
        A validated :class:`Scene`; ``scene.meta`` holds the non-geometry keys.

    Raises:
        SceneError: unsafe pickle (before anything in it runs), unreadable file, or
            a malformed scene; the one-line message names the key and the fix.
    """
    path = Path(path)
    data = safe_load_pickle(path)
    return scene_from_dict(data, path.name, name=name or path.stem, source=f"file {path}")


def scene_geometry_mm(scene: Scene) -> dict:
    """The scene's geometry as NAF keys in mm: the file's exact values when they still
    describe ``scene.geometry`` (a loaded scene), else :meth:`Geometry.to_mm`."""
    geometry_mm = scene.meta.get(GEOMETRY_MM_META)
    try:
        exact = isinstance(geometry_mm, dict) and Geometry.from_mm(**geometry_mm) == scene.geometry
    except Exception:  # malformed or stale meta: fall back to the geometry itself
        exact = False
    if exact:
        return dict(geometry_mm)
    full = scene.geometry.to_mm()
    return {k: full[k] for k in GEOMETRY_KEYS}


def scene_to_dict(scene: Scene) -> dict:
    """The NAF dict for ``scene`` (inverse of :func:`scene_from_dict`)."""
    geo = scene_geometry_mm(scene)
    out: dict[str, Any] = dict(DEFAULT_META)
    out.update({k: v for k, v in scene.meta.items() if k != GEOMETRY_MM_META})
    out.update(geo)
    out["numTrain"] = len(scene.train)
    out["numVal"] = len(scene.val)
    out["train"] = {"angles": np.asarray(scene.train.angles), "projections": np.asarray(scene.train.projections, dtype=np.float32)}
    out["val"] = {"angles": np.asarray(scene.val.angles), "projections": np.asarray(scene.val.projections, dtype=np.float32)}
    if scene.image is not None:
        out["image"] = np.asarray(scene.image, dtype=np.float32)
    if scene.labels is not None:
        out["labels"] = np.asarray(scene.labels, dtype=np.uint8)
    return out


def atomic_write_bytes(path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (temp file in the same folder + ``os.replace``)."""
    try:
        atomic_write(path, lambda handle: handle.write(data))
    except OSError as exc:
        raise SceneError(f"cannot write {path} ({exc.strerror or exc}); choose a writable output path") from None


def save_naf(scene: Scene, path) -> Path:
    """Save ``scene`` as a NAF pickle (protocol 4), atomically. Returns the path."""
    path = Path(path)
    atomic_write_bytes(path, pickle.dumps(scene_to_dict(scene), protocol=4))
    return path
