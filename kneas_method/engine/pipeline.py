"""``kneas-train``'s orchestrator: scene -> run folder -> the run's pipeline.

``train(config)`` loads the scene (``loading.load_scene``: a public
``data/<name>_50.pickle`` wins over the built-in phantom; ``--views``; held-out
views made from training views when the scene has none), creates the run folder
(``DIR/<scene>/<method>/<timestamp>``, or the given one with ``--resume``),
writes ``config.json`` and hands over to the pipeline of the run's kind,
``config.setup(...)`` with the box the views are fitted on (``data.truncation.fitting_scene``:
the scene's own, or longer along the axis where the object goes on beyond it): :class:`~.neural_pipeline.NeuralPipeline` for
:class:`~kneas_method.methods.TrainConfig`,
:class:`~.classical_pipeline.ClassicalPipeline` for
:class:`~kneas_method.methods.ClassicalConfig`, or a plugin's own.

Resuming (``--resume RUN_DIR``, config from ``loading.resume_config``): a run with
``metrics.json`` is complete and only its summary is printed; otherwise the
pipeline continues (bounds from ``bounds.json``, training from the newest checkpoint).
"""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import torch

from ..console import say
from ..errors import ConfigError
from ..data.truncation import fitting_scene
from . import report
from .code_version import code_version
from ..device import resolve_device
from .loading import load_scene
from .run_dir import check_writable, create_run_dir, read_json, save_run_config


def train(config) -> int:
    """Run one resolved config (train or reconstruct, then evaluate); returns the exit code."""
    started = time.perf_counter()
    # the code record (cached for the process) is taken as the run starts, so a checkout that moves on
    # while the run trains does not relabel it with the later commit
    code_version()
    device = resolve_device(config.device)
    if config.resume:
        run_dir = Path(config.resume)
        if (run_dir / "metrics.json").is_file():
            say(f"run {run_dir} is already complete; nothing to resume")
            report.print_summary(run_dir, read_json(run_dir / "metrics.json", "metrics file"))
            return 0
        check_writable(run_dir)  # a full or read-only run folder is reported before training resumes
        say(f"resuming run {run_dir} ({config.method}, preset {config.preset}, seed {config.seed})")
        scene = load_scene(config, say=say)
    else:
        scene = load_scene(config, say=say)
        run_dir = create_run_dir(config.output_dir, scene.name, config.method)
        save_run_config(run_dir, config)
        say(f"run folder: {run_dir}")
    try:
        fitting = fitting_scene(scene, say=say)
        say(f"device: {device}; torch threads: {torch.get_num_threads()}")
        return config.setup(scene=scene, fitting=fitting, run_dir=run_dir, device=device, started=started).run()
    except ConfigError:
        if not config.resume and _holds_no_work(run_dir):  # a mistake in the settings: no folder left that resumes into it
            shutil.rmtree(run_dir, ignore_errors=True)
            for parent in (run_dir.parent, run_dir.parent.parent):  # <method>/ and <scene>/, where nothing else is in them
                try:
                    parent.rmdir()
                except OSError:
                    break
        raise


def _holds_no_work(run_dir: Path) -> bool:
    """True when the fresh ``run_dir`` holds only its ``config.json`` and empty folders (a settings
    error found before anything was computed): nothing there is worth keeping."""
    for path in run_dir.rglob("*"):
        if path.is_file() and path != run_dir / "config.json":
            return False
    return True
