"""Reconstructed volumes of a run (``kneas-export volume``): ``.npy``, and NIfTI when nibabel is installed.

Files written (``out_dir``):

* ``attenuation.nii.gz`` / ``attenuation.npy``: float32 ``[nx, ny, nz]``, the
  attenuation in **data units** (1/m; NAF scenes: the normalised [0, 1] scale) at
  the scene's voxel centres (``model.query(...)["mu"]``, or an FDK run's volume).
* ``labels.nii.gz`` / ``labels.npy``: uint8 ``[nx, ny, nz]`` material labels:
  SDF methods ``1 + argmax_k w_k`` with 0 (air) where ``Σ_k w_k < 0.5`` (labels
  1..K = the model's materials in ascending attenuation); methods without an SDF
  only with ``thresholds`` (label = number of thresholds the attenuation exceeds).
* ``volume.json``: shape, voxel size and origin (mm), the affine, units, the
  axis convention.

Axis convention / affine
------------------------
Array index ``image[a, b, c]`` is the voxel centred at ``(x_a, y_b, z_c)`` of
:meth:`Geometry.voxel_centres` (SPEC §1), in mm. Its index -> kneas-mm affine
(:func:`volume_affine`) is::

    [[dx, 0,  0,  x_0],
     [0,  dy, 0,  y_0],
     [0,  0,  dz, z_0],
     [0,  0,  0,  1  ]]

with ``(dx, dy, dz)`` the voxel size in mm and ``(x_0, y_0, z_0)`` the first
voxel centre in mm (``offOrigin`` included). The NIfTI affine (sform and qform,
code 1 "scanner", units mm) maps the index to NIfTI's RAS+ world:

* **scenes imported from a scanner** (``kneas-data import``) carry
  ``meta["world_affine_lps"]``, the map from kneas's frame (mm) to the
  scanner's RTK/ITK world (LPS, mm); the NIfTI affine is
  ``diag(-1, -1, 1, 1) @ world_affine_lps @ volume_affine`` (LPS -> RAS), so the
  volume opens in a viewer exactly where RTK's reconstruction of the same data
  does (rotation axis = world y, as RTK);
* other scenes (simulated, NAF pickles) have no scanner world: kneas identifies
  its x, y, z (z = rotation axis) with R, A, S, with no flips, so 3D Slicer and
  ITK-SNAP place the volume, the meshes of ``kneas-export mesh`` (same mm frame)
  and the ground truth at the same positions; Slicer's R/A/S labels are then
  the scanner's x/y/z axes.

When ITK is installed (``pip install 'kneas[scanner]'``) ``attenuation.mha`` (and
``labels.mha``) are written too, for RTK users: the same world placement (LPS),
stored with an identity direction (the array's axes permuted/flipped to the
world axes, which is exact because the map is an axis permutation).
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch

from ..errors import missing_optional

NIFTI_UNITS = "mm"


def volume_affine(geometry) -> np.ndarray:
    """The ``[4, 4]`` voxel-index -> mm affine of ``geometry``'s voxel grid (module docs)."""
    mm = geometry.mm_per_unit
    first = [float(ax[0]) * mm for ax in geometry.voxel_axes(dtype=torch.float64)]
    aff = np.eye(4)
    for i in range(3):
        aff[i, i] = float(geometry.d_voxel[i]) * mm
        aff[i, 3] = first[i]
    return aff


RAS_FROM_LPS = np.diag([-1.0, -1.0, 1.0, 1.0])


def world_affine_lps(scene) -> np.ndarray:
    """kneas mm -> LPS mm [4, 4]: the scene's scanner frame map, else the identification kneas xyz = RAS."""
    from ..data.rtk_geometry import scanner_world_affine

    a = scanner_world_affine(scene)
    return RAS_FROM_LPS.copy() if a is None else a  # no scanner world: kneas xyz = RAS, so LPS = diag(-1, -1, 1) @ kneas


def nifti_affine(scene) -> np.ndarray:
    """The ``[4, 4]`` voxel-index -> RAS mm affine written to NIfTI (module docs)."""
    return RAS_FROM_LPS @ world_affine_lps(scene) @ volume_affine(scene.geometry)


def write_mha(array: np.ndarray, scene, path: Path) -> Path:
    """Write a kneas-order volume ``[nx, ny, nz]`` as ``.mha`` in LPS world (identity direction) through ITK."""
    from ..data.itk_io import write_image
    from ..data.rtk_geometry import itk_array_of_world, volume_to_world_array, world_grid_of

    grid = world_grid_of(scene.geometry, world_affine_lps(scene))
    return write_image(itk_array_of_world(volume_to_world_array(np.asarray(array), grid)), path,
                       spacing=grid["spacing"], origin=grid["origin"], purpose="writing .mha volumes")


def _importable(module: str) -> bool:
    """Whether an optional package (``itk``, ``nibabel``) can be imported."""
    try:
        __import__(module)
    except ImportError:
        return False
    return True


def reconstruct(run, *, chunk: int = 65536) -> dict[str, np.ndarray]:
    """``{"mu": [nx, ny, nz] data units, and for a model with materials "weights" [nx, ny, nz, K]
    and "mu_materials"}`` of a loaded run at its scene's voxel centres."""
    if run.model is None:
        return {"mu": np.asarray(run.volume, dtype=np.float32)}
    from ..evaluation.surfaces import query_grid

    return query_grid(run.model, run.scene.geometry, keys=("mu", "weights", "mu_materials"), chunk=chunk)


def label_volume(q: dict, thresholds: Optional[Sequence[float]] = None, air_threshold: float = 0.5) -> Optional[np.ndarray]:
    """Material labels (uint8) of :func:`reconstruct`'s grids: from the weights with partial-volume
    shells relabelled (the labels ``kneas-eval`` scores), or from attenuation thresholds (data
    units); None if neither."""
    from ..evaluation.surfaces import voxel_labels

    mu = q["mu"]
    if "weights" in q and "mu_materials" in q:
        return voxel_labels(q, air_threshold)[0]
    if thresholds:
        t = np.sort(np.asarray(thresholds, dtype=np.float64))
        return np.searchsorted(t, np.asarray(mu, dtype=np.float64), side="right").astype(np.uint8)
    return None


def write_nifti(array: np.ndarray, affine: np.ndarray, path: Path, *, description: str = "") -> Path:
    """Write ``array`` as NIfTI-1 with ``affine`` (sform and qform code 1, units mm)."""
    try:
        import nibabel as nib
    except ImportError:
        raise missing_optional("nibabel", "nifti", "writing NIfTI volumes") from None
    img = nib.Nifti1Image(np.asarray(array), affine)
    img.header.set_xyzt_units(xyz=NIFTI_UNITS)
    img.set_sform(affine, code=1)
    img.set_qform(affine, code=1)
    if description:
        img.header["descrip"] = description[:79].encode()
    nib.save(img, str(path))
    return Path(path)


def export_volume(run, out_dir, *, thresholds: Optional[Sequence[float]] = None, nifti: Optional[bool] = None,
                  chunk: int = 65536, air_threshold: float = 0.5, mha: Optional[bool] = None) -> dict:
    """Write the attenuation and label volumes (``.npy``; NIfTI / ``.mha`` when nibabel / ITK is there) and ``volume.json``.

    ``nifti``: True requires nibabel, False skips it, None (default) writes it when nibabel is
    installed and otherwise says in ``notes`` how to get it. ``mha``: the same with ITK.

    Returns the ``volume.json`` dict (paths, shape, voxel size, origin, affine, notes).
    """
    from ..engine.run_dir import write_json

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    geo = run.scene.geometry
    q = reconstruct(run, chunk=chunk)
    mu, weights = q["mu"], q.get("weights")
    labels = label_volume(q, thresholds, air_threshold)
    aff = nifti_affine(run.scene)
    lps = world_affine_lps(run.scene)
    imported = run.scene.meta.get("world_affine_lps") is not None
    info: dict = {
        "method": run.config.method,
        "scene": run.scene.name,
        "shape": list(mu.shape),
        "voxel_mm": [float(v) * geo.mm_per_unit for v in geo.d_voxel],
        "origin_mm": [float(v) for v in volume_affine(geo)[:3, 3]],
        "affine": aff.tolist(),
        "world_affine_lps": lps.tolist(),
        "axes": ("image[a, b, c] at (x_a, y_b, z_c) mm of kneas's frame; world LPS = world_affine_lps @ (x, y, z, 1) "
                 "(the scanner's RTK/ITK world, rotation axis = world y); NIfTI affine = diag(-1,-1,1,1) @ that @ index affine")
        if imported else "image[a, b, c] at (x_a, y_b, z_c) mm, scanner x/y/z = NIfTI R/A/S (z = rotation axis)",
        "attenuation_units": "data units (1/m; NAF normalised scale)",
        "files": {},
        "notes": [],
    }
    np.save(out / "attenuation.npy", mu.astype(np.float32))
    info["files"]["attenuation_npy"] = str(out / "attenuation.npy")
    if labels is not None:
        np.save(out / "labels.npy", labels)
        info["files"]["labels_npy"] = str(out / "labels.npy")
        info["labels"] = ("1 + argmax of the selector weights (materials in ascending attenuation), 0 = air where the "
                          f"total weight < {air_threshold}; partial-volume shells relabelled (kneas_method.evaluation."
                          "partial_volume), as kneas-eval scores them") if weights is not None else \
            f"number of thresholds {sorted(float(t) for t in thresholds)} (data units) the attenuation exceeds"
    else:
        info["notes"].append(f"{run.config.method} has no materials: no label volume (give --threshold to make one)")
    if nifti is None:
        nifti = _importable("nibabel")
        if not nifti:
            info["notes"].append(f"no NIfTI files: {missing_optional('nibabel', 'nifti', 'writing NIfTI volumes')}")
    if nifti:
        write_nifti(mu.astype(np.float32), aff, out / "attenuation.nii.gz", description=f"kneas {run.config.method} mu data units")
        info["files"]["attenuation_nifti"] = str(out / "attenuation.nii.gz")
        if labels is not None:
            write_nifti(labels, aff, out / "labels.nii.gz", description=f"kneas {run.config.method} material labels")
            info["files"]["labels_nifti"] = str(out / "labels.nii.gz")
    if mha is None:
        mha = _importable("itk")
    if mha:
        write_mha(mu.astype(np.float32), run.scene, out / "attenuation.mha")
        info["files"]["attenuation_mha"] = str(out / "attenuation.mha")
        if labels is not None:
            write_mha(labels, run.scene, out / "labels.mha")
            info["files"]["labels_mha"] = str(out / "labels.mha")
    write_json(out / "volume.json", info)
    return info
