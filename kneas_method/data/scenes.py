"""Resolve a scene name or path to a :class:`Scene` (used by ``kneas-train --scene``).

Order: an existing file is loaded as a NAF pickle; a built-in name (``foot``, ``jaw``,
``chest``, ``abdomen``) uses the public benchmark ``<data_dir>/<name>_50.pickle`` when
present, otherwise the built-in phantom simulated once with the default
:class:`SimulationConfig` and cached as ``<cache_dir>/<name>_50.pickle``. The cache
records a key derived from the simulation config, the phantom's description and the
simulator version; a mismatch regenerates the file.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from ..errors import SceneError
from .naf import load_naf, save_naf
from .scene import Scene
from .simulate import NOISE_MODEL_VERSION, SIMULATOR_VERSION, SimulationConfig, simulate_phantom

CACHE_KEY_META = "cache_key"


def builtin_names() -> tuple[str, ...]:
    """Names of the built-in phantom scenes."""
    from .phantoms import PHANTOM_NAMES

    return tuple(PHANTOM_NAMES)


def default_cache_dir() -> Path:
    """``$KNEAS_CACHE`` or ``~/.cache/kneas/scenes``."""
    env = os.environ.get("KNEAS_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "kneas" / "scenes"


def cache_key(name: str, cfg: SimulationConfig) -> str:
    """A short hash of everything that determines a built-in scene's content."""
    from .phantoms import get_phantom

    phantom = get_phantom(name)
    payload = {"name": name, "config": cfg.to_dict(), "phantom": phantom.describe(), "simulator": SIMULATOR_VERSION}
    if cfg.noise:
        payload["noise_model"] = NOISE_MODEL_VERSION
    return hashlib.sha256(json.dumps(payload, sort_keys=True, default=str).encode()).hexdigest()[:16]


def builtin_scene(
    name: str,
    *,
    cache_dir=None,
    cfg: SimulationConfig | None = None,
    progress: Optional[Callable[[str], None]] = None,
) -> Scene:
    """The built-in phantom scene ``name``, simulated once and cached (atomic write)."""
    cfg = cfg or SimulationConfig()
    cache_dir = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    path = cache_dir / f"{name}_{cfg.n_train}.pickle"
    key = cache_key(name, cfg)
    if path.is_file():
        try:
            scene = load_naf(path, name=name)
            if scene.meta.get(CACHE_KEY_META) == key:
                scene.source = f"built-in phantom {name} (cached at {path})"
                return scene
        except SceneError:
            pass  # damaged or foreign file: regenerate it
    scene = simulate_phantom(name, cfg, progress=progress)
    scene.meta[CACHE_KEY_META] = key
    save_naf(scene, path)
    scene = load_naf(path, name=name)  # exactly what later runs will see
    scene.source = f"built-in phantom {name} (cached at {path})"
    return scene


def public_benchmark_path(name: str, data_dir="data") -> Path:
    """Where a public benchmark pickle for ``name`` is looked for (``data_dir/<name>_50.pickle``);
    where it exists it stands in for the built-in scene of that name."""
    return Path(data_dir) / f"{name}_50.pickle"


def resolve_scene(
    spec: str,
    *,
    data_dir="data",
    cache_dir=None,
    progress: Optional[Callable[[str], None]] = None,
    flag: str = "--scene",
) -> Scene:
    """Turn ``--scene`` into a :class:`Scene`.

    Args:
        spec: a path to a NAF ``.pickle`` file, or a built-in name.
        data_dir: where public benchmark pickles (``<name>_50.pickle``) are looked for.
        cache_dir: where simulated built-in scenes are cached (default
            ``$KNEAS_CACHE`` or ``~/.cache/kneas/scenes``).
        progress: optional ``progress(message)`` while a built-in scene is simulated.
        flag: how a refusal names the argument (:func:`check_scene_spec`).

    Returns:
        The scene; ``scene.source`` says where it came from.
    """
    spec = str(spec)
    check_scene_spec(spec, flag)
    path = Path(spec).expanduser()
    if path.is_file():
        scene = load_naf(path)
        scene.source = f"file {path}"
        return scene
    public = public_benchmark_path(spec, data_dir)
    if public.is_file():
        try:
            scene = load_naf(public, name=spec)
        except SceneError as exc:
            shadow = f"; it stands in for the built-in {spec!r}: remove it to use that" if spec in builtin_names() else ""
            raise SceneError(f"{public}: {exc}{shadow}") from None
        scene.source = f"public benchmark {public}"
        return scene
    return builtin_scene(spec, cache_dir=cache_dir, progress=progress)


def training_view_count(spec, *, data_dir="data") -> int:
    """The number of training views the scene :func:`resolve_scene` gives for ``spec`` has,
    without simulating a built-in scene (its :class:`SimulationConfig`'s ``n_train``); a pickle
    (a file, or a public benchmark in ``data_dir`` standing in for a built-in name) is read.

    Raises:
        SceneError: as :func:`check_scene_spec`, or the pickle's own refusal.
    """
    from .naf import safe_load_pickle

    spec = str(spec)
    check_scene_spec(spec)
    path = Path(spec).expanduser()
    if not path.is_file():
        public = public_benchmark_path(spec, data_dir)
        if not public.is_file():
            return int(SimulationConfig().n_train)
        path = public
    d = safe_load_pickle(path)
    train = d.get("train") if isinstance(d, dict) else None
    if not isinstance(train, dict) or "angles" not in train:
        raise SceneError(f"{path.name} has no train.angles; a NAF scene needs train = {{'angles': [N], 'projections': [N, nV, nU]}}")
    return int(np.asarray(train["angles"]).reshape(-1).size)


def check_scene_spec(spec, flag: str = "--scene") -> None:
    """Refuse, without loading anything, a ``--scene`` that :func:`resolve_scene` would refuse:
    neither an existing file nor a built-in name (so a command can say so before any other work).

    ``flag`` names the argument in the message (``--scene``, or ``SCENE`` for a positional one).

    Raises:
        SceneError: naming the closest built-in scene, or that a directory was given.
    """
    spec = str(spec)
    path = Path(spec).expanduser()
    names = builtin_names()
    if path.is_file() or spec in names:
        return
    if path.is_dir():
        raise SceneError(f"{flag} {spec} is a directory; give a NAF .pickle file or a built-in scene ({', '.join(names)})")
    import difflib

    close = difflib.get_close_matches(spec, names, n=1, cutoff=0.6)
    raise SceneError(
        f"{flag} {spec!r} is neither an existing file nor a built-in scene"
        + (f"; did you mean {close[0]}?" if close else "")
        + f" (built-in: {', '.join(names)}; or the path of an existing NAF .pickle file)"
    )
