"""The one place a device name or tensor becomes a ``torch.device``."""

from __future__ import annotations

from typing import Any, Optional

import torch

from .errors import KneasError


def resolve_device(device: Any = None, like: Optional[torch.Tensor] = None, flag: str = "--device") -> torch.device:
    """``device`` as a checked ``torch.device``.

    ``auto`` -> cuda if available else cpu; None -> ``like``'s device when it is a tensor, else cpu;
    anything else (``cpu``, ``cuda:1``, a ``torch.device``) as given.

    Raises:
        KneasError: not a torch device, or CUDA asked for where there is none (``flag`` names the
        setting in the message).
    """
    if device is None:
        device = like.device if isinstance(like, torch.Tensor) else "cpu"
    if isinstance(device, str) and device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError) as exc:
        raise KneasError(f"{flag} {device!r} is not a torch device ({exc}); use auto, cpu or cuda") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise KneasError(f"{flag} {str(device)!r} asked for but no CUDA GPU is available; use {flag} cpu or auto")
    return dev
