"""A classical reconstruction of a neural run's training views, for its bounds and warm start.

Computed once per run and kept in the run folder as ``<algorithm>_volume.npy`` (data
units) with ``<algorithm>_volume.json`` (settings, seconds), so a resumed run reuses it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..atomic import atomic_write
from ..classical.reconstruct import Reconstruction, reconstruct
from ..console import say
from ..errors import KneasError
from .progress import stage_progress
from .run_dir import read_json, write_json


def classical_volume(algorithm: str, config, scene, run_dir: Path, device) -> Reconstruction:
    """The run's ``algorithm`` reconstruction of its training views (cached in ``run_dir``)."""
    from ..console import console

    path, info_path = Path(run_dir) / f"{algorithm}_volume.npy", Path(run_dir) / f"{algorithm}_volume.json"
    if path.is_file() and info_path.is_file():
        try:
            volume = np.load(path, allow_pickle=False)
            info = read_json(info_path, f"{algorithm} volume info")
            if tuple(volume.shape) == tuple(scene.geometry.n_voxel):
                return Reconstruction(volume, float(info.get("seconds", 0.0)), dict(info.get("settings", {})))
        except (OSError, ValueError, KneasError):
            pass
    say(f"{algorithm}: reconstructing {len(scene.train)} training views for the bounds / warm start")
    with stage_progress(console, unit="iterations") as progress:
        task = progress.add_task(algorithm, total=None, info="")

        def report(i, total, residual):
            progress.update(task, completed=i, total=total, info=f"residual {residual:.3e}")

        rec = reconstruct(algorithm, scene, config.reconstruction, device=device, progress=report)
    volume = np.asarray(rec.volume, dtype=np.float32)
    atomic_write(path, lambda fh: np.save(fh, volume))
    write_json(info_path, {"seconds": rec.seconds, "settings": rec.settings})
    return rec
