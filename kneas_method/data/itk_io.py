"""Image files through ITK (optional: ``pip install 'kneas[scanner]'``).

ITK is imported only inside these functions; without it they raise a one-line
:class:`KneasError` naming the extra to install. Arrays use ITK's numpy order:
an image of size ``(n0, n1, n2)`` (index ``i0`` fastest) is the array
``[n2, n1, n0]``; physical point of index ``i`` = ``origin + direction @ (spacing * i)`` (mm, LPS).
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import KneasError, SceneError, missing_optional

# the image files ITK reads (projections, volumes), by the ends of their names
IMAGE_SUFFIXES = (".mha", ".mhd", ".nrrd", ".nhdr", ".tif", ".tiff", ".png", ".nii", ".nii.gz", ".dcm", ".his", ".hnd",
                  ".xim", ".edf", ".vtk", ".hdr", ".bmp", ".jpg", ".jpeg")

ITK_EXTRA = "scanner"


def require_itk(purpose: str):
    """``import itk`` or a one-line error: ``install it with: pip install 'kneas[scanner]'``."""
    try:
        import itk  # noqa: F401
    except ImportError:
        raise missing_optional("itk-io", ITK_EXTRA, purpose) from None
    return itk


@dataclass
class ImageData:
    """An image read through ITK.

    Attributes:
        array: numpy array in ITK order (``[n2, n1, n0]`` for 3-D, ``[n1, n0]`` for 2-D).
        spacing, origin: per ITK axis (mm).
        direction: [D, D] direction matrix.
        path: the file (or folder) it came from.
    """

    array: np.ndarray
    spacing: np.ndarray
    origin: np.ndarray
    direction: np.ndarray
    path: str


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    # ITK exceptions carry a long description; keep its most telling part.
    if "Description:" in text:
        text = text.split("Description:", 1)[1].strip()
    return text[:200] or type(exc).__name__


@contextlib.contextmanager
def native_stderr(lines: list):
    """Collect what C++ code writes to file descriptor 2 inside the block into ``lines`` (ITK's
    readers print their reason there, e.g. MetaImage's "data not read completely", and raise an
    exception that does not say it). Where fd 2 cannot be redirected, nothing is collected."""
    try:
        saved = os.dup(2)
    except OSError:
        yield
        return
    with tempfile.TemporaryFile(mode="w+b") as tmp:
        sys.stderr.flush()
        os.dup2(tmp.fileno(), 2)
        try:
            yield
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            lines.extend(line for line in tmp.read().decode("utf-8", "replace").splitlines() if line.strip())


def _reason(native: list, exc: BaseException) -> str:
    """Why ITK could not read a file: the reader's own words where it printed them, else the exception's."""
    if not native:
        return _one_line(exc)
    text = " ".join(" ".join(native).split())
    if "not read completely" in text:
        return f"{text[:160]}: the file is shorter than its header says (truncated? copy it again)"
    return text[:200]


def read_image(path, *, purpose: str = "reading projection images") -> ImageData:
    """Read one image file (any format ITK reads) or a DICOM series folder.

    Raises:
        SceneError: missing or unreadable file (one line).
        KneasError: ITK not installed.
    """
    itk = require_itk(purpose)
    path = Path(path)
    if not path.exists():
        raise SceneError(f"{path}: no such file; check the path")
    native: list = []
    try:
        with native_stderr(native):
            image = itk.imread(str(path))
        array = np.asarray(itk.array_from_image(image))
        spacing = np.asarray(image.GetSpacing(), dtype=np.float64)
        origin = np.asarray(image.GetOrigin(), dtype=np.float64)
        direction = np.asarray(itk.array_from_matrix(image.GetDirection()), dtype=np.float64)
    except Exception as exc:  # ITK raises RuntimeError / its own types
        raise SceneError(f"{path.name}: ITK cannot read it ({_reason(native, exc)}); check the file and its format") from None
    if native:  # a reader's warnings on a file it did read: passed on, not lost
        print("\n".join(native), file=sys.stderr)
    if array.ndim == 3 and image.GetNumberOfComponentsPerPixel() > 1 and array.shape[-1] == image.GetNumberOfComponentsPerPixel():
        raise SceneError(f"{path.name} holds {array.shape[-1]}-component (colour/vector) pixels; projections must be grey values")
    return ImageData(array=array, spacing=spacing, origin=origin, direction=direction, path=str(path))


def write_image(array: np.ndarray, path, *, spacing, origin, direction=None, purpose: str = "writing .mha images") -> Path:
    """Write ``array`` (ITK order) with the given geometry (mm); compressed when the format allows."""
    itk = require_itk(purpose)
    path = Path(path)
    arr = np.ascontiguousarray(array)
    dim = arr.ndim
    try:
        image = itk.image_from_array(arr)
        image.SetSpacing([float(v) for v in spacing][:dim])
        image.SetOrigin([float(v) for v in origin][:dim])
        d = np.eye(dim) if direction is None else np.asarray(direction, dtype=np.float64)[:dim, :dim]
        image.SetDirection(itk.matrix_from_array(np.ascontiguousarray(d)))
        path.parent.mkdir(parents=True, exist_ok=True)
        itk.imwrite(image, str(path), compression=True)
    except OSError as exc:
        raise KneasError(f"cannot write {path} ({exc.strerror or exc}); choose a writable output path") from None
    except Exception as exc:
        raise KneasError(f"ITK cannot write {path} ({_one_line(exc)}); choose another path or format") from None
    return path
