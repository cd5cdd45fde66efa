"""Does cross-validation on the projections pick an iterative method's iteration count? (Not part of the test suite.)

    python benchmarks/iteration_cv.py --scenes foot,jaw,chest,abdomen --iterations 5,10,20,40
    python benchmarks/iteration_cv.py --scenes /path/to/jaw-noisy.pickle --algorithm sart

Every ``--every``-th training view is held out; the algorithm reconstructs from the
others at each iteration count, and each volume is scored by its Joseph projection's
mean squared residual on the held-out views (what a user without ground truth can
compute) and, where the scene has one, by psnr3d against the ground truth. If the
held-out residual picked the count, its minimum would sit where psnr3d peaks.
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def main(argv=None) -> int:
    from kneas_method.classical.projector import forward
    from kneas_method.classical import iterative
    from kneas_method.data.scenes import resolve_scene
    from kneas_method.evaluation.metrics import psnr3d

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", default="foot", help="comma-separated built-in names or scene pickles")
    ap.add_argument("--algorithm", default="asd-pocs", choices=["asd-pocs", "sart", "os-sart", "cgls"])
    ap.add_argument("--iterations", default="5,10,20,40", help="comma-separated iteration counts")
    ap.add_argument("--every", type=int, default=10, help="hold out every N-th training view (default 10)")
    args = ap.parse_args(argv)
    run = {"asd-pocs": iterative.asd_pocs, "sart": iterative.sart, "os-sart": iterative.os_sart, "cgls": iterative.cgls}[args.algorithm]
    counts = [int(c) for c in args.iterations.split(",")]
    for spec in args.scenes.split(","):
        scene = resolve_scene(spec)
        p, a, geo = np.asarray(scene.train.projections), np.asarray(scene.train.angles), scene.geometry
        held = np.arange(len(a)) % args.every == args.every // 2
        gt = None if scene.image is None else np.asarray(scene.image, np.float32)
        for n in counts:
            t0 = time.perf_counter()
            x = np.asarray(run(p[~held], geo, a[~held], iterations=n))
            residual = float(np.mean((np.asarray(forward(x, geo, a[held])) - p[held]) ** 2))
            quality = "" if gt is None else f"  psnr3d {psnr3d(x, gt):.2f}"
            print(f"{spec:>10} {args.algorithm} {n:3d} iterations ({(~held).sum()} views): held-out residual {residual:.4e}"
                  f"{quality}  ({time.perf_counter() - t0:.0f} s)", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
