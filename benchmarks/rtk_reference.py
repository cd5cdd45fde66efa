"""RTK's reconstructions of a kneas scene, as reference figures and a geometry cross-check (not part of the test suite).

    python benchmarks/rtk_reference.py                      # built-in foot
    python benchmarks/rtk_reference.py --scene my_scene.pickle --threads 2

The scene's training views go to RTK through kneas's own exporter
(``kneas-data export --rtk``: projections ``.mha`` + RTK geometry XML, read back
with RTK's XML reader), RTK (``itk-rtk``, CPU) reconstructs them on the scene's
voxel grid placed in RTK's world by the same frame map, and the result comes
back to kneas's array order through the inverse map. So if RTK gets good figures
on the converted data, the RTK <-> kneas mapping is right; a mirrored or shifted
geometry would give a blurred or displaced volume and poor figures.

Methods (RTK's defaults otherwise, as its command-line tools):

* ``fdk``: ``rtk.FDKConeBeamReconstructionFilter`` (Ram-Lak), after
  ``rtk.DisplacedDetectorImageFilter`` (an offset, half-fan detector's weights, as ``rtkfdk``) and
  ``rtk.ParkerShortScanImageFilter`` when the scan is shorter than 360°
  (the NAF scenes cover 180°, less than a short scan: limited-angle artefacts);
* ``sart``: ``rtk.SARTConeBeamReconstructionFilter``, 5 iterations, λ 0.5,
  positivity, Joseph forward projector, voxel-based back projector (rtksart's default);
* ``os-sart``: the same filter with 5 projections per subset (10 subsets of 50 views), 10
  iterations, λ 1 (kneas's os-sart defaults);
* ``cg``: ``rtk.ConjugateGradientConeBeamReconstructionFilter`` (CGLS on the
  normal equations, unit weights, no regularisation), 30 iterations.

Units: RTK reconstructs line integrals given with mm geometry in 1/mm; the
volumes are multiplied by 1000 to kneas data units (1/m) before the metrics
(``kneas_method.evaluation.metrics.volume_metrics`` against ``scene.image``:
SPEC §5 primary psnr3d/ssim3d, plus the least-squares-rescaled variant).
Wall time: the reconstruction filter's ``Update()`` only (no file IO).

Writes JSON to ``--out`` (default ``benchmarks/results/rtk_reference_<scene>.json``).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent


def _rtk():
    try:
        import itk
        from itk import RTK as rtk
    except ImportError:
        sys.exit("this benchmark needs itk-rtk: pip install itk-rtk (it is part of kneas's dev extra)")
    return itk, rtk


def read_geometry(rtk, path):
    reader = rtk.ThreeDCircularProjectionGeometryXMLFileReader.New()
    reader.SetFilename(str(path))
    reader.GenerateOutputInformation()
    return reader.GetOutputObject()


def volume_source(itk, rtk, grid):
    F3 = itk.Image[itk.F, 3]
    src = rtk.ConstantImageSource[F3].New()
    src.SetOrigin([float(v) for v in grid["origin_mm"]])
    src.SetSpacing([float(v) for v in grid["spacing_mm"]])
    src.SetSize([int(v) for v in grid["size"]])
    src.SetConstant(0.0)
    return src


def run_fdk(itk, rtk, projections, geometry, grid, short_scan: bool):
    F3 = itk.Image[itk.F, 3]
    src = volume_source(itk, rtk, grid)
    t0 = time.perf_counter()
    proj = projections
    displaced = rtk.DisplacedDetectorImageFilter[F3].New()  # as rtkfdk: a half-fan detector's weights (none on a centred one)
    displaced.InPlaceOff()
    displaced.SetInput(proj)
    displaced.SetGeometry(geometry)
    displaced.Update()
    proj = displaced.GetOutput()
    if short_scan:
        parker = rtk.ParkerShortScanImageFilter[F3].New()
        parker.InPlaceOff()  # in place it would take over the shared projections' buffer
        parker.SetInput(proj)
        parker.SetGeometry(geometry)
        parker.Update()
        proj = parker.GetOutput()
    fdk = rtk.FDKConeBeamReconstructionFilter[F3].New()
    fdk.SetInput(0, src.GetOutput())
    fdk.SetInput(1, proj)
    fdk.SetGeometry(geometry)
    fdk.Update()
    return fdk.GetOutput(), time.perf_counter() - t0


def run_sart(itk, rtk, projections, geometry, grid, iterations=5, lam=0.5, back="voxel", per_subset=1):
    F3 = itk.Image[itk.F, 3]
    src = volume_source(itk, rtk, grid)
    src.Update()
    sart = rtk.SARTConeBeamReconstructionFilter[F3, F3].New()
    sart.SetInput(src.GetOutput())
    sart.SetInput(1, projections)
    sart.SetGeometry(geometry)
    sart.SetNumberOfIterations(iterations)
    sart.SetLambda(lam)
    sart.SetEnforcePositivity(True)
    sart.SetNumberOfProjectionsPerSubset(per_subset)  # > 1: OS-SART
    kind = type(sart)
    sart.SetForwardProjectionFilter(kind.ForwardProjectionType_FP_JOSEPH)
    sart.SetBackProjectionFilter(kind.BackProjectionType_BP_JOSEPH if back == "joseph" else kind.BackProjectionType_BP_VOXELBASED)
    t0 = time.perf_counter()
    sart.Update()
    return sart.GetOutput(), time.perf_counter() - t0


def run_cg(itk, rtk, projections, geometry, grid, iterations=30):
    F3 = itk.Image[itk.F, 3]
    src = volume_source(itk, rtk, grid)
    src.Update()
    weights = rtk.ConstantImageSource[F3].New()
    weights.SetInformationFromImage(projections)
    weights.SetConstant(1.0)
    weights.Update()
    cg = rtk.ConjugateGradientConeBeamReconstructionFilter[F3].New()
    cg.SetInput(src.GetOutput())
    cg.SetInput(1, projections)
    cg.SetInput(2, weights.GetOutput())
    cg.SetGeometry(geometry)
    cg.SetNumberOfIterations(iterations)
    kind = type(cg)
    cg.SetForwardProjectionFilter(kind.ForwardProjectionType_FP_JOSEPH)
    cg.SetBackProjectionFilter(kind.BackProjectionType_BP_VOXELBASED)
    t0 = time.perf_counter()
    cg.Update()
    return cg.GetOutput(), time.perf_counter() - t0


def to_kneas(itk, image, vgrid) -> np.ndarray:
    """RTK's world image (ITK order [w2, w1, w0], 1/mm) -> kneas's volume [nx, ny, nz] in 1/m."""
    from kneas_method.data.rtk_geometry import world_array_to_volume

    arr_w = np.transpose(itk.array_from_image(image), (2, 1, 0))
    return world_array_to_volume(arr_w, vgrid).astype(np.float32) * 1000.0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", default="foot", help="built-in scene name or NAF pickle (default foot)")
    p.add_argument("--data-dir", default="data", help="where public benchmark pickles are looked for")
    p.add_argument("--methods", default="fdk,sart,os-sart,cg", help="comma-separated subset of fdk,sart,os-sart,cg")
    p.add_argument("--os-sart-subsets", type=int, default=10, help="OS-SART subsets (kneas's default 10), 10 iterations, lambda 1")
    p.add_argument("--sart-iterations", type=int, default=5)
    p.add_argument("--sart-lambda", type=float, default=0.5)
    p.add_argument("--sart-bp", choices=("voxel", "joseph"), default="voxel", help="SART back projector (default voxel-based, as rtksart)")
    p.add_argument("--cg-iterations", type=int, default=30)
    p.add_argument("--threads", type=int, default=None, help="ITK threads (default: ITK's choice)")
    p.add_argument("--keep", default=None, metavar="DIR", help="keep the exported RTK files and volumes in DIR")
    p.add_argument("--out", default=None, help="JSON output (default benchmarks/results/rtk_reference_<scene>.json)")
    args = p.parse_args(argv)

    itk, rtk = _rtk()
    if args.threads:
        itk.MultiThreaderBase.SetGlobalDefaultNumberOfThreads(int(args.threads))
    from kneas_method.data.rtk_export import export_rtk, scene_world_affine
    from kneas_method.data.rtk_geometry import world_grid_of
    from kneas_method.data.scenes import resolve_scene
    from kneas_method.classical.fdk import fdk_reconstruct
    from kneas_method.evaluation.metrics import volume_metrics

    scene = resolve_scene(args.scene, data_dir=args.data_dir)
    if scene.image is None:
        sys.exit(f"scene {scene.name} has no ground-truth image; RTK's figures need one")
    workdir = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="kneas-rtk-"))
    info = export_rtk(scene, workdir)
    geometry = read_geometry(rtk, info["files"]["geometry"])
    projections = itk.imread(info["files"]["projections"], itk.F)
    grid = info["volume_grid_lps"]
    vgrid = world_grid_of(scene.geometry, scene_world_affine(scene))
    angles = np.sort(np.mod(scene.train.angles, 2 * math.pi))
    gaps = np.diff(np.concatenate([angles, [angles[0] + 2 * math.pi]]))
    step = float(np.median(gaps))  # the angular spacing of the views
    short_scan = bool(np.max(gaps) > 2.5 * step)
    g_mm = scene.geometry.to_mm()
    half_fan = math.degrees(math.atan((0.5 * g_mm["sDetector"][0] + abs(g_mm["offDetector"][0])) / g_mm["DSD"]))
    arc = math.degrees(2 * math.pi - float(np.max(gaps)) + step)
    notes = []
    if short_scan and arc < 180.0 + 2 * half_fan:
        notes.append(f"the scan covers about {arc:.0f} deg, less than a short scan (180 + 2 x {half_fan:.1f} deg fan): RTK's "
                     "Parker weights do not apply (RTK's FDK weights the end views by the wrap-around gap), so RTK's FDK "
                     "figure shows limited-angle weighting artefacts, not a geometry error; kneas's FDK keeps weight 1 on "
                     "lines measured once")
    print(f"scene {scene.name}: {len(scene.train)} training views, volume {tuple(scene.geometry.n_voxel)}, "
          f"RTK files in {workdir}")

    results: dict = {}
    t0 = time.perf_counter()
    vol = fdk_reconstruct(scene)
    results["kneas_fdk"] = {**volume_metrics(vol, scene.image), "wall_s": round(time.perf_counter() - t0, 3),
                            "settings": "kneas_method.classical.fdk, Ram-Lak, redundancy weights"}
    print(f"  kneas FDK: psnr3d {results['kneas_fdk']['psnr3d']:.2f} dB in {results['kneas_fdk']['wall_s']:.1f} s")
    for method in [m.strip() for m in args.methods.split(",") if m.strip()]:
        if method == "fdk":
            image, wall = run_fdk(itk, rtk, projections, geometry, grid, short_scan)
            settings = "DisplacedDetectorImageFilter, " + ("ParkerShortScanImageFilter, " if short_scan else "") + \
                "FDKConeBeamReconstructionFilter, Ram-Lak"
        elif method == "sart":
            image, wall = run_sart(itk, rtk, projections, geometry, grid, args.sart_iterations, args.sart_lambda, args.sart_bp)
            settings = (f"SARTConeBeamReconstructionFilter, {args.sart_iterations} iterations, lambda {args.sart_lambda}, "
                        f"positivity, Joseph forward, {'Joseph' if args.sart_bp == 'joseph' else 'voxel-based'} back projection")
        elif method == "os-sart":
            per = max(1, len(scene.train) // args.os_sart_subsets)
            image, wall = run_sart(itk, rtk, projections, geometry, grid, 10, 1.0, "voxel", per_subset=per)
            settings = (f"SARTConeBeamReconstructionFilter, {per} projections per subset (OS-SART), 10 iterations, lambda 1, "
                        "positivity, Joseph forward, voxel-based back projection")
        elif method == "cg":
            image, wall = run_cg(itk, rtk, projections, geometry, grid, args.cg_iterations)
            settings = f"ConjugateGradientConeBeamReconstructionFilter, {args.cg_iterations} iterations, unit weights, no regularisation"
        else:
            sys.exit(f"unknown method {method!r}; use fdk, sart, os-sart, cg")
        vol = to_kneas(itk, image, vgrid)
        if args.keep:
            itk.imwrite(image, str(workdir / f"rtk_{method}.mha"))
        key = f"rtk_{method}"
        results[key] = {**volume_metrics(vol, scene.image), "wall_s": round(wall, 3), "settings": settings}
        print(f"  RTK {method}: psnr3d {results[key]['psnr3d']:.2f} dB, ssim3d {results[key]['ssim3d']:.4f} in {wall:.1f} s")

    out = Path(args.out) if args.out else HERE / "results" / f"rtk_reference_{scene.name}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    payload = {
        "benchmark": "rtk_reference",
        "scene": scene.name,
        "scene_source": scene.source,
        "views": len(scene.train),
        "volume": list(scene.geometry.n_voxel),
        "short_scan": short_scan,
        "notes": notes,
        "path": "kneas scene -> kneas-data export --rtk (projections.mha + geometry.xml) -> RTK's XML reader -> RTK -> "
                "inverse frame map -> kneas array; RTK's 1/mm x 1000 = kneas 1/m",
        "results": results,
        "machine": {"platform": platform.platform(), "cpu_count": os.cpu_count(), "python": platform.python_version(),
                    "itk": getattr(itk, "__version__", "?"),
                    "itk_threads": int(itk.MultiThreaderBase.GetGlobalDefaultNumberOfThreads()),
                    "load_average_at_end": [round(v, 2) for v in os.getloadavg()]},
    }
    out.write_text(json.dumps(payload, indent=2), encoding="utf-8")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
