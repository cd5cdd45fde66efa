"""``benchmarks/error_anatomy.py``'s split of a volume's error by the interface it sits on."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from error_anatomy import edge_pairs  # noqa: E402


def _naive(error, labels, names):
    """Voxel by voxel: the lowest and highest label in each 3x3x3 neighbourhood (clipped at the border)."""
    nx, ny, nz = labels.shape
    sums: dict[tuple[int, int], list[float]] = {}
    for i in range(nx):
        for j in range(ny):
            for k in range(nz):
                block = labels[max(i - 1, 0):i + 2, max(j - 1, 0):j + 2, max(k - 1, 0):k + 2]
                lo, hi = int(block.min()), int(block.max())
                if lo != hi:
                    sums.setdefault((lo, hi), []).append(float(error[i, j, k]))
    name = lambda k: "air" if k == 0 else names[k - 1]
    return {f"{name(a)} | {name(b)}": (len(v), float(np.sum(np.square(v))), float(np.mean(v))) for (a, b), v in sums.items()}


def test_edge_pairs_match_the_voxel_by_voxel_split():
    rng = np.random.default_rng(0)
    labels = np.zeros((9, 8, 7), dtype=np.int64)
    labels[2:7, 2:6, 1:6] = 1
    labels[4:6, 3:5, 2:4] = 2          # a block of material 2 inside 1
    labels[3, 3:5, 4] = 3              # a thin shell of material 3, one voxel thick
    error = rng.normal(0.0, 0.01, labels.shape)
    error[3, 3:5, 4] += 0.2            # most of the error on the thin shell
    rows = edge_pairs(error, labels, ("soft", "bone", "shell"), top=20)
    naive = _naive(error, labels, ("soft", "bone", "shell"))
    total = float(np.sum(error ** 2))
    assert {r["pair"] for r in rows} == set(naive)
    for r in rows:
        n, sq, bias = naive[r["pair"]]
        assert r["voxels"] == n
        assert abs(r["error_share"] - sq / total) < 1e-3
        assert abs(r["bias"] - bias) < 1e-4
    shares = [r["error_share"] for r in rows]
    assert shares == sorted(shares, reverse=True)
    assert "shell" in rows[0]["pair"]  # the interface that holds the error comes first
    assert len(edge_pairs(error, labels, ("soft", "bone", "shell"), top=2)) == 2
