"""`kneas-data`: simulate, inspect and list CT scenes.

    kneas-data simulate --phantom foot -o foot_50.pickle
    kneas-data simulate --volume ct.nii.gz --convert -o my_50.pickle
    kneas-data inspect foot_50.pickle --png foot.png
    kneas-data scenes
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from ..errors import ConfigError, KneasError
from .common import console, run_cli


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="kneas-data", description="Simulate, inspect and list cone-beam CT scenes (NAF pickle format).")
    sub = p.add_subparsers(dest="command", metavar="{simulate,inspect,scenes}")
    sub.required = True

    s = sub.add_parser("simulate", help="simulate a NAF scene from a built-in phantom or a CT volume")
    src = s.add_mutually_exclusive_group(required=True)
    src.add_argument("--phantom", metavar="NAME", help="built-in phantom (see `kneas-data scenes`)")
    src.add_argument("--volume", metavar="FILE", help="CT volume: .npy, .nii, .nii.gz or .mat")
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

    i = sub.add_parser("inspect", help="describe a scene pickle and draw a projection and slices")
    i.add_argument("scene", metavar="SCENE.pickle")
    i.add_argument("--png", default=None, metavar="OUT.png", help="write a figure of one projection and the middle slices")

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
    out = Path(args.output)
    if out.is_dir():
        raise ConfigError(f"-o {out} is a directory; give a file name such as {out / 'scene_50.pickle'}")
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


def _fmt(values) -> str:
    arr = np.atleast_1d(np.asarray(values, dtype=float))
    return "(" + ", ".join(f"{v:.4g}" for v in arr) + ")"


def _range(arr) -> str:
    return f"[{float(np.min(arr)):.4g}, {float(np.max(arr)):.4g}]"


def _inspect(args) -> int:
    from ..data.naf import load_naf

    scene = load_naf(args.scene)
    g = scene.geometry.to_mm()
    c = console
    c.print(f"[bold]{args.scene}[/]  (scene '{scene.name}', mode {g['mode']})")
    c.print(f"  DSD {g['DSD']:.6g} mm, DSO {g['DSO']:.6g} mm; model scale {scene.geometry.scale:.6g} units/m")
    c.print(f"  detector {tuple(scene.geometry.n_detector)} px (nU, nV) x {_fmt(g['dDetector'])} mm = {_fmt(g['sDetector'])} mm, offset {_fmt(g['offDetector'])} mm")
    c.print(f"  volume {tuple(scene.geometry.n_voxel)} x {_fmt(g['dVoxel'])} mm = {_fmt(g['sVoxel'])} mm, offset {_fmt(g['offOrigin'])} mm")
    near, far = scene.geometry.near_far
    c.print(f"  near/far {near * scene.geometry.mm_per_unit:.5g} / {far * scene.geometry.mm_per_unit:.5g} mm along the central ray")
    for label, views in (("train", scene.train), ("val", scene.val)):
        p = views.projections
        obj = float(np.mean(p > 0)) * 100
        c.print(
            f"  {label}: {len(views)} views {tuple(p.shape)}, angles {np.degrees(views.angles.min()):.2f}..{np.degrees(views.angles.max()):.2f} deg, "
            f"projections {_range(p)} ({obj:.1f} % object pixels)"
        )
    if scene.image is not None:
        c.print(f"  image {tuple(scene.image.shape)} {scene.image.dtype}, values {_range(scene.image)}")
    else:
        c.print("  image: none (no ground truth)")
    if scene.materials:
        c.print(f"  materials: {', '.join(f'{i + 1}={m}' for i, m in enumerate(scene.materials))}")
    skip = {"geometry_mm", "simulation"}
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
    args = _parser().parse_args(sys.argv[1:] if argv is None else argv)

    def body():
        if args.command == "simulate":
            return _simulate(args)
        if args.command == "inspect":
            return _inspect(args)
        return _scenes(args)

    run_cli(body)


if __name__ == "__main__":  # pragma: no cover
    main()
