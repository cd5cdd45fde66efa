"""GPU check: the torch hash grid vs. the tiny-cuda-nn one (run on a CUDA machine with tinycudann).

    python benchmarks/check_tcnn.py [--points 65536] [--init-scale 1.0]

Prints both parameter counts. If the layouts match it copies the torch table into
tiny-cuda-nn (float32 params and float32 compute), and prints the max abs output
difference, the max abs difference of the input gradient and timings. If they do not
match (current tiny-cuda-nn releases: 12,132,352 vs the SPEC's 12,165,328 for the paper
config, because tcnn counts base_resolution in vertices and offsets coordinates by 0.5),
it says so and only times both. Exit status: 0 = outputs agree (or nothing to compare),
1 = outputs differ beyond tolerance, 2 = no CUDA / no tinycudann.
"""

from __future__ import annotations

import argparse
import sys
import time

import torch

from kneas_method.errors import ConfigError
from kneas_method.fields.hash_grid import (
    HashGridConfig,
    HashGridEncoding,
    TcnnHashGridEncoding,
    copy_torch_to_tcnn,
    tcnn_encoding_config,
)


def timed(fn, reps: int = 10) -> float:
    fn()
    torch.cuda.synchronize()
    t = time.perf_counter()
    for _ in range(reps):
        fn()
    torch.cuda.synchronize()
    return (time.perf_counter() - t) / reps * 1000


def step(enc, x0, eikonal: bool):
    def run():
        x = x0.clone().requires_grad_(eikonal)
        y = enc(x)
        loss = y.square().sum()
        if eikonal:
            (g,) = torch.autograd.grad(y.sum(), x, create_graph=True)
            loss = loss + ((g.norm(dim=-1) - 1) ** 2).mean()
        loss.backward()
    return run


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=65536)
    ap.add_argument("--init-scale", type=float, default=1.0, help="table init range for the comparison")
    ap.add_argument("--tol", type=float, default=1e-4)
    args = ap.parse_args()
    if not torch.cuda.is_available():
        print("no CUDA device: nothing to check")
        return 2
    try:
        import tinycudann as tcnn
    except ImportError:
        print("tinycudann is not installed: nothing to check")
        return 2
    print("torch", torch.__version__, "| tinycudann", getattr(tcnn, "__version__", "?"), "|", torch.cuda.get_device_name())
    cfg = HashGridConfig(implementation="torch", init_scale=args.init_scale)
    dev = torch.device("cuda")
    ref = HashGridEncoding(cfg).to(dev)
    raw = tcnn.Encoding(3, tcnn_encoding_config(cfg))
    print(f"parameters: torch layout {ref.layout.n_params:,} | tinycudann {raw.params.numel():,}")
    g = torch.Generator(device=dev).manual_seed(0)
    x = torch.rand(args.points, 3, device=dev, generator=g) * 2 - 1
    print(f"torch  fwd+bwd {timed(step(ref, x, False)):.2f} ms | with eikonal double-backward "
          f"{timed(step(ref, x, True)):.2f} ms  ({args.points} points)")
    try:
        fast = TcnnHashGridEncoding(cfg, dtype=torch.float32)
    except ConfigError as exc:
        print(f"layouts differ, no output comparison: {exc}")
        p = ((x + 1) / 2).contiguous()
        print(f"tcnn(raw, own layout) fwd+bwd {timed(lambda: raw(p).float().square().sum().backward()):.2f} ms")
        return 0
    copy_torch_to_tcnn(ref, fast)
    xg = x[:4096].clone().requires_grad_(True)
    xt = x[:4096].clone().requires_grad_(True)
    ya, yb = ref(xg), fast(xt)
    diff = (ya - yb).abs().max().item()
    (ga,) = torch.autograd.grad(ya.sum(), xg)
    (gb,) = torch.autograd.grad(yb.sum(), xt)
    gdiff = (ga - gb).abs().max().item()
    print(f"max |torch - tcnn| output {diff:.3e} (output scale {ya.abs().max().item():.3e}); d/dx {gdiff:.3e}")
    print(f"tcnn   fwd+bwd {timed(step(fast, x, False)):.2f} ms")
    try:
        print(f"tcnn   with eikonal double-backward {timed(step(fast, x, True)):.2f} ms")
    except Exception as exc:  # older tinycudann: no backward-of-backward for the grid
        print(f"tcnn   eikonal double-backward failed: {type(exc).__name__}: {exc}")
    ok = diff <= args.tol * max(1.0, ya.abs().max().item())
    print("AGREE" if ok else "DIFFER")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
