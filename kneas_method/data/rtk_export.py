"""Write a kneas scene for RTK: projections ``.mha`` + RTK geometry XML (``kneas-data export --rtk``).

Files written in ``out_dir``:

* ``projections.mha``: float32 line integrals, ITK size ``(nU, nV, N)``, pixel
  spacing ``(dU, dV)`` mm, detector centre at the origin, identity direction,
  rows in RTK's order (:func:`~kneas_method.data.rtk_geometry.kneas_rows_to_rtk`);
* ``geometry.xml``: RTK's ``RTKThreeDCircularGeometry`` (version 3), one
  ``<Projection>`` per image, in the same order;
* ``image.mha`` (scenes with ground truth): the ground-truth volume on the
  scene's voxel grid in RTK's world frame (data units, 1/m);
* ``rtk.json``: the views written, the reconstruction grid in RTK's world
  (``--dimension/--spacing/--origin`` for RTK's command-line tools) and the frame map.

The frame map is the scene's own (``meta["world_affine_lps"]``, from
``kneas-data import``) or, for other scenes, the default
:func:`~kneas_method.data.rtk_geometry.kneas_to_world_affine`; so importing the
export gives back the same projections and geometry.

RTK reconstructs line integrals given with lengths in mm, so its volumes are in
1/mm: multiply by 1000 for kneas data units (1/m).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from .rtk_geometry import (
    WORLD_AFFINE_META,
    axis_shift_of,
    itk_array_of_world,
    kneas_rows_to_rtk,
    kneas_to_rtk,
    kneas_to_world_affine,
    volume_to_world_array,
    world_grid_of,
    write_rtk_geometry,
)
from .naf import atomic_write_bytes, scene_geometry_mm
from .scene import Scene, Views

VIEW_CHOICES = ("train", "val", "all")
RTK_UNITS_NOTE = "RTK's volumes from these files are in 1/mm; multiply by 1000 for kneas data units (1/m)"


def scene_world_affine(scene: Scene) -> np.ndarray:
    """The scene's kneas-mm -> RTK/ITK LPS-mm affine [4, 4] (its stored one, else the default map)."""
    stored = scene.meta.get(WORLD_AFFINE_META)
    if stored is None:
        return kneas_to_world_affine(0.0)
    return kneas_to_world_affine(axis_shift_of(stored))


def export_views(scene: Scene, views: str) -> Views:
    """The views to write: ``train``, ``val`` or ``all`` (train then val)."""
    if views not in VIEW_CHOICES:
        raise ConfigError(f"--views {views!r} is not known; use one of {', '.join(VIEW_CHOICES)}")
    if views == "train":
        return scene.train
    if views == "val":
        if len(scene.val) == 0:
            raise ConfigError("the scene has no held-out views; export --views train")
        return scene.val
    return Views(np.concatenate([scene.train.angles, scene.val.angles]),
                 np.concatenate([scene.train.projections, scene.val.projections]))


def export_rtk(scene: Scene, out_dir, *, views: str = "train") -> dict:
    """Write ``scene`` for RTK (module docstring). Returns the ``rtk.json`` dict."""
    from .itk_io import require_itk, write_image

    require_itk("kneas-data export --rtk")
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--rtk {out} is a file; give a folder")
    from ..engine.run_dir import check_writable

    check_writable(out, needed_bytes=0, flag="--rtk")
    chosen = export_views(scene, views)
    affine = scene_world_affine(scene)
    shift = float(affine[1, 3])
    geom, grid = kneas_to_rtk(scene.geometry, chosen.angles, axis_shift_mm=shift, geometry_mm=scene_geometry_mm(scene))
    proj = kneas_rows_to_rtk(np.asarray(chosen.projections, dtype=np.float32))
    write_image(proj, out / "projections.mha", spacing=(grid.spacing_u, grid.spacing_v, 1.0),
                origin=(grid.origin_u, grid.origin_v, 0.0))
    write_rtk_geometry(geom, out / "geometry.xml")
    vgrid = world_grid_of(scene.geometry, affine)
    files = {"projections": str(out / "projections.mha"), "geometry": str(out / "geometry.xml")}
    if scene.image is not None:
        write_image(itk_array_of_world(volume_to_world_array(scene.image.astype(np.float32), vgrid)), out / "image.mha",
                    spacing=vgrid["spacing"], origin=vgrid["origin"])
        files["image"] = str(out / "image.mha")
    fmt = lambda vals: ",".join(f"{v:.10g}" for v in vals)  # noqa: E731
    info = {
        "scene": scene.name,
        "views": views,
        "n_projections": len(chosen),
        "mode": scene.geometry.mode,
        "files": files,
        "world_affine_lps": affine.tolist(),
        "volume_grid_lps": {"size": list(vgrid["size"]), "spacing_mm": list(vgrid["spacing"]), "origin_mm": list(vgrid["origin"]),
                            "direction": "identity", "kneas_axis_of_world_axis": list(vgrid["order"])},
        "rtkfdk": (f"rtkfdk -p {out} -r projections.mha -g {out / 'geometry.xml'} -o fdk.mha "
                   f"--dimension {fmt(vgrid['size'])} --spacing {fmt(vgrid['spacing'])} --origin {fmt(vgrid['origin'])}"),
        "units": RTK_UNITS_NOTE,
    }
    atomic_write_bytes(out / "rtk.json", json.dumps(info, indent=2).encode())
    return info
