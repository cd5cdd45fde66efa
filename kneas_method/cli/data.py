"""`kneas-data`: simulate, import, inspect, export and list CT scenes.

    kneas-data simulate --phantom foot -o foot_50.pickle
    kneas-data simulate --volume ct.nii.gz --convert -o my_50.pickle
    kneas-data simulate --volume dicom_series_folder/ --convert -o my_50.pickle
    kneas-data import projections.mha --geometry geometry.xml -o scan.pickle
    kneas-data import 'raw/*.tif' --geometry geometry.xml --flat flat.tif --dark dark.tif --pixel-mm 0.4 --centre-detector -o scan.pickle
    kneas-data inspect foot_50.pickle --png foot.png
    kneas-data export scan.pickle --rtk rtk_dir/
    kneas-data scenes
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from ..errors import ConfigError, KneasError
from .common import ArgumentParser, console, run_cli


def _parser() -> argparse.ArgumentParser:
    p = ArgumentParser(prog="kneas-data", description="Simulate, import, inspect, export and list cone-beam CT scenes (NAF pickle format).")
    sub = p.add_subparsers(dest="command", metavar="{simulate,import,inspect,export,scenes}")
    sub.required = True

    s = sub.add_parser("simulate", help="simulate a NAF scene from a built-in phantom or a CT volume")
    src = s.add_mutually_exclusive_group(required=True)
    src.add_argument("--phantom", metavar="NAME", help="built-in phantom (see `kneas-data scenes`)")
    src.add_argument("--volume", metavar="FILE", help="CT volume: .npy, .nii, .nii.gz, .mat, or a DICOM series folder")
    s.add_argument("-o", "--output", required=True, metavar="OUT.pickle", help="scene pickle to write")
    g = s.add_argument_group("volume")
    g.add_argument("--n-voxel", type=int, default=128, help="phantom volume grid size per axis (default 128)")
    g.add_argument("--voxel-mm", type=float, default=None, help="voxel size in mm (default 2.0, or the NIfTI header's)")
    g.add_argument("--convert", action="store_true", help="convert raw/HU values to attenuation (NAF's convert)")
    g.add_argument("--rescale-slope", type=float, default=1.0, help="HU = raw*slope + intercept (with --convert)")
    g.add_argument("--rescale-intercept", type=float, default=0.0, help="HU = raw*slope + intercept (with --convert)")
    g.add_argument("--no-normalize", action="store_true", help="keep attenuation units instead of scaling to [0, 1]")
    g.add_argument("--key", default=None, help="variable name inside a .mat file (default 'img')")
    g = s.add_argument_group("scanner")
    g.add_argument("--mode", choices=("cone", "parallel"), default="cone")
    g.add_argument("--dsd-mm", type=float, default=1500.0, help="source-detector distance (mm)")
    g.add_argument("--dso-mm", type=float, default=1000.0, help="source-origin distance (mm)")
    g.add_argument("--n-detector", type=int, default=None, help="detector pixels per side (default 128)")
    g.add_argument("--detector-mm", type=float, default=None, help="detector pixel size (mm; default: fit the volume)")
    g = s.add_argument_group("views")
    g.add_argument("--views", "--n-train", dest="n_train", type=int, default=50, help="training views (default 50)")
    g.add_argument("--n-val", type=int, default=50, help="held-out views (default 50)")
    g.add_argument("--total-angle", type=float, default=180.0, help="scan range in degrees (default 180)")
    g.add_argument("--start-angle", type=float, default=0.0, help="first angle in degrees")
    g.add_argument("--even-val-angles", action="store_true", help="held-out angles evenly spaced instead of random")
    g = s.add_argument_group("noise")
    g.add_argument("--noise", action="store_true", help="add Poisson + Gaussian detector noise (as NAF)")
    g.add_argument("--photons", type=float, default=1e5, help="photons per pixel for --noise")
    g.add_argument("--electronic-sigma", type=float, default=10.0, help="electronic noise std (counts)")
    g.add_argument("--seed", type=int, default=0)
    s.add_argument("--device", default=None, help="torch device for the volume projector (default cpu)")

    m = sub.add_parser("import", help="import your own scan: projection images + RTK geometry XML -> scene pickle")
    m.add_argument("projections", nargs="+", metavar="PROJECTIONS",
                   help="projection images (any format ITK reads: .mha, .mhd, .nrrd, .tif, ...): one stack, several files, a folder or a quoted glob")
    m.add_argument("--geometry", required=True, metavar="GEOMETRY.xml", help="RTK geometry XML (rtksimulatedgeometry, rtkvarianobigeometry, ... write it)")
    m.add_argument("-o", "--output", required=True, metavar="SCENE.pickle",
                   help="scene pickle to write; its file name is the scene's name (run folders are made under it)")
    m.add_argument("--kind", choices=("auto", "counts", "normalized", "line-integrals"), default="auto",
                   help="what the pixel values are (default auto: detected; counts when --flat/--dark/--i0 is given)")
    m.add_argument("--flat", metavar="FLAT", default=None, help="flat-field image(s) without the object (raw counts); frames are averaged")
    m.add_argument("--dark", metavar="DARK", default=None, help="dark-field image(s) (raw counts); frames are averaged")
    m.add_argument("--i0", type=float, default=None, metavar="VALUE", help="unattenuated intensity I0 instead of a flat field (raw counts)")
    m.add_argument("--volume-size", type=int, default=None, metavar="N", help="voxels along the grid's largest side (default: fit the field of view, at most 256)")
    m.add_argument("--voxel-mm", type=float, default=None, metavar="MM", help="voxel size in mm (default: a detector pixel at the isocentre)")
    m.add_argument("--pixel-mm", type=float, nargs="+", default=None, metavar="MM", help="detector pixel size (one, or u and v) when the files carry none (TIFF)")
    m.add_argument("--centre-detector", action="store_true", help="put the detector centre at u = v = 0 (files without an origin; offsets then come from the XML)")

    i = sub.add_parser("inspect", help="describe a scene (pickle or built-in name) and draw a projection and slices")
    i.add_argument("scene", metavar="SCENE", help="scene pickle or built-in scene name")
    i.add_argument("--png", default=None, metavar="OUT.png", help="write a figure of one projection and the middle slices")

    e = sub.add_parser("export", help="write a scene for RTK: projections .mha + RTK geometry XML")
    e.add_argument("scene", metavar="SCENE", help="scene pickle or built-in scene name")
    e.add_argument("--rtk", required=True, metavar="DIR", help="folder for projections.mha, geometry.xml (and image.mha, rtk.json)")
    e.add_argument("--views", choices=("train", "val", "all"), default="train", help="which views to write (default train)")

    sub.add_parser("scenes", help="list the built-in scenes, their materials and attenuation levels")
    return p


def _config(args):
    from ..data.simulate import SimulationConfig

    return SimulationConfig(
        n_voxel=args.n_voxel, voxel_mm=args.voxel_mm if args.voxel_mm is not None else 2.0,
        dsd_mm=args.dsd_mm, dso_mm=args.dso_mm, n_detector=args.n_detector, detector_mm=args.detector_mm,
        n_train=args.n_train, n_val=args.n_val, total_angle_deg=args.total_angle, start_angle_deg=args.start_angle,
        random_val_angles=not args.even_val_angles, noise=args.noise, photons=args.photons,
        electronic_sigma=args.electronic_sigma, seed=args.seed, mode=args.mode,
    )


def _simulate(args) -> int:
    from rich.progress import Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

    from ..data.naf import save_naf
    from ..data.simulate import simulate_from_volume, simulate_phantom
    from ..data.volume_io import load_volume, volume_meta

    cfg = _config(args)
    cfg.validate()
    out = _output_file(args.output, "scene_50.pickle")
    t0 = time.perf_counter()
    with Progress(SpinnerColumn(), TextColumn("{task.description}"), TimeElapsedColumn(), console=console, transient=True) as bar:
        task = bar.add_task("starting", total=None)

        def step(msg: str) -> None:
            bar.update(task, description=msg)

        if args.phantom is not None:
            from ..data.phantoms import get_phantom

            phantom = get_phantom(args.phantom)
            scene = simulate_phantom(phantom, cfg, progress=step)
        else:
            step(f"reading {args.volume}")
            vol, header_mm = load_volume(
                args.volume, convert=args.convert, rescale_slope=args.rescale_slope,
                rescale_intercept=args.rescale_intercept, normalize=not args.no_normalize, key=args.key,
            )
            voxel_mm = args.voxel_mm if args.voxel_mm is not None else (header_mm if header_mm is not None else cfg.voxel_mm)
            name = Path(args.volume).name.split(".")[0]
            meta = volume_meta(convert=args.convert, rescale_slope=args.rescale_slope, rescale_intercept=args.rescale_intercept, normalize=not args.no_normalize)
            meta["volume_file"] = str(args.volume)
            scene = simulate_from_volume(vol, cfg, voxel_mm=voxel_mm, name=name, meta=meta, device=args.device, progress=step)
        step(f"writing {out}")
        save_naf(scene, out)
    elapsed = time.perf_counter() - t0
    g = scene.geometry.to_mm()
    console.print(f"[bold]wrote[/] {out}  ({out.stat().st_size / 1e6:.1f} MB) in {elapsed:.1f} s")
    console.print(
        f"  source: {args.phantom and 'phantom ' + args.phantom or 'volume ' + str(args.volume)}; "
        f"volume {tuple(scene.geometry.n_voxel)} x {_fmt(g['dVoxel'])} mm; "
        f"detector {tuple(scene.geometry.n_detector)} x {_fmt(g['dDetector'])} mm"
    )
    console.print(
        f"  train {scene.train.projections.shape}, val {scene.val.projections.shape}; "
        f"projection max {float(scene.train.projections.max()):.4g}; noise {'on' if cfg.noise else 'off'}"
    )
    return 0


def _output_file(output: str, example: str) -> Path:
    """``-o`` as a path, refused before any work when it is a folder or its folder cannot be written."""
    from ..engine.run_dir import check_writable

    out = Path(output)
    if out.is_dir():
        raise ConfigError(f"-o {out} is a directory; give a file name such as {out / example}")
    suffix = Path(example).suffix
    if out.suffix.lower() != suffix:
        raise ConfigError(f"-o {out}: the file written is a scene {suffix}; give a name ending in {suffix}, such as "
                          f"{out.with_suffix(suffix) if out.suffix else out.parent / (out.name + suffix)}")
    check_writable(out.parent, needed_bytes=0, flag="-o")
    return out


def _import(args) -> int:
    from ..data.naf import save_naf
    from ..data.scanner_import import import_scan

    out = _output_file(args.output, "scan.pickle")
    t0 = time.perf_counter()
    with console.status("reading projections and geometry"):
        scene = import_scan(
            args.projections, args.geometry, flat=args.flat, dark=args.dark, i0=args.i0, kind=args.kind,
            volume_size=args.volume_size, voxel_mm=args.voxel_mm, pixel_mm=args.pixel_mm,
            centre_detector=args.centre_detector, name=Path(args.output).stem,
        )
        save_naf(scene, out)
    g = scene.geometry.to_mm()
    imp = scene.meta["import"]
    conv = imp["conversion"]
    say = lambda msg: console.print(msg, soft_wrap=True, markup=False)  # noqa: E731
    say(f"wrote {out}  ({out.stat().st_size / 1e6:.1f} MB) in {time.perf_counter() - t0:.1f} s")
    a = np.degrees(scene.train.angles)
    say(f"  {len(scene.train)} projections from {imp['projections']['count']} file(s); {g['mode']} beam, DSO {g['DSO']:.6g} mm, "
        f"DSD {g['DSD']:.6g} mm; angles {a.min():.2f}..{a.max():.2f} deg ({scene.meta['totalAngle']:.1f} deg arc)")
    say(f"  detector {tuple(scene.geometry.n_detector)} px x {_fmt(g['dDetector'])} mm, offset {_fmt(g['offDetector'])} mm (kneas u, v)")
    i0 = f", I0 {conv['i0']:.6g}" + (" (estimated from the air border)" if conv.get("i0_estimated_from") else "") if "i0" in conv else ""
    say(f"  values: {conv['kind']}{' (detected)' if conv['detected'] else ''}: {conv['formula']}{i0}")
    if conv.get("kind_warning"):
        say(f"warning: {conv['kind_warning']}")
    p = scene.train.projections
    neg = 100 * float(np.mean(p < 0))
    say(f"  line integrals {_range(p)}" + (f", {neg:.1f} % below 0 (noise in air, kept)" if neg else ""))
    say(f"  grid {tuple(scene.geometry.n_voxel)} x {_fmt(g['dVoxel'])} mm, offset {_fmt(g['offOrigin'])} mm "
        f"({imp['grid']['chosen']}: radius {imp['grid']['fov_radius_mm']:.4g} mm, height {imp['grid']['fov_height_mm']:.4g} mm)")
    say(f"  frame: {imp['frame']}")
    from ..engine.loading import HOLDOUT_AT_MOST, HOLDOUT_FRACTION

    say(f"  no ground truth and no held-out views: kneas-train holds {HOLDOUT_FRACTION:.0%} of the projections (at most "
        f"{HOLDOUT_AT_MOST}, evenly spread over the scan) out of training for the 2D metrics and trains on the rest")
    for note in imp["notes"]:
        say(f"note: {note}")
    return 0


def _export(args) -> int:
    from ..data.rtk_export import export_rtk
    from ..data.scenes import resolve_scene

    scene = resolve_scene(args.scene, flag="SCENE", progress=lambda msg: console.print(msg, soft_wrap=True, markup=False))
    info = export_rtk(scene, args.rtk, views=args.views)
    say = lambda msg: console.print(msg, soft_wrap=True, markup=False)  # noqa: E731
    say(f"wrote {info['n_projections']} {args.views} projections of {scene.name} for RTK to {args.rtk}")
    for key, path in info["files"].items():
        say(f"  {key}: {path}")
    say(f"  reconstruct with: {info['rtkfdk']}")
    say(f"  note: {info['units']}")
    return 0


def _fmt(values) -> str:
    arr = np.atleast_1d(np.asarray(values, dtype=float))
    return "(" + ", ".join(f"{v + 0.0:.4g}" for v in arr) + ")"  # + 0.0: no "-0"


def _range(arr) -> str:
    return f"[{float(np.min(arr)) + 0.0:.4g}, {float(np.max(arr)) + 0.0:.4g}]"  # + 0.0: no "-0"


def _inspect(args) -> int:
    from ..data.scenes import resolve_scene

    if args.png:  # refused before the report, not after it
        from ..engine.run_dir import check_writable

        if Path(args.png).is_dir():
            raise ConfigError(f"--png {args.png} is a folder; give a file name such as {Path(args.png) / 'scene.png'}")
        check_writable(Path(args.png).parent, needed_bytes=0, flag="--png")
    scene = resolve_scene(args.scene, flag="SCENE", progress=lambda msg: console.print(msg, soft_wrap=True, markup=False))
    g = scene.geometry.to_mm()
    c = console
    c.print(f"[bold]{args.scene}[/]  (scene '{scene.name}', mode {g['mode']})")
    c.print(f"  DSD {g['DSD']:.6g} mm, DSO {g['DSO']:.6g} mm; model scale {scene.geometry.scale:.6g} units/m")
    c.print(f"  detector {tuple(scene.geometry.n_detector)} px (nU, nV) x {_fmt(g['dDetector'])} mm = {_fmt(g['sDetector'])} mm, offset {_fmt(g['offDetector'])} mm")
    c.print(f"  volume {tuple(scene.geometry.n_voxel)} x {_fmt(g['dVoxel'])} mm = {_fmt(g['sVoxel'])} mm, offset {_fmt(g['offOrigin'])} mm")
    near, far = scene.geometry.near_far
    c.print(f"  near/far {near * scene.geometry.mm_per_unit:.5g} / {far * scene.geometry.mm_per_unit:.5g} mm along the central ray")
    from ..datamanagers.ct import noise_air_threshold

    threshold, sigma = noise_air_threshold(scene.train.projections)
    for label, views in (("train", scene.train), ("val", scene.val)):
        p = views.projections
        if len(views) == 0:
            c.print(f"  {label}: 0 views (no held-out views; evaluation holds out training views)")
            continue
        obj = float(np.mean(p > threshold)) * 100
        neg = float(np.mean(p < 0)) * 100
        c.print(
            f"  {label}: {len(views)} views {tuple(p.shape)}, angles {np.degrees(views.angles.min()):.2f}..{np.degrees(views.angles.max()):.2f} deg, "
            f"projections {_range(p)} ({obj:.1f} % object pixels" + (f", {neg:.1f} % below 0" if neg else "") + ")"
        )
    if threshold > 0:
        c.print(f"  noise: sigma {sigma:.3g} in air (from the negative values); air = p <= {threshold:.3g}")
    from ..data.truncation import fitting_scene

    fitting_scene(scene, threshold, say=lambda line: c.print(f"  {line}", soft_wrap=True))
    if scene.image is not None:
        c.print(f"  image {tuple(scene.image.shape)} {scene.image.dtype}, values {_range(scene.image)}")
    else:
        c.print("  image: none (no ground truth)")
    if scene.materials:
        c.print(f"  materials: {', '.join(f'{i + 1}={m}' for i, m in enumerate(scene.materials))}")
    if isinstance(scene.meta.get("import"), dict):
        imp = scene.meta["import"]
        c.print(f"  imported from {imp.get('geometry')} ({imp.get('projections', {}).get('count', '?')} projection file(s)); "
                f"{imp.get('conversion', {}).get('formula', '')}", markup=False)
        c.print(f"  frame: {imp.get('frame', '')}", markup=False)
    skip = {"geometry_mm", "simulation", "import", "world_affine_lps"}
    extras = {k: v for k, v in scene.meta.items() if k not in skip and (np.isscalar(v) or v is None)}
    if extras:
        c.print("  " + ", ".join(f"{k}={v}" for k, v in extras.items()))
    if args.png:
        _figure(scene, Path(args.png))
        c.print(f"  figure: {args.png}")
    return 0


def _figure(scene, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [("train projection 0 (line integral)", scene.train.projections[0])]
    if scene.image is not None:
        nx, ny, nz = scene.image.shape
        panels += [
            (f"image[:, :, {nz // 2}] (xy)", scene.image[:, :, nz // 2].T),
            (f"image[:, {ny // 2}, :] (xz)", scene.image[:, ny // 2, :].T),
            (f"image[{nx // 2}, :, :] (yz)", scene.image[nx // 2, :, :].T),
        ]
    fig, axes = plt.subplots(1, len(panels), figsize=(4 * len(panels), 4), squeeze=False)
    for ax, (title, img) in zip(axes[0], panels):
        im = ax.imshow(img, cmap="gray", origin="lower" if "image" in title else "upper")
        ax.set_title(title, fontsize=9)
        ax.axis("off")
        fig.colorbar(im, ax=ax, fraction=0.046)
    fig.suptitle(f"{scene.name}", fontsize=10)
    fig.tight_layout()
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(out, dpi=100)
    except OSError as exc:
        raise KneasError(f"cannot write {out} ({exc.strerror or exc}); choose a writable --png path") from None
    finally:
        plt.close(fig)


def _scenes(args) -> int:
    from ..data.phantoms import PHANTOM_NAMES, get_phantom

    for name in PHANTOM_NAMES:
        phantom = get_phantom(name)
        console.print(f"[bold]{name}[/]")
        console.print(phantom.describe())
        console.print("")
    console.print("Use one with `kneas-train <method> --scene NAME` or `kneas-data simulate --phantom NAME -o OUT.pickle`.")
    return 0


def main(argv: list[str] | None = None) -> None:
    """Console entry point (``kneas-data``)."""
    def body():
        args = _parser().parse_args(sys.argv[1:] if argv is None else argv)
        if args.command == "simulate":
            return _simulate(args)
        if args.command == "inspect":
            return _inspect(args)
        if args.command == "import":
            return _import(args)
        if args.command == "export":
            return _export(args)
        return _scenes(args)

    run_cli(body)


if __name__ == "__main__":  # pragma: no cover
    main()
