"""Read user CT volumes (.npy, NIfTI, MATLAB .mat, a DICOM series folder) and convert them to attenuation.

A DICOM series (a folder of slices) is read through ITK (``pip install
'kneas[scanner]'``), which applies each slice's rescale slope/intercept, so its
values are HU: pass ``--convert`` with the default slope 1 and intercept 0. The
array is taken in the image's index order (x = columns, y = rows, z = slices)
with ITK's voxel spacing; without ITK, pydicom is used when it is installed.

HU conversion follows NAF's data generator: ``HU = raw·slope + intercept``, then
``mu = mu_water·(1 + HU/1000)`` with ``mu_water = 0.2 /cm = 20 /m`` (negative values,
below air, are clipped to 0). With ``normalize`` the volume is divided by its maximum
so it spans [0, 1] like the public NAF scenes; otherwise it stays in 1/m (when
converted) or in the file's own units (taken as 1/m).
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

from ..errors import KneasError, SceneError, missing_optional

MU_WATER_PER_M = 20.0  # 0.2 /cm
SUPPORTED = (".npy", ".nii", ".nii.gz", ".mat", "a DICOM series folder")


def _suffix(path: Path) -> str:
    name = path.name.lower()
    if name.endswith(".nii.gz"):
        return ".nii.gz"
    return path.suffix.lower()


def hu_to_mu(raw: np.ndarray, rescale_slope: float = 1.0, rescale_intercept: float = 0.0) -> np.ndarray:
    """Raw scanner values -> attenuation [1/m]: ``mu_water·(1 + (raw·slope + intercept)/1000)``, clipped at 0."""
    hu = np.asarray(raw, dtype=np.float64) * float(rescale_slope) + float(rescale_intercept)
    return np.clip(MU_WATER_PER_M * (1.0 + hu / 1000.0), 0.0, None)


def _read_npy(path: Path):
    try:
        arr = np.load(path, allow_pickle=False)
    except ValueError as exc:
        if "pickle" in str(exc).lower():
            raise SceneError(f"{path.name} holds Python objects, not a numeric array; kneas loads only plain .npy arrays (save with allow_pickle=False)") from None
        raise SceneError(f"{path.name} is not a readable .npy file ({exc}); re-save it with numpy.save") from None
    if not isinstance(arr, np.ndarray):  # a zip (.npz) archive renamed to .npy
        raise SceneError(f"{path.name} is an .npz archive; save the volume alone with numpy.save")
    return arr, None


def _read_nifti(path: Path):
    try:
        import nibabel as nib
    except ImportError:
        raise missing_optional("nibabel", "nifti", "reading NIfTI volumes") from None
    try:
        img = nib.load(str(path))
        arr = np.asarray(img.dataobj, dtype=np.float32)
        zooms = tuple(float(z) for z in img.header.get_zooms()[:3])
    except Exception as exc:
        msg = " ".join(str(exc).split())
        raise SceneError(f"{path.name} is not a readable NIfTI file ({msg}); check the file") from None
    voxel = zooms if len(zooms) == 3 and all(np.isfinite(zooms)) and all(z > 0 for z in zooms) else None
    # NIfTI units: mm is the convention (xyzt_units); convert metres/microns if declared.
    try:
        space_unit = img.header.get_xyzt_units()[0]
        factor = {"meter": 1000.0, "micron": 1e-3}.get(space_unit, 1.0)
        if voxel is not None:
            voxel = tuple(v * factor for v in voxel)
    except Exception:  # pragma: no cover - header without units
        pass
    return arr, voxel


def _read_dicom_series(path: Path):
    """A DICOM series folder -> (array [nx, ny, nz] in HU, voxel mm)."""
    try:
        import itk  # noqa: F401
    except ImportError:
        return _read_dicom_pydicom(path)
    from .itk_io import read_image

    img = read_image(path, purpose="reading a DICOM series")
    arr = np.asarray(img.array)
    if arr.ndim == 2:
        arr = arr[None]
    if arr.ndim != 3:
        raise SceneError(f"{path.name}: the DICOM series is {arr.ndim}-D; a CT volume must be 3-D")
    voxel = tuple(float(v) for v in img.spacing[:3])
    return np.transpose(arr, (2, 1, 0)), voxel


def _read_dicom_pydicom(path: Path):
    try:
        import pydicom
    except ImportError:
        raise KneasError("reading a DICOM series needs ITK (or pydicom), which is not installed; install it with: "
                         "pip install 'kneas[scanner]'") from None
    slices = []
    for f in sorted(p for p in path.iterdir() if p.is_file()):
        try:
            ds = pydicom.dcmread(str(f))
            slices.append((float(ds.ImagePositionPatient[2]), ds))
        except Exception:
            continue
    if not slices:
        raise SceneError(f"{path} holds no readable DICOM slices; give a DICOM series folder")
    slices.sort(key=lambda t: t[0])
    arr = np.stack([ds.pixel_array.astype(np.float64) * float(getattr(ds, "RescaleSlope", 1.0))
                    + float(getattr(ds, "RescaleIntercept", 0.0)) for _, ds in slices], 0)  # [z, y, x]
    first = slices[0][1]
    dy, dx = (float(v) for v in first.PixelSpacing)
    dz = abs(slices[1][0] - slices[0][0]) if len(slices) > 1 else float(getattr(first, "SliceThickness", 1.0))
    return np.transpose(arr, (2, 1, 0)), (dx, dy, dz)


def _read_mat(path: Path, key: Optional[str]):
    import scipy.io

    try:
        data = scipy.io.loadmat(str(path))
    except NotImplementedError:
        raise SceneError(f"{path.name} is a MATLAB v7.3 (HDF5) file, which scipy cannot read; re-save it in MATLAB with save(..., '-v7') or export a .npy") from None
    except Exception as exc:
        msg = " ".join(str(exc).split())
        raise SceneError(f"{path.name} is not a readable .mat file ({msg}); check the file") from None
    arrays = {k: v for k, v in data.items() if not k.startswith("__") and isinstance(v, np.ndarray)}
    if key is not None:
        if key not in arrays:
            raise SceneError(f"{path.name} has no variable '{key}'; it has: {', '.join(sorted(arrays)) or 'none'}; pass one of those with --key")
        return arrays[key], None
    if "img" in arrays:  # NAF's generator reads 'img'
        return arrays["img"], None
    three_d = [k for k, v in arrays.items() if v.ndim == 3 and v.dtype != object]
    if len(three_d) == 1:
        return arrays[three_d[0]], None
    raise SceneError(
        f"{path.name} has {len(three_d)} 3-D arrays ({', '.join(sorted(three_d)) or 'none'}) and no 'img'; "
        "name the volume with --key"
    )


def load_volume(
    path,
    *,
    convert: bool = False,
    rescale_slope: float = 1.0,
    rescale_intercept: float = 0.0,
    normalize: bool = True,
    key: Optional[str] = None,
) -> tuple[np.ndarray, Optional[tuple[float, float, float]]]:
    """Load a CT volume and turn it into attenuation.

    Args:
        path: ``.npy``, ``.nii``, ``.nii.gz`` or ``.mat`` file, or a DICOM series folder.
        convert: treat values as raw scanner values and convert via HU to attenuation [1/m].
        rescale_slope, rescale_intercept: ``HU = raw·slope + intercept`` (only with ``convert``).
        normalize: divide by the maximum so the volume spans [0, 1].
        key: variable name inside a ``.mat`` file (default ``img``, else its only 3-D array).

    Returns:
        ``(volume, voxel_mm)``: float32 [nx, ny, nz] and the voxel size in mm from the
        file header (NIfTI, DICOM) or None when the format carries none.
    """
    path = Path(path)
    if path.is_dir():
        suffix = "dicom"
    elif not path.is_file():
        raise SceneError(f"{path}: no such file; check the path to the volume")
    else:
        suffix = _suffix(path)
    if suffix == "dicom":
        arr, voxel = _read_dicom_series(path)
    elif suffix == ".npy":
        arr, voxel = _read_npy(path)
    elif suffix in (".nii", ".nii.gz"):
        arr, voxel = _read_nifti(path)
    elif suffix == ".mat":
        arr, voxel = _read_mat(path, key)
    else:
        raise SceneError(f"{path.name}: unsupported volume format '{suffix}'; use one of {', '.join(SUPPORTED)}")
    arr = np.asarray(arr)
    if arr.dtype == object or not (np.issubdtype(arr.dtype, np.number) or arr.dtype == np.bool_):
        raise SceneError(f"{path.name}: the volume has dtype {arr.dtype}; it must be numeric")
    if arr.ndim == 4 and arr.shape[-1] == 1:
        arr = arr[..., 0]
    if arr.ndim != 3:
        raise SceneError(f"{path.name}: the volume has shape {arr.shape}; it must be 3-D [nx, ny, nz]")
    if min(arr.shape) < 1:
        raise SceneError(f"{path.name}: the volume has shape {arr.shape}; it is empty")
    vol = arr.astype(np.float64)
    if not np.all(np.isfinite(vol)):
        raise SceneError(f"{path.name}: the volume contains NaN or inf; clean it first")
    if convert:
        vol = hu_to_mu(vol, rescale_slope, rescale_intercept)
    elif np.any(vol < 0):
        raise SceneError(
            f"{path.name}: the volume has negative values (min {vol.min():.4g}), so it is not attenuation; "
            "if it is in HU or raw scanner units pass --convert (with --rescale-slope/--rescale-intercept)"
        )
    if normalize:
        peak = float(vol.max())
        if peak <= 0:
            raise SceneError(f"{path.name}: the volume is all zero after conversion; nothing to normalise (check --convert and the rescale values)")
        vol = vol / peak
    return np.ascontiguousarray(vol.astype(np.float32)), voxel


def volume_meta(*, convert: bool, rescale_slope: float, rescale_intercept: float, normalize: bool) -> dict:
    """The NAF meta keys recording a volume's conversion."""
    return {"convert": bool(convert), "rescale_slope": float(rescale_slope), "rescale_intercept": float(rescale_intercept), "normalize": bool(normalize)}
