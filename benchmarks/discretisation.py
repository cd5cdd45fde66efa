"""How much of a classical reconstruction's error is its projector's discretisation (not part of the test suite).

    python benchmarks/discretisation.py --scenes foot,jaw,chest,abdomen
    python benchmarks/discretisation.py --scenes foot --runs "asd-pocs:iterations=20" sart --out benchmarks/results/discretisation_cpu.json

The built-in scenes' projections are exact line integrals through the analytic phantom, and their
ground truth is each voxel's mean over that phantom; kneas's classical methods reconstruct with a
Joseph projector on the voxel grid, which does not give exactly those line integrals for that
volume. For each scene and run (``algorithm[:key=value,...]`` as in ``benchmarks/classical.py``) the
same reconstruction is made twice from the scene's training views: from its own projections, and
from the Joseph projections of its exact volume (data the projector itself would give). The psnr3d
difference is what the discretisation costs that method; ``data_rms`` / ``difference_rms`` are the
rms of the projections and of the two data sets' difference (line-integral units). Needs ground truth.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).resolve().parent


def main(argv=None) -> int:
    sys.path.insert(0, str(HERE))
    from classical import machine, parse_run
    from heldout import scene_from_spec

    from kneas_method.classical.options import ALGORITHMS, ReconstructionOptions
    from kneas_method.classical.projector import forward
    from kneas_method.classical.reconstruct import reconstruct
    from kneas_method.evaluation.metrics import psnr3d

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default="foot", help="comma-separated built-in names, NAF pickle paths or heldout:NAME")
    ap.add_argument("--runs", nargs="*", default=["asd-pocs"], help="runs 'algorithm[:key=value,...]' (default: asd-pocs)")
    ap.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    ap.add_argument("--out", default=None, help="JSON file to write (default: none)")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    runs = [parse_run(r) for r in args.runs]
    for name, _ in runs:
        if name not in ALGORITHMS:
            raise SystemExit(f"error: unknown algorithm {name!r}; choose from {', '.join(ALGORITHMS)}")

    rows = []
    print(f"{'scene':9s} {'run':28s} {'own data':>9s} {'joseph data':>12s} {'cost dB':>8s}")
    for spec in [s.strip() for s in args.scenes.split(",") if s.strip()]:
        scene = scene_from_spec(spec)
        if scene.image is None:
            raise SystemExit(f"error: scene {spec!r} has no ground-truth volume; this benchmark needs one")
        exact = np.asarray(scene.image, dtype=np.float32)
        own = np.asarray(scene.train.projections, dtype=np.float32)
        joseph = np.asarray(forward(exact, scene.geometry, scene.train.angles), dtype=np.float32)
        rms = {"data_rms": float(np.sqrt(np.mean(own.astype(np.float64) ** 2))),
               "difference_rms": float(np.sqrt(np.mean((own.astype(np.float64) - joseph) ** 2)))}
        consistent = dataclasses.replace(scene, train=dataclasses.replace(scene.train, projections=joseph))
        for name, kwargs in runs:
            options = ReconstructionOptions(**kwargs)
            scores = [psnr3d(np.clip(reconstruct(name, s, options).volume, 0.0, None), exact) for s in (scene, consistent)]
            row = {"scene": spec, "algorithm": name, "settings": kwargs, "psnr3d_own_data": round(scores[0], 4),
                   "psnr3d_joseph_data": round(scores[1], 4), "cost_db": round(scores[1] - scores[0], 4),
                   **rms}
            rows.append(row)
            label = name + (":" + ",".join(f"{k}={v}" for k, v in kwargs.items()) if kwargs else "")
            print(f"{spec:9s} {label:28s} {scores[0]:9.2f} {scores[1]:12.2f} {scores[1] - scores[0]:8.2f}", flush=True)
    if args.out:
        Path(args.out).write_text(json.dumps({"command": " ".join(sys.argv), "machine": machine(args.threads), "rows": rows},
                                             indent=1), encoding="utf-8")
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
