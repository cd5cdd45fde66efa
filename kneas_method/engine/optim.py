"""The optimiser every fit of a run uses: Adam, fused where torch has it for the device.

torch's default Adam makes several passes over each parameter tensor a step; the fused one makes one.
With the cpu preset's 2^19-entry hash table that is 22.5 ms against 2.6 ms a step on 2 cores
(docs/experiments.md, "A 2^19 hash table with a fused Adam"), the same update up to rounding.
"""

from __future__ import annotations

from typing import Iterable

import torch


def adam(params: Iterable[torch.nn.Parameter], lr: float) -> torch.optim.Adam:
    """``torch.optim.Adam(params, lr)``, fused where this torch and the parameters' device support it
    (torch >= 2.4 on the CPU, CUDA), else torch's default implementation."""
    params = list(params)
    try:
        return torch.optim.Adam(params, lr=lr, fused=True)
    except (RuntimeError, TypeError, ValueError):  # an older torch, or a device without the fused kernel
        return torch.optim.Adam(params, lr=lr)
