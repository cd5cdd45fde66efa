"""3D PSNR against wall time, fast vs reference training path (not part of the test suite).

    python benchmarks/quality.py                       # cpu preset, built-in foot, k-neas K = 3
    python benchmarks/quality.py --steps 400 --eval-every 100 --out benchmarks/results/quality_cpu.json

Drives ``CTModel`` + ``CTDataManager`` directly with a minimal loop (Adam,
lr 1e-3, the floater loss over the first 20 % of the steps), the same batches
and the same loss-sampling generator for both paths, and steps them
**interleaved** (one reference step, one fast step, ...) so machine load hits
both alike. Only training steps are timed; evaluation is not.

- reference: ``benchmarks/naive.py``'s straightforward model (per-level hash-grid loop,
  K double-backward eikonal passes) and ``torch.optim.Adam`` (default update);
- fast: the default path (forward-mode eikonal gradients) and fused Adam; its
  eikonal mode / fraction can be changed (``--fast-eikonal-mode``,
  ``--fast-eikonal-fraction``) to measure what an approximation costs in quality.

Bounds: a fixed choice so that both paths train the same model: the paper's GMM
procedure (SPEC §4, ``bounds.GMMBounds`` with K = 3) fitted to the ground-truth
volume's values ("oracle" bounds: this benchmark measures the speed/quality of
the training step, not the bound estimation, which the full pipeline does from
the prior model).

3D PSNR: SPEC §5 primary figure (data units, peak 1, no fitting) on the voxel
centres, every ``--eval-stride``-th voxel per axis (1 = all).

Writes JSON (``--out``, default ``benchmarks/results/quality_<preset>.json``):
per path the curve ``[(step, train_wall_s, psnr3d)]``, and the summary at equal
steps and at equal wall time (each path's PSNR at the time the fast path needed
for all steps, interpolated along the slower path's curve).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).resolve().parent


def oracle_bounds(scene, K: int):
    from kneas_method.bounds import GMMBounds

    est = GMMBounds(n_components=K, random_state=0).fit(np.asarray(scene.image).reshape(-1))
    return [float(a) for a in est.alphas_], [float(b) for b in est.betas_]


@torch.no_grad()
def psnr3d_of(model, scene, stride: int, chunk: int = 1 << 16) -> float:
    from kneas_method.evaluation.metrics import psnr3d

    was = model.training
    model.eval()
    pts = scene.geometry.voxel_centres()[::stride, ::stride, ::stride]
    shape = pts.shape[:3]
    flat = pts.reshape(-1, 3)
    mu = torch.cat([model.query(flat[i : i + chunk])["mu"] for i in range(0, len(flat), chunk)])
    model.train(was)
    gt = np.asarray(scene.image)[::stride, ::stride, ::stride]
    return float(psnr3d(mu.reshape(shape).numpy(), gt))


def main(argv=None) -> int:
    from kneas_method import methods, presets
    from kneas_method.data.scenes import builtin_scene

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--preset", default="cpu", choices=["cpu", "paper", "tiny"])
    ap.add_argument("--scene", default="foot")
    ap.add_argument("--materials", type=int, default=3)
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--eval-every", type=int, default=100)
    ap.add_argument("--eval-stride", type=int, default=2, help="evaluate every n-th voxel per axis (1 = all)")
    ap.add_argument("--fast-eikonal-mode", default=None, choices=[None, "autograd", "finite-difference"])
    ap.add_argument("--fast-eikonal-fraction", type=float, default=None)
    ap.add_argument("--no-reference", action="store_true", help="train the fast path only")
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)

    scene = builtin_scene(args.scene)
    cfg = presets.resolve(dataclasses.replace(methods.k_neas.config, preset=args.preset, num_materials=args.materials))
    alphas, betas = oracle_bounds(scene, args.materials)
    base = dataclasses.replace(cfg.model, alphas=tuple(alphas), betas=tuple(betas))
    base = dataclasses.replace(base, encoding_options={**base.encoding_options, "implementation": "torch"})
    fast_cfg = dataclasses.replace(
        base,
        eikonal_mode=args.fast_eikonal_mode or base.eikonal_mode,
        eikonal_fraction=args.fast_eikonal_fraction if args.fast_eikonal_fraction is not None else base.eikonal_fraction,
    )
    paths = {"fast": fast_cfg} if args.no_reference else {"reference": base, "fast": fast_cfg}

    runs = {}
    for name, mc in paths.items():
        torch.manual_seed(args.seed)
        model = mc.setup(scale=scene.geometry.scale)
        if name == "reference":
            from naive import make_reference

            make_reference(model)
        model.train()
        opt = (torch.optim.Adam(model.parameters(), lr=1e-3) if name == "reference"
               else torch.optim.Adam(model.parameters(), lr=1e-3, fused=True))
        dm = cfg.datamanager.setup(scene=scene, device="cpu", seed=args.seed)
        gen = torch.Generator().manual_seed(args.seed + 7919)
        runs[name] = {"model": model, "opt": opt, "dm": dm, "gen": gen, "wall": 0.0,
                      "curve": [[0, 0.0, psnr3d_of(model, scene, args.eval_stride)]]}

    for step in range(1, args.steps + 1):
        for name, r in runs.items():  # interleaved
            batch = r["dm"].next_train()
            t0 = time.perf_counter()
            losses = r["model"].loss_dict(batch, (step - 1) / args.steps, generator=r["gen"])
            r["opt"].zero_grad(set_to_none=True)
            losses["total"].backward()
            r["opt"].step()
            r["wall"] += time.perf_counter() - t0
            r["last_loss"] = {k: float(v.detach()) for k, v in losses.items()}
        if step % args.eval_every == 0 or step == args.steps:
            for name, r in runs.items():
                r["curve"].append([step, r["wall"], psnr3d_of(r["model"], scene, args.eval_stride)])
            print(f"step {step}: " + "  ".join(f"{n}: {r['wall']:.0f} s, PSNR3D {r['curve'][-1][2]:.2f} dB" for n, r in runs.items()),
                  flush=True)

    def at_time(curve, t):
        steps, walls, ps = zip(*curve)
        return float(np.interp(t, walls, ps))

    result = {
        "benchmark": "quality", "scene": args.scene, "preset": args.preset, "materials": args.materials,
        "steps": args.steps, "eval_stride": args.eval_stride, "bounds": {"alphas": alphas, "betas": betas, "source": "GMM of the ground-truth volume"},
        "fast_options": {"eikonal_mode": fast_cfg.eikonal_mode or "autograd", "eikonal_fraction": fast_cfg.eikonal_fraction},
        "reference_options": {"eikonal_fraction": base.eikonal_fraction},
        "resolved": {"encoding_options": dict(base.encoding_options), "num_samples": base.num_samples,
                     "num_object_rays": cfg.datamanager.num_object_rays, "num_air_rays": cfg.datamanager.num_air_rays},
        "machine": {"platform": platform.platform(), "cpu_count": os.cpu_count(), "torch_threads": torch.get_num_threads(),
                    "torch": torch.__version__, "load_avg_1m_at_end": os.getloadavg()[0]},
        "curves": {n: r["curve"] for n, r in runs.items()},
        "final_losses": {n: r["last_loss"] for n, r in runs.items()},
        "train_wall_s": {n: r["wall"] for n, r in runs.items()},
    }
    if "reference" in runs:
        f, ref = runs["fast"], runs["reference"]
        t_fast = f["wall"]
        result["equal_steps"] = {"steps": args.steps, "psnr3d_fast": f["curve"][-1][2], "psnr3d_reference": ref["curve"][-1][2]}
        result["equal_wall_time"] = {"wall_s": t_fast, "psnr3d_fast": f["curve"][-1][2],
                                     "psnr3d_reference": at_time(ref["curve"], t_fast),
                                     "note": "reference PSNR interpolated along its eval curve at the fast path's training time"}
        result["speedup_train_wall"] = ref["wall"] / t_fast
        print(f"equal steps ({args.steps}): fast {f['curve'][-1][2]:.2f} dB, reference {ref['curve'][-1][2]:.2f} dB")
        print(f"equal wall time ({t_fast:.0f} s): fast {f['curve'][-1][2]:.2f} dB, reference {at_time(ref['curve'], t_fast):.2f} dB")
        print(f"training wall time: reference {ref['wall']:.0f} s, fast {t_fast:.0f} s ({ref['wall'] / t_fast:.2f}x)")
    print(f"load average (1 min) at end: {os.getloadavg()[0]:.2f}")
    out = Path(args.out) if args.out else HERE / "results" / f"quality_{args.preset}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2), encoding="utf-8")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
