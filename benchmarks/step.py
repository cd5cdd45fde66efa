"""Time one full training step of the paper architecture (not part of the test suite).

    python benchmarks/step.py --rays 256 --samples 64 --materials 3 --device cpu
    python benchmarks/step.py --rays 256 --samples 64 --materials 3 --device cpu --reference
    python benchmarks/step.py --rays 256 --samples 64 --materials 3 --device cpu --compare

One step = what the trainer does per training projection: draw a batch (done up
front here, from the built-in foot scene, so only the model is timed), render
``rays`` object rays + ``rays // 4`` air rays (the paper's 512 : 128) with
``samples`` stratified points each, the losses of k-neas (intensity + floater +
exact eikonal on every sample, SPEC §3), ``backward``, and an Adam step with
``zero_grad``. Architecture: the paper's hash grid (14 levels x 2 features,
2^19 entries, 12.2 M parameters), SDF MLP, shared attenuation body with K heads,
soft selector (``--materials K``). ``--preset cpu`` times the cpu preset's
smaller grid and eikonal fraction instead. ``--anchor-points 4096`` adds the cpu
preset's anchor term (the field queried at that many more points per step, as
``stages.anchor.Anchor.loss``), which the preset's training pays at every step:

    python benchmarks/step.py --preset cpu --rays 128 --samples 64 --materials 3 --anchor-points 4096

Paths:

- default (fast): vectorised hash grid; the K distance gradients in forward mode
  from the render's own pass (``SDFField.forward_with_gradients``: no double
  backward); masked eikonal mean without boolean indexing; fused Adam (``--optimizer``).
- ``--reference`` (the straightforward implementation, ``benchmarks/naive.py``):
  the hash grid as a per-level Python loop with 8 gathers per level; the eikonal by
  K separate ``autograd.grad(d_k.sum(), x, create_graph=True)`` double backwards on
  every sample; ``torch.optim.Adam`` with its default (single-tensor, dense) update.
- ``--reference --reference-grid vectorised``: as ``--reference`` but with the
  vectorised hash grid, i.e. exactly the repository's training step before the
  speed work (the stricter baseline).
- ``--compare``: both models in one process, steps interleaved (ref, fast, ref, ...),
  so machine load hits both alike; prints both medians and the speed-up.

Prints ``step_ms: X`` (median over ``--repeats`` after ``--warmup``) and
``samples_per_s: Y`` and writes JSON (``--out``, default
``benchmarks/results/step_<device>[_reference|_compare].json``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import torch

HERE = Path(__file__).resolve().parent


def build(args, mode: str, device: torch.device):
    """``mode``: ``fast``, ``reference`` (loop grid) or ``reference-vectorised-grid``."""
    reference = not mode.startswith("fast")
    eik_mode, eik_fraction = args.eikonal_mode, args.eikonal_fraction
    if mode.startswith("fast:"):  # a --variants entry "fast:<eikonal mode>:<fraction>"
        _, eik_mode, frac = mode.split(":")
        eik_fraction = float(frac)
    from kneas_method import methods, presets

    cfg = dataclasses.replace(methods.k_neas.config, preset=args.preset, num_materials=args.materials)
    cfg = presets.resolve(cfg)
    preset_fraction = float(cfg.model.eikonal_fraction if cfg.model.eikonal_fraction is not None else 1.0)
    fraction = preset_fraction if (reference or eik_fraction is None) else eik_fraction
    enc = dict(cfg.model.encoding_options)
    enc["implementation"] = "tcnn" if args.tcnn and not reference else "torch"
    model_cfg = dataclasses.replace(
        cfg.model, num_samples=args.samples, encoding_options=enc,
        eikonal_mode="autograd" if reference else eik_mode, eikonal_fraction=fraction, compile=args.compile and not reference,
    )
    torch.manual_seed(args.seed)
    model = model_cfg.setup(scale=args.scale, device=device).to(device)
    if reference:  # the straightforward implementation (benchmarks/naive.py); "vectorised": the code before the speed work
        from naive import make_reference

        make_reference(model, grid="vectorised" if mode == "reference-vectorised-grid" else "loop")
    model.train()
    if reference or args.optimizer == "adam":
        opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    elif args.optimizer == "adam-fused":
        opt = torch.optim.Adam(model.parameters(), lr=1e-3, fused=True)
    elif args.optimizer == "adam-foreach":
        opt = torch.optim.Adam(model.parameters(), lr=1e-3, foreach=True)
    else:
        raise SystemExit(f"unknown --optimizer {args.optimizer}")
    return model, opt


def batches(args, device: torch.device, n: int = 8):
    """``n`` training batches of the built-in foot scene (rays object + rays//4 air)."""
    from kneas_method.data.scenes import builtin_scene
    from kneas_method.datamanagers.ct import CTDataManagerConfig

    scene = builtin_scene("foot")
    dm = CTDataManagerConfig(num_object_rays=args.rays, num_air_rays=max(1, args.rays // 4)).setup(scene=scene, device=device, seed=args.seed)
    return [dm.next_train() for _ in range(n)], float(scene.geometry.scale)


def anchor_term(model, anchor_points: int, generator) -> torch.Tensor:
    """What the trainer's anchor adds to a step (``stages.anchor.Anchor.loss``): the field queried at
    ``anchor_points`` random points of the box, an MSE and the label cross-entropy against
    targets (here random, the cost is the same), weight 0.01."""
    device = next(model.parameters()).device
    points = (torch.rand(anchor_points, 3, generator=generator) * 2 - 1).mul(0.9 * model.bound).to(device)
    targets = (torch.rand(anchor_points, generator=generator) * 0.02).to(device)
    q = model.query(points)
    loss = torch.mean((q["mu"] - targets) ** 2)
    if "distances" in q:
        loss = loss + 0.03 * model.occupancy_loss(q["distances"], targets)
    return 0.01 * loss


def step(model, opt, batch, generator, progress: float = 0.0, anchor_points: int = 0) -> float:
    losses = model.loss_dict(batch, progress, generator=generator)
    if anchor_points:
        losses["total"] = losses["total"] + anchor_term(model, anchor_points, generator)
    opt.zero_grad(set_to_none=True)
    losses["total"].backward()
    opt.step()
    return losses["total"]


def sync(device):
    if device.type == "cuda":
        torch.cuda.synchronize()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rays", type=int, default=256, help="object rays per step (plus rays//4 air rays)")
    ap.add_argument("--samples", type=int, default=64, help="samples per ray")
    ap.add_argument("--materials", type=int, default=3, help="K")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--reference", action="store_true", help="time the straightforward implementation")
    ap.add_argument("--compare", action="store_true", help="time reference and fast interleaved in one process")
    ap.add_argument("--reference-grid", default="loop", choices=["loop", "vectorised", "both"],
                    help="hash grid of the reference: the per-level loop (default) or the vectorised one "
                         "(= the repository's code before the speed work); 'both' with --compare times all three")
    ap.add_argument("--eikonal-mode", default="autograd", choices=["autograd", "finite-difference"],
                    help="fast path: exact (forward-mode gradients) or finite differences")
    ap.add_argument("--preset", default="paper", choices=["paper", "cpu"],
                    help="architecture + eikonal fraction: paper (14-level 2^19 grid, eikonal on every sample) or the cpu preset's")
    ap.add_argument("--eikonal-fraction", type=float, default=None,
                    help="fast path: fraction of samples with the eikonal term (default: the preset's; the reference always uses the preset's)")
    ap.add_argument("--variants", default=None,
                    help="extra fast-path variants timed interleaved with the others, e.g. "
                         "'autograd:1.0,finite-difference:0.25' (eikonal mode:fraction)")
    ap.add_argument("--optimizer", default="adam-fused", choices=["adam", "adam-fused", "adam-foreach"], help="fast path optimiser")
    ap.add_argument("--tcnn", action="store_true", help="fast path: tinycudann hash grid (CUDA; needs --eikonal-mode finite-difference)")
    ap.add_argument("--compile", action="store_true", help="fast path: torch.compile the fused SDF pass (opt-in; minutes to compile)")
    ap.add_argument("--threads", type=int, default=None, help="torch.set_num_threads")
    ap.add_argument("--anchor-points", type=int, default=0,
                    help="add the trainer's anchor term on this many points per step (the cpu preset's: 4096; default 0, none)")
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    data, args.scale = batches(args, device)
    n_rays = len(data[0]["origins"])
    samples_per_step = n_rays * args.samples

    ref = "reference-vectorised-grid" if args.reference_grid == "vectorised" else "reference"
    if args.compare:
        modes = (["reference", "reference-vectorised-grid"] if args.reference_grid == "both" else [ref]) + ["fast"]
    else:
        modes = [ref] if args.reference else ["fast"]
    if args.variants:
        modes += [f"fast:{v}" for v in args.variants.split(",")]
    runs = {m: build(args, m, device) for m in modes}
    any_model = runs[modes[-1]][0]
    gens = {m: torch.Generator().manual_seed(args.seed + 1) for m in modes}
    times: dict[str, list[float]] = {m: [] for m in modes}
    for i in range(args.warmup + args.repeats):
        for m in modes:  # interleaved
            model, opt = runs[m]
            sync(device)
            t0 = time.perf_counter()
            step(model, opt, data[i % len(data)], gens[m], anchor_points=args.anchor_points)
            sync(device)
            if i >= args.warmup:
                times[m].append(time.perf_counter() - t0)

    result = {
        "benchmark": "step",
        "preset": args.preset, "rays": args.rays, "air_rays": n_rays - args.rays, "samples": args.samples, "materials": args.materials,
        "samples_per_step": samples_per_step, "device": str(device),
        "machine": {"platform": platform.platform(), "processor": platform.processor(), "cpu_count": os.cpu_count(),
                    "torch_threads": torch.get_num_threads(), "torch": torch.__version__,
                    "gpu": torch.cuda.get_device_name(0) if device.type == "cuda" else None,
                    "load_avg_1m": os.getloadavg()[0]},
        "anchor_points": args.anchor_points,
        "fast_options": {"eikonal_mode": args.eikonal_mode, "eikonal_fraction": args.eikonal_fraction,
                         "optimizer": args.optimizer, "tcnn": args.tcnn, "compile": args.compile},
        "warmup": args.warmup, "repeats": args.repeats,
        "encoding_options": dict(any_model.config.encoding_options), "parameters": any_model.num_parameters(),
        "eikonal_fraction_by_mode": {m: runs[m][0].config.eikonal_fraction for m in modes},
    }
    for m in modes:
        med = statistics.median(times[m])
        result[m] = {"step_ms": 1e3 * med, "samples_per_s": samples_per_step / med, "all_ms": [1e3 * t for t in times[m]]}
        print(f"{m}: step_ms: {1e3 * med:.1f}  samples_per_s: {samples_per_step / med:.0f}")
    if args.compare or args.variants:
        for m in [m for m in modes if m != "fast"]:
            result[f"fast_speedup_vs_{m}"] = result[m]["step_ms"] / result["fast"]["step_ms"]
            print(f"fast speedup vs {m}: {result[f'fast_speedup_vs_{m}']:.2f}x")
    else:
        print(f"step_ms: {result[modes[0]]['step_ms']:.1f}")
        print(f"samples_per_s: {result[modes[0]]['samples_per_s']:.0f}")
    print(f"load average (1 min) at end: {os.getloadavg()[0]:.2f}; torch threads {torch.get_num_threads()}")
    suffix = "_compare" if args.compare else ("_reference" if args.reference else "")
    tag = "" if args.preset == "paper" else f"_{args.preset}"
    out = Path(args.out) if args.out else HERE / "results" / f"step_{device.type}{tag}{suffix}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2), encoding="utf-8")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
