"""`kneas-export {mesh,volume,figures} RUN_DIR`: meshes, volumes and figures of a trained run.

    kneas-export mesh outputs/foot/k-neas/20250101-120000 --resolution 256 --format ply
    kneas-export volume outputs/foot/k-neas/20250101-120000 -o foot-volumes/
    kneas-export figures outputs/foot/k-neas/20250101-120000/checkpoints/step-00001000.ckpt
    kneas-export mesh outputs/foot/naf/20250101-120000 --threshold 0.4

RUN_DIR is a run folder or one of its checkpoint files (a checkpoint copied to
another machine works next to its run's ``config.json``; no GPU is needed).
Files go to ``-o DIR`` (default ``RUN_DIR/export/``).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Optional

from ..errors import KneasError
from .common import ArgumentParser, console, run_cli


def _say(text: str) -> None:
    """Print plain text (paths and notes may hold brackets, which rich would read as markup)."""
    from rich.markup import escape

    console.print(escape(str(text)))


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("run", metavar="RUN_DIR", help="run folder (DIR/<scene>/<method>/<timestamp>) or a checkpoint file of it")
    p.add_argument("-o", "--output", metavar="DIR", default=None, help="output folder (default RUN_DIR/export/)")
    p.add_argument("--scene", default=None, help="scene to use instead of the run's (built-in name or NAF pickle; same volume box)")
    p.add_argument("--device", default="cpu", help="torch device: cpu (default), cuda, or auto")
    p.add_argument("--chunk", type=int, default=65536, help="points per network query (bounds memory; default 65536)")


def _parser() -> argparse.ArgumentParser:
    p = ArgumentParser(prog="kneas-export", description="Export meshes, volumes and figures of a trained kneas run.")
    sub = p.add_subparsers(dest="command", metavar="{mesh,volume,figures}")
    sub.required = True

    m = sub.add_parser("mesh", help="one surface mesh per material (open3d) plus a combined one coloured by material")
    _common(m)
    m.add_argument("--resolution", type=int, default=256, help="grid cells along the volume's longest side (default 256)")
    m.add_argument("--format", default="ply", choices=("ply", "obj", "stl", "glb"), help="mesh file format (default ply)")
    m.add_argument("--min-fragment", type=float, default=64.0,
                   help="drop connected pieces smaller than this: triangles if >= 1, fraction of the mesh if < 1 (default 64)")
    m.add_argument("--surface", choices=("raw", "visible"), default="raw",
                   help="raw: zero level set of each d_k (default); visible: only where the selector shows material k, "
                        "partial-volume shells relabelled (the surfaces kneas-eval scores)")
    m.add_argument("--threshold", type=float, action="append", default=None, metavar="MU",
                   help="methods without an SDF (naf, fdk): attenuation iso-level(s), data units; repeatable (default: Otsu)")

    v = sub.add_parser("volume", help="attenuation and material label volumes as .npy, and NIfTI (.nii.gz) when nibabel is installed")
    _common(v)
    v.add_argument("--threshold", type=float, action="append", default=None, metavar="MU",
                   help="methods without an SDF: label = number of these attenuation levels (data units) exceeded")
    v.add_argument("--no-nifti", action="store_true", help="write no NIfTI files (written when nibabel is installed: pip install 'kneas[nifti]')")
    v.add_argument("--no-mha", action="store_true", help="write no .mha files (written when ITK is installed: pip install 'kneas[scanner]')")

    f = sub.add_parser("figures", help="projection, slice, weight and label figures (PNG)")
    _common(f)
    f.add_argument("--views", type=int, default=3, help="held-out views to draw (default 3; 0 = all)")
    return p


def output_folder(run_dir: Path, output: Optional[str], default_name: str) -> Path:
    """``-o DIR`` or ``RUN_DIR/<default_name>``, created and checked writable."""
    from ..engine.run_dir import check_writable

    return check_writable(Path(output) if output else run_dir / default_name, needed_bytes=16 * 2**20, flag="-o DIR")


def _load(args):
    from ..device import resolve_device
    from ..engine.loading import load_run

    run = load_run(args.run, scene=args.scene, device=resolve_device(args.device))
    what = f"checkpoint {run.checkpoint_path}" + (f" (step {run.step})" if run.step is not None else "") if run.checkpoint_path else "volume.npy"
    _say(f"{run.config.method} run {run.run_dir}: {what}; scene {run.scene.name}")
    for note in run.notes:
        _say(f"note: {note}")
    return run


def _mesh(args) -> int:
    from ..engine.run_dir import write_json
    from ..export.mesh import export_meshes

    if args.resolution < 2:
        raise KneasError(f"--resolution must be at least 2, got {args.resolution}")
    run = _load(args)
    out = output_folder(run.run_dir, args.output, "export")
    t0 = time.perf_counter()
    res = export_meshes(run, out, resolution=args.resolution, fmt=args.format, min_fragment=args.min_fragment,
                        thresholds=args.threshold, surface=args.surface, chunk=args.chunk, progress=_say)
    for note in res.notes:
        _say(f"note: {note}")
    nx, ny, nz = res.resolution
    _say(f"grid {nx} x {ny} x {nz} cells of {res.cell_mm[0]:.3g} x {res.cell_mm[1]:.3g} x {res.cell_mm[2]:.3g} mm; "
                  f"iso-surfaces by {res.extractor or '-'}")
    for m in res.meshes + ([res.combined] if res.combined else []):
        if m.path is None:
            _say(f"  {m.name}: {m.note}")
            continue
        dropped = f", dropped {m.dropped_components} fragment(s) / {m.dropped_triangles} triangles" if m.dropped_components else ""
        note = f" ({m.note})" if m.note else ""
        _say(f"  {m.name}: {m.vertices} vertices, {m.triangles} triangles, "
                      f"{'watertight' if m.watertight else 'not watertight'} (checked by: {m.watertight_check}){dropped}{note} -> {m.path}")
    info = res.to_dict()
    info.update(method=run.config.method, scene=run.scene.name, checkpoint=str(run.checkpoint_path) if run.checkpoint_path else None,
                units="vertices in mm, scene frame", seconds=round(time.perf_counter() - t0, 2))
    write_json(out / "meshes.json", info)
    if all(m.path is None for m in res.meshes):
        raise KneasError("no mesh was written: no surface crosses the level" + ("s" if len(res.meshes) > 1 else "")
                         + (" (see the line above); choose a --threshold inside the attenuation's range" if res.thresholds else ""))
    return 0


def _volume(args) -> int:
    from ..export.volume import export_volume

    run = _load(args)
    out = output_folder(run.run_dir, args.output, "export")
    info = export_volume(run, out, thresholds=args.threshold, nifti=False if args.no_nifti else None, chunk=args.chunk,
                         mha=False if args.no_mha else None)
    for note in info["notes"]:
        _say(f"note: {note}")
    vx = ", ".join(f"{v:.4g}" for v in info["voxel_mm"])
    org = ", ".join(f"{v:.4g}" for v in info["origin_mm"])
    _say(f"volume {tuple(info['shape'])}, voxel ({vx}) mm, first voxel centre ({org}) mm")
    for key, path in info["files"].items():
        _say(f"  {key}: {path}")
    return 0


def _figures(args) -> int:
    from ..export.figures import export_figures

    run = _load(args)
    out = output_folder(run.run_dir, args.output, "export")
    paths = export_figures(run, out, views=None if args.views == 0 else args.views, chunk=args.chunk)
    for p in paths:
        _say(f"  {p}")
    return 0


def main(argv=None) -> None:
    argv = sys.argv[1:] if argv is None else list(argv)

    def body() -> int:
        args = _parser().parse_args(argv)
        if args.chunk < 1:
            raise KneasError(f"--chunk must be at least 1 point per query, got {args.chunk}; leave it out for 65536")
        if args.command == "figures" and args.views < 0:
            raise KneasError(f"--views must be 0 (all) or more, got {args.views}")
        return {"mesh": _mesh, "volume": _volume, "figures": _figures}[args.command](args)

    run_cli(body)


if __name__ == "__main__":  # pragma: no cover
    main()
