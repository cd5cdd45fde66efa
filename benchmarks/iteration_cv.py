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
import dataclasses

import numpy as np


def main(argv=None) -> int:
    from kneas_method.classical.options import ALGORITHMS, ReconstructionOptions
    from kneas_method.classical.reconstruct import reconstruct
    from kneas_method.classical.projector import forward
    from kneas_method.data.scenes import resolve_scene
    from kneas_method.evaluation.metrics import psnr3d

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", default="foot", help="comma-separated built-in names or scene pickles")
    ap.add_argument("--algorithm", default="asd-pocs", choices=[a for a in ALGORITHMS if a != "fdk"])
    ap.add_argument("--iterations", default="5,10,20,40", help="comma-separated iteration counts")
    ap.add_argument("--every", type=int, default=10, help="hold out every N-th training view (default 10)")
    args = ap.parse_args(argv)
    counts = [int(c) for c in args.iterations.split(",")]
    for spec in args.scenes.split(","):
        scene = resolve_scene(spec)
        p, a, geo = np.asarray(scene.train.projections), np.asarray(scene.train.angles), scene.geometry
        held = np.arange(len(a)) % args.every == args.every // 2
        fit = dataclasses.replace(scene, train=scene.train.subset(np.flatnonzero(~held)))
        gt = None if scene.image is None else np.asarray(scene.image, np.float32)
        for n in counts:
            rec = reconstruct(args.algorithm, fit, ReconstructionOptions(iterations=n))
            x = rec.volume
            residual = float(np.mean((np.asarray(forward(x, geo, a[held])) - p[held]) ** 2))
            quality = "" if gt is None else f"  psnr3d {psnr3d(x, gt):.2f}"
            print(f"{spec:>10} {args.algorithm} {n:3d} iterations ({(~held).sum()} views): held-out residual {residual:.4e}"
                  f"{quality}  ({rec.seconds:.0f} s)", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
