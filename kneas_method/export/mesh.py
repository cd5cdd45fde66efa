"""Surface meshes of a trained run (``kneas-export mesh``), written with open3d.

What is extracted
-----------------
* SDF methods (``neas-*``, ``kselector*``, ``k-neas``): one surface per material,
  the zero level set of ``d_k`` (``surface="raw"``, default: the model's whole
  surface of material ``k``, e.g. the skin for soft tissue) or of the visible
  region ``e_k = max(d_k, max_{j>k} -d_j)`` (``surface="visible"``: where the
  selector shows material ``k``, with partial-volume shells relabelled as evaluation
  does; see :mod:`kneas_method.evaluation.surfaces` and
  :mod:`kneas_method.evaluation.partial_volume`).
* Methods with no SDF (``naf``, ``fdk``): iso-surfaces of the attenuation
  ``mu = threshold`` for each threshold (data units); the default threshold is
  Otsu's on the attenuation grid, and the report says it was thresholded.

How
---
The field is sampled at the cell centres of a grid covering the scene's volume
box, ``resolution`` cells along its longest side (default 256), the others in
proportion. It is queried in chunks of ``chunk`` points, so the network's
activations stay bounded whatever the resolution; the sampled field is kept as
one float32 array, ``nx·ny·nz·4`` bytes per material (67 MB per material at
256^3). The grid is padded with one outside layer so surfaces touching the
volume border close.

Iso-surfaces come from open3d's ``open3d.t.geometry.TriangleMesh.create_isosurfaces``
(flying edges, the tensor API; open3d >= 0.18) when present, else from
``skimage.measure.marching_cubes``; either way the result is an
``open3d.geometry.TriangleMesh`` whose vertices are converted to **mm** in the
scene's physical frame (``geometry.voxel_centres`` x ``mm_per_unit``). Vertices
closer than 1e-3 of a cell are merged and zero-area triangles removed (marching
cubes makes both where the field vanishes at a grid point), triangles are
oriented outwards, and connected components (``cluster_connected_triangles``)
smaller than ``min_fragment`` are dropped: a count of triangles when >= 1, a
fraction of the mesh's triangles when < 1.

open3d is imported only here (``pip install 'kneas[mesh]'``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional, Sequence

import numpy as np

from ..errors import KneasError, missing_optional

FORMATS = ("ply", "obj", "stl", "glb")
DEFAULT_RESOLUTION = 256
DEFAULT_MIN_FRAGMENT = 64.0
SURFACES = ("raw", "visible")


LIBUSB_SONAME = "libusb-1.0.so.0"


def load_libusb() -> Optional[str]:
    """Make ``libusb-1.0`` (which open3d's Linux wheel links against) loadable without root:
    when the system has none, load the copy PyPI's ``libusb-package`` ships (part of
    ``kneas[mesh]``) with ``RTLD_GLOBAL``, so open3d's import finds it by its soname.

    Returns where libusb comes from (``"system"``, the package's file path), or None when
    neither is there (open3d's import then names the missing library)."""
    import ctypes
    import sys

    if not sys.platform.startswith("linux"):
        return "system"
    try:
        ctypes.CDLL(LIBUSB_SONAME, mode=ctypes.RTLD_GLOBAL)
        return "system"
    except OSError:
        pass
    try:
        import libusb_package
    except ImportError:
        return None
    path = libusb_package.get_library_path()
    if path is None:
        return None
    ctypes.CDLL(str(path), mode=ctypes.RTLD_GLOBAL)
    return str(path)


def import_open3d():
    """open3d (with libusb loaded first, :func:`load_libusb`), or a one-line KneasError
    naming what is missing and how to get it with pip."""
    import importlib.util

    if importlib.util.find_spec("open3d") is None:
        raise missing_optional("open3d", "mesh", "mesh export")
    libusb = load_libusb()
    try:
        import open3d as o3d
    except (ImportError, OSError) as exc:
        cause = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        hint = ("libusb-1.0 is missing: install it with pip install libusb-package (part of pip install 'kneas[mesh]')"
                if "libusb" in cause and libusb is None else "reinstall it with pip install --force-reinstall open3d")
        raise KneasError(f"open3d is installed but cannot load ({cause}); {hint}") from None
    return o3d


def material_colors(n: int) -> np.ndarray:
    """``[n, 3]`` RGB in [0, 1], one distinct colour per material (tab10)."""
    import matplotlib

    cmap = matplotlib.colormaps["tab10"]
    return np.array([cmap(i % 10)[:3] for i in range(n)], dtype=np.float64)


@dataclass
class MeshInfo:
    """One exported surface."""

    name: str
    path: Optional[Path]
    vertices: int
    triangles: int
    watertight: bool
    components: int
    dropped_components: int
    dropped_triangles: int
    source: str
    level: Optional[float] = None
    note: str = ""
    watertight_check: str = ""
    in_combined: bool = True

    def to_dict(self) -> dict:
        return {k: (str(v) if isinstance(v, Path) else v) for k, v in self.__dict__.items()}


@dataclass
class MeshExport:
    meshes: list[MeshInfo] = field(default_factory=list)
    combined: Optional[MeshInfo] = None
    resolution: tuple[int, int, int] = (0, 0, 0)
    cell_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    kind: str = "sdf"
    thresholds: Optional[list[float]] = None
    extractor: str = ""
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        return {
            "kind": self.kind, "resolution": list(self.resolution), "cell_mm": list(self.cell_mm),
            "thresholds_data_units": self.thresholds, "extractor": self.extractor,
            "meshes": [m.to_dict() for m in self.meshes],
            "combined": self.combined.to_dict() if self.combined else None, "notes": self.notes,
        }


# ------------------------------------------------------------------ extraction
def isosurface(field: np.ndarray, grid_geometry, level: float = 0.0, *, inside_negative: bool = True):
    """Iso-surface ``field == level`` of ``field [nx, ny, nz]`` sampled at ``grid_geometry``'s
    cell centres, as an ``open3d.geometry.TriangleMesh`` with vertices in mm.

    ``inside_negative``: the solid is where ``field < level`` (SDFs); else where
    ``field > level`` (attenuation). Triangles face outwards. Returns
    ``(mesh or None, extractor name)``; None when the field never crosses ``level``.
    """
    import torch

    o3d = import_open3d()
    f = np.asarray(field, dtype=np.float32) - np.float32(level)
    if not inside_negative:
        f = -f
    if f.size == 0 or not float(f.min()) < 0.0:
        return None, ""
    pad = max(float(np.abs(f).max()), 1e-6)
    f = np.pad(f, 1, constant_values=pad)
    if hasattr(o3d.t.geometry.TriangleMesh, "create_isosurfaces"):
        # open3d indexes the volume as [z, y, x] -> vertex (x, y, z): pass it transposed.
        tm = o3d.t.geometry.TriangleMesh.create_isosurfaces(o3d.core.Tensor(np.ascontiguousarray(f.transpose(2, 1, 0))), [0.0])
        verts = tm.vertex.positions.numpy().astype(np.float64) if "positions" in tm.vertex else np.zeros((0, 3))
        faces = tm.triangle.indices.numpy().astype(np.int64) if "indices" in tm.triangle else np.zeros((0, 3), np.int64)
        extractor = "open3d.t.geometry.TriangleMesh.create_isosurfaces"
    else:  # older open3d
        from skimage.measure import marching_cubes

        verts, faces, _n, _v = marching_cubes(f, level=0.0)
        verts = verts.astype(np.float64)
        faces = faces.astype(np.int64)
        extractor = "skimage.measure.marching_cubes"
    if len(faces) == 0:
        return None, extractor
    spacing_mm = np.array([float(d) * grid_geometry.mm_per_unit for d in grid_geometry.d_voxel])
    first_mm = np.array([float(ax[0]) for ax in grid_geometry.voxel_axes(dtype=torch.float64)]) * grid_geometry.mm_per_unit
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector((verts - 1.0) * spacing_mm + first_mm),
                                     o3d.utility.Vector3iVector(faces.astype(np.int32)))
    mesh.merge_close_vertices(1e-3 * float(spacing_mm.min()))
    mesh.remove_degenerate_triangles()
    mesh.remove_duplicated_triangles()
    mesh.remove_unreferenced_vertices()
    _orient_outwards(mesh, f, grid_geometry, spacing_mm, first_mm)
    return mesh, extractor


def _orient_outwards(mesh, padded_field: np.ndarray, grid_geometry, spacing_mm, first_mm) -> None:
    """Flip all triangles if their normals point into the solid (field < 0 inside)."""
    tri = np.asarray(mesh.triangles)
    if len(tri) == 0:
        return
    v = np.asarray(mesh.vertices)
    a, b, c = v[tri[:, 0]], v[tri[:, 1]], v[tri[:, 2]]
    n = np.cross(b - a, c - a)
    centre = (a + b + c) / 3.0
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    ok = norm[:, 0] > 0
    if not ok.any():
        return
    probe = centre[ok] + 0.5 * float(spacing_mm.min()) * n[ok] / norm[ok]
    idx = np.rint((probe - first_mm) / spacing_mm + 1.0).astype(np.int64)
    idx = np.clip(idx, 0, np.array(padded_field.shape) - 1)
    vals = padded_field[idx[:, 0], idx[:, 1], idx[:, 2]]
    if np.mean(vals < 0) > 0.5:  # the normals point inside
        mesh.triangles = type(mesh.triangles)(tri[:, [0, 2, 1]].astype(np.int32))


def drop_fragments(mesh, min_fragment: float = DEFAULT_MIN_FRAGMENT) -> tuple[int, int, int]:
    """Remove connected components smaller than ``min_fragment`` (triangles if >= 1,
    fraction of all triangles if < 1). Returns ``(components, dropped components, dropped triangles)``."""
    n = len(mesh.triangles)
    if n == 0:
        return 0, 0, 0
    cluster, counts, _area = mesh.cluster_connected_triangles()
    cluster, counts = np.asarray(cluster), np.asarray(counts)
    limit = float(min_fragment) * n if 0 < min_fragment < 1 else float(min_fragment)
    small = counts < limit
    if small.all():  # never drop everything: keep the largest piece
        small[int(np.argmax(counts))] = False
    if small.any():
        mesh.remove_triangles_by_mask(small[cluster])
        mesh.remove_unreferenced_vertices()
    return int(len(counts)), int(small.sum()), int(counts[small].sum())


SELF_INTERSECTION_LIMIT = 20000


def check_watertight(mesh, limit: int = SELF_INTERSECTION_LIMIT) -> tuple[bool, str]:
    """``(watertight, how)``. Up to ``limit`` triangles: open3d's ``is_watertight()``
    (closed edge- and vertex-manifold, no self-intersection). Above it, open3d's
    self-intersection test (quadratic in the triangle count: ~10 s at 40k triangles)
    is skipped and the mesh is called watertight when it is a closed edge- and
    vertex-manifold, which is what marching-cubes output (never self-intersecting
    by construction) needs."""
    if len(mesh.triangles) <= limit:
        return bool(mesh.is_watertight()), "is_watertight()"
    closed = bool(mesh.is_edge_manifold(allow_boundary_edges=False) and mesh.is_vertex_manifold())
    return closed, f"closed manifold (self-intersection test skipped above {limit} triangles)"


def write_mesh(mesh, path: Path) -> Path:
    """Write ``mesh`` (PLY, OBJ, STL or GLB by suffix); KneasError when open3d fails."""
    o3d = import_open3d()
    mesh.compute_vertex_normals()
    mesh.compute_triangle_normals()
    path = Path(path)
    if path.suffix.lower() == ".glb":
        # open3d 0.20's legacy writer puts the buffer in a data URI, which makes an
        # invalid .glb (its own reader refuses it); the tensor-API writer is correct.
        ok = o3d.t.io.write_triangle_mesh(str(path), o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    else:
        ok = o3d.io.write_triangle_mesh(str(path), mesh, write_ascii=False)
    if not ok or not path.is_file():
        raise KneasError(f"open3d could not write {path}; check the folder is writable or choose another --format")
    return path


# --------------------------------------------------------------------- fields
def sample_fields(run, resolution: int = DEFAULT_RESOLUTION, *, surface: str = "raw", chunk: int = 65536):
    """The scalar fields to contour on the export grid.

    Returns ``(grid_geometry, fields [nx, ny, nz, C] float32, kind)``: ``kind`` is
    ``"sdf"`` (C = K distance fields, model units) or ``"attenuation"`` (C = 1, data units).
    """
    from ..evaluation.surfaces import grid_points, query_grid, shell_free_fields, visible_fields

    if surface not in SURFACES:
        raise KneasError(f"--surface {surface!r} is unknown; choose one of {', '.join(SURFACES)}")
    geo = run.scene.geometry
    if run.model is None:  # FDK: the volume on the scene grid
        vol = np.asarray(run.volume, dtype=np.float32)
        if resolution is not None and max(vol.shape) != int(resolution):
            from scipy.ndimage import zoom

            grid, _ = grid_points(geo, resolution=resolution)
            vol = zoom(vol, [n / s for n, s in zip(grid.n_voxel, vol.shape)], order=1).astype(np.float32)
            vol = vol[: grid.n_voxel[0], : grid.n_voxel[1], : grid.n_voxel[2]]
            if vol.shape != tuple(grid.n_voxel):
                vol = np.pad(vol, [(0, n - s) for n, s in zip(grid.n_voxel, vol.shape)], mode="edge")
            return grid, vol[..., None], "attenuation"
        return geo, vol[..., None], "attenuation"
    grid, _ = grid_points(geo, resolution=resolution)
    levels = material_levels(run, chunk=chunk)[1] if run.has_surfaces and surface == "visible" and run.model.num_materials > 1 else None
    if levels is not None:
        return grid, shell_free_fields(run.model, grid, levels, geo, chunk=chunk), "sdf"
    if run.has_surfaces:
        d = query_grid(run.model, grid, keys=("distances",), chunk=chunk)["distances"]
        return grid, (visible_fields(d) if surface == "visible" else d), "sdf"
    mu = query_grid(run.model, grid, keys=("mu",), chunk=chunk)["mu"]
    return grid, mu[..., None], "attenuation"


def outer_layers(labels: np.ndarray, mean_mu: Sequence[float], *, core_fraction: float = 0.05) -> list[int]:
    """Materials that are a partial-volume layer at the object's outer surface, not a material.

    A smooth reconstruction passes from air to the first tissue through intermediate
    attenuations, and a K-material model can give that rim its own material: a layer
    about one voxel thick between air and the object, whose attenuation is nearer air's
    than any material's (foot: material 1, mean 0.07 against soft tissue's 0.28). Such a
    material ``k`` (1-based) is reported when both hold:

    * its mean attenuation ``mean_mu[k-1]`` is nearer air (0) than the mean of every
      other material (:func:`kneas_method.evaluation.surfaces.match_materials` with the
      other materials' means as the levels);
    * it has almost no core: fewer than ``core_fraction`` of its voxels survive a
      binary erosion with the 3x3x3 cube, i.e. nowhere is it more than ~2 voxels thick.

    A thick low-attenuation material (lung) keeps its core; a thin dense one (enamel) is
    not near air. Needs no ground truth.

    Args:
        labels: ``[X, Y, Z]`` integer labels, 0 = air, k = material k (on the scene's grid).
        mean_mu: ``[K]`` mean attenuation of each material where it is the label.
    Returns:
        the 1-based material numbers, ascending.
    """
    from scipy.ndimage import binary_erosion

    from ..evaluation.surfaces import match_materials

    mean_mu = np.asarray(mean_mu, dtype=np.float64)
    labels = np.asarray(labels)
    out = []
    for k in range(1, len(mean_mu) + 1):
        others = np.delete(mean_mu, k - 1)
        if len(others) == 0 or match_materials([mean_mu[k - 1]], others)[0] != 0:
            continue
        region = labels == k
        n = int(region.sum())
        if n == 0:
            continue
        core = int(binary_erosion(region, structure=np.ones((3, 3, 3), bool)).sum())
        if core < core_fraction * n:
            out.append(k)
    return out


def material_levels(run, chunk: int = 65536) -> tuple[Optional[np.ndarray], Optional[np.ndarray]]:
    """``(labels [X, Y, Z], mean attenuation [K])`` of a run with a K-material selector on the
    scene's voxel grid (the grid evaluation scores); ``(None, None)`` without one."""
    from ..evaluation.surfaces import query_grid, voxel_labels

    q = query_grid(run.model, run.scene.geometry, keys=("mu", "weights", "mu_materials"), chunk=chunk)
    if "weights" not in q or "mu_materials" not in q:
        return None, None
    labels, levels, _ = voxel_labels(q, shells=False)  # the rim is a whole material: judged on the labels as they are
    return labels, levels


def outer_layers_of_run(run, chunk: int = 65536) -> list[int]:
    """:func:`outer_layers` of a run with a K-material selector (:func:`material_levels`)."""
    labels, levels = material_levels(run, chunk=chunk)
    return [] if labels is None else outer_layers(labels, levels)


def default_threshold(mu: np.ndarray) -> float:
    """Otsu's threshold of the attenuation grid (data units)."""
    from skimage.filters import threshold_otsu

    v = np.asarray(mu, dtype=np.float64)
    lo, hi = float(v.min()), float(v.max())
    if not hi > lo:
        raise KneasError("the reconstructed attenuation is constant, so there is no surface to threshold; check the run")
    try:
        return float(threshold_otsu(v))
    except ValueError:  # range too narrow for a 256-bin histogram: take the midpoint
        return 0.5 * (lo + hi)


# ---------------------------------------------------------------------- export
def export_meshes(
    run,
    out_dir,
    *,
    resolution: int = DEFAULT_RESOLUTION,
    fmt: str = "ply",
    min_fragment: float = DEFAULT_MIN_FRAGMENT,
    thresholds: Optional[Sequence[float]] = None,
    surface: str = "raw",
    chunk: int = 65536,
    progress: Optional[Callable[[str], None]] = None,
) -> MeshExport:
    """Extract and write one mesh per material (or threshold) plus a combined mesh
    coloured by material, into ``out_dir``. See the module docs. ``progress`` is called with one
    line as each phase starts (None: silent).

    Returns a :class:`MeshExport` with the counts and watertightness per mesh
    (also written as ``meshes.json`` by the CLI).
    """
    o3d = import_open3d()
    fmt = fmt.lower().lstrip(".")
    if fmt not in FORMATS:
        raise KneasError(f"--format {fmt!r} is not supported; choose one of {', '.join(FORMATS)}")
    if not min_fragment >= 0:
        raise KneasError(f"--min-fragment must be >= 0 (triangles, or a fraction < 1), got {min_fragment}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    say = progress or (lambda line: None)
    say(f"mesh: the run's fields on a grid of {resolution} cells along the box's longest side")
    grid, fields, kind = sample_fields(run, resolution, surface=surface, chunk=chunk)
    mm = grid.mm_per_unit
    result = MeshExport(resolution=tuple(grid.n_voxel), cell_mm=tuple(float(d) * mm for d in grid.d_voxel), kind=kind)
    jobs = []  # (name, field, level, inside_negative, source)
    layers: list[int] = []
    if kind == "sdf":
        if thresholds:
            result.notes.append(f"{run.config.method} has signed distances: its surfaces are their zero level sets, so "
                                "--threshold (for methods without them: naf and the classical ones) was not used")
        K = fields.shape[-1]
        names = _material_names(run, K)
        layers = outer_layers_of_run(run, chunk=chunk) if K > 1 else []
        for k in layers:
            result.notes.append(
                f"{names[k - 1]} is a layer at most ~2 voxels thick between air and the object, its attenuation nearer "
                f"air's than any other material's: the partial-volume rim of the outer surface, not a tissue; its mesh is "
                f"written but left out of combined.{fmt} (evaluation counts it as air)")
        for k in range(K):
            what = "d_%d = 0" % (k + 1) if surface == "raw" else "visible region of material %d" % (k + 1)
            jobs.append((names[k], fields[..., k], 0.0, True, what))
    else:
        mu = fields[..., 0]
        if thresholds is None or len(thresholds) == 0:
            thresholds = [default_threshold(mu)]
            result.notes.append(f"{run.config.method} has no signed distance field: thresholded the attenuation at "
                                f"{thresholds[0]:.4g} (data units, Otsu); choose with --threshold")
        else:
            result.notes.append(f"{run.config.method} has no signed distance field: thresholded the attenuation at "
                                f"{', '.join(f'{t:.4g}' for t in thresholds)} (data units)")
        result.thresholds = [float(t) for t in thresholds]
        for i, t in enumerate(sorted(float(t) for t in thresholds)):
            jobs.append((f"threshold-{i + 1}", mu, t, False, f"mu = {t:.6g} (data units)"))
    colors = material_colors(len(jobs))
    combined = o3d.geometry.TriangleMesh()
    from ..data.rtk_geometry import scanner_world_affine

    world = scanner_world_affine(run.scene)
    if world is not None:
        result.notes.append("vertices in the scanner's world (RTK/ITK LPS, mm), where kneas-export volume's .mha and "
                            "RTK's reconstruction of the same data lie")
    for i, (name, f, level, inside_negative, source) in enumerate(jobs):
        say(f"mesh: {name} ({i + 1}/{len(jobs)}), marching cubes and checks")
        mesh, extractor = isosurface(f, grid, level, inside_negative=inside_negative)
        if mesh is not None and world is not None:
            mesh.transform(world)
        result.extractor = result.extractor or extractor
        stem = _slug(name)
        if mesh is None or len(mesh.triangles) == 0:
            span = ("" if inside_negative else
                    f": the attenuation spans {float(f.min()):.4g} to {float(f.max()):.4g} (data units)")
            result.meshes.append(MeshInfo(name, None, 0, 0, False, 0, 0, 0, source, level,
                                          note=f"no surface in the volume (the field never crosses the level{span}); no file written",
                                          in_combined=False))
            continue
        comps, dropped, dropped_tri = drop_fragments(mesh, min_fragment)
        mesh.paint_uniform_color(colors[i])
        path = write_mesh(mesh, out / f"{stem}.{fmt}")
        tight, how = check_watertight(mesh)
        rim = (i + 1) in layers  # only SDF runs have layers
        result.meshes.append(MeshInfo(name, path, len(mesh.vertices), len(mesh.triangles), tight,
                                      comps, dropped, dropped_tri, source, level, watertight_check=how,
                                      note="outer partial-volume layer; not in the combined mesh" if rim else "",
                                      in_combined=not rim))
        if not rim:
            combined += mesh
    if len(combined.triangles):
        path = write_mesh(combined, out / f"combined.{fmt}")
        # the union of closed surfaces is closed; nested materials touch, so no self-intersection test here
        parts = [m for m in result.meshes if m.path is not None and m.in_combined]
        tight = all(m.watertight for m in parts)
        result.combined = MeshInfo("combined", path, len(combined.vertices), len(combined.triangles), tight,
                                   sum(m.components - m.dropped_components for m in parts), 0, 0,
                                   "all meshes" + (" but the outer partial-volume layer" if layers else "") + ", coloured by material",
                                   watertight_check="watertight when every part is")
    else:
        result.notes.append("no surface found in the volume, so no file was written")
    return result


def _material_names(run, K: int) -> list[str]:
    return [f"material {k + 1}" for k in range(K)]


def _slug(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_" else "-" for c in name.strip().lower()).strip("-") or "mesh"
