"""The optimiser every fit of a run uses: Adam, fused where torch has it for the device.

torch's default Adam makes several passes over each parameter tensor a step; the fused one makes one.
On the cpu preset's step that is 1.0 ms against 3.1 ms with its 2^16-entry hash table, and 2.6 ms
against 22.5 ms with a 2^19-entry one (2 cores, 2026-12-06), the same update up to rounding.
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
