"""Which machine made a run: its processor, core count, torch build and GPU.

torch does not promise the same figures from the same seed on another platform or release (its kernels
sum in an order that depends on the processor's vector width and the build), and training can carry a
last-bit difference into a different volume. ``metrics.json`` carries this record as ``machine`` so
that two runs of the same command and seed that disagree can be told apart by where they ran.
"""

from __future__ import annotations

import functools
import os
import platform
from pathlib import Path
from typing import Optional

import torch

CPUINFO = Path("/proc/cpuinfo")


def processor_name(cpuinfo: Path = CPUINFO) -> str:
    """The processor's model name (Linux's ``/proc/cpuinfo``), else what :mod:`platform` knows."""
    try:
        for line in cpuinfo.read_text(encoding="utf-8", errors="replace").splitlines():
            key, _, value = line.partition(":")
            if key.strip() == "model name" and value.strip():
                return " ".join(value.split())
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown"


@functools.lru_cache(maxsize=None)
def _cpu_record() -> dict:
    return {"processor": processor_name(), "cores": os.cpu_count(), "torch": torch.__version__}


def machine_record(device: torch.device | str) -> dict:
    """``{"processor", "cores", "torch"}``, plus ``gpu`` (its name) when ``device`` is a CUDA device."""
    device = torch.device(device)
    out = dict(_cpu_record())
    if device.type == "cuda":
        out["gpu"] = torch.cuda.get_device_name(device)
    return out


def describe(record: Optional[dict]) -> str:
    """A short label: ``AMD EPYC / 2 cores / torch 2.13.0``; a GPU run ``NVIDIA H100 80GB HBM3 / torch 2.11.0``;
    ``not recorded`` for runs that predate the record."""
    if not isinstance(record, dict) or not record:
        return "not recorded"
    where = record.get("gpu") or f"{record.get('processor', '?')} / {record.get('cores', '?')} cores"
    return f"{where} / torch {record.get('torch', '?')}"
