"""Experiment grids: the cells of the paper's tables, each one ordinary ``kneas-train`` run.

A :class:`Cell` is (scene, method, K, views, seed, preset [, extra train args]).
It runs as::

    kneas-train METHOD --scene SCENE [--num-materials K] [--views V] --seed S \
        --preset P --output-dir OUT/cells/<cell id> [extra args]

so the run lands in ``OUT/cells/<cell id>/<scene>/<method>/<timestamp>/`` and
the cell is complete once a ``metrics.json`` exists under its folder.

Grids (``kneas-bench``):

- ``table1``: scenes x {neas-1m (1M), neas-2m (2M), k-neas K = 1..4} x seeds (Table 1).
- ``views``: scenes (chest) x views {5, 10, 20, 50} x {neas-2m, k-neas K = 2} x seeds (Table 2).
- ``ablation``: scenes (foot) x {kselector, kselector-floater, kselector-shared, k-neas}, K = 2, x seeds (Table 3).
- ``grid``: any scenes x methods x K x views x seeds.

Every table grid (``table1``, ``views``, ``ablation``) also has one cell per
scene (and per view count) for each classical reference method
(:data:`REFERENCE_METHODS`: ``fdk``, ``sart``, ``os-sart``, ``cgls``,
``asd-pocs``; ``references`` picks which, default all): they are
deterministic, so each runs once (seed 0), without ``--num-materials``, as a
classical reference row. In ``grid`` they are ordinary methods that run once
(``kneas-bench grid`` adds its ``--references`` to ``--methods``).

The table grids also have, per scene and view count, one *oracle* cell for each method of
``oracles`` (``kneas-bench --oracles``, default :data:`ORACLE_METHODS`): the method run for
:data:`ORACLE_ITERATIONS` iterations with every count scored against the scene's truth
(``kneas-train --trace``); its row holds the best count's 3D figures, the bar no user can pick.
"""

from __future__ import annotations

import hashlib
import re
import sys
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Iterable, Optional, Sequence

from ..classical.options import ALGORITHMS
from ..errors import ConfigError

# The classical reference methods: the classical kneas-train methods (ClassicalConfig
# specs). No training, no materials, deterministic: one run (seed 0) per scene and view count.
REFERENCE_METHODS: tuple[str, ...] = ALGORITHMS
# Methods whose material count is fixed (no --num-materials passed) or absent.
FIXED_K = {"neas-1m": 1, "neas-2m": 2}
NO_MATERIALS = (*REFERENCE_METHODS, "naf")
TABLE1_K = (1, 2, 3, 4)
VIEWS = (5, 10, 20, 50)
ABLATION_METHODS = ("kselector", "kselector-floater", "kselector-shared", "k-neas")
DEFAULT_TRAIN_PREFIX = (sys.executable, "-c", "from kneas_method.cli.train import main; main()")
# The oracle rows: these classical methods run this many iterations, every count scored against the
# truth (kneas-train --trace); the row is the best count, which no user can pick from projections alone.
ORACLE_METHODS: tuple[str, ...] = ("sart", "asd-pocs")
ORACLE_ITERATIONS = 40
ORACLE_SUFFIX = "@best"  # an oracle cell's method in its group key: "asd-pocs@best"


def _slug(text: str) -> str:
    s = re.sub(r"[^A-Za-z0-9_.-]+", "_", str(text)).strip("_.") or "x"
    return s


def scene_slug(scene: str) -> str:
    """A folder-safe name for a scene: the built-in name, or a pickle's stem plus a short hash of its path."""
    if "/" in scene or scene.endswith((".pickle", ".pkl")):
        digest = hashlib.sha1(str(Path(scene).expanduser()).encode()).hexdigest()[:6]
        return f"{_slug(Path(scene).stem)}-{digest}"
    return _slug(scene)


@dataclass(frozen=True)
class Cell:
    """One training run of a grid.

    Attributes:
        scene: built-in scene name or path to a NAF pickle.
        method: registered kneas-train method (the classical references included).
        k: number of materials (None for methods without materials: the classical references, naf).
        views: training views kept (None = all of the scene's, 50 for the benchmarks).
        seed: training seed.
        preset: kneas-train preset (``tiny``, ``cpu``, ``paper``, ``auto``).
        extra: extra ``kneas-train`` arguments, passed through verbatim.
        oracle: a classical reference run for :data:`ORACLE_ITERATIONS` iterations with every count
            scored (``--trace``); its row is the best count's volume.
        folder: the id of the cell whose folder this one shares, or None for its own: a cell that keeps
            all of its scene's training views trains exactly what the cell asking for all of them trains
            (``Scene.subsample_views`` keeps the scene as it is), so the grids give it that cell's folder
            (:func:`share_all_views`) and the manifest records it. Not part of the id or the group.
    """

    scene: str
    method: str
    k: Optional[int]
    views: Optional[int]
    seed: int
    preset: str
    extra: tuple[str, ...] = field(default=())
    oracle: bool = False
    folder: Optional[str] = field(default=None, compare=False)

    @property
    def id(self) -> str:
        """Deterministic folder name, e.g. ``foot__k-neas__K2__vall__s0__tiny``."""
        parts = [scene_slug(self.scene), _slug(self.method), f"K{self.k}" if self.k is not None else "K-",
                 f"v{self.views}" if self.views is not None else "vall", f"s{self.seed}", _slug(self.preset)]
        if self.extra:
            parts.append("x" + hashlib.sha1("\0".join(self.extra).encode()).hexdigest()[:8])
        if self.oracle:
            parts.append(f"best{ORACLE_ITERATIONS}")
        return "__".join(parts)

    @property
    def group(self) -> tuple:
        """The cell without its seed: the key that seeds are averaged over (an oracle's method ends in ``@best``)."""
        return (self.scene, self.method + (ORACLE_SUFFIX if self.oracle else ""), self.k, self.views)

    def train_args(self, output_dir: str | Path) -> list[str]:
        """``kneas-train`` arguments (after the program) for this cell."""
        args = [self.method, "--scene", self.scene]
        if self.k is not None and self.method not in FIXED_K and self.method not in NO_MATERIALS:
            args += ["--num-materials", str(self.k)]
        if self.views is not None:
            args += ["--views", str(self.views)]
        args += ["--seed", str(self.seed), "--preset", self.preset, "--output-dir", str(output_dir)]
        if self.oracle:
            args += ["--reconstruction.iterations", str(ORACLE_ITERATIONS), "--trace"]
        return args + list(self.extra)

    def command(self, output_dir: str | Path, prefix: Sequence[str] = DEFAULT_TRAIN_PREFIX) -> list[str]:
        """The full command line: ``prefix`` (how to start kneas-train) + :meth:`train_args`."""
        return [*prefix, *self.train_args(output_dir)]

    def to_dict(self) -> dict:
        d = asdict(self)
        d["extra"] = list(self.extra)
        d["id"] = self.id
        return d


def seeds_from_count(n: int) -> tuple[int, ...]:
    """``--seeds N`` means N seeds: 0 .. N-1."""
    if n < 1:
        raise ConfigError(f"--seeds must be at least 1 (it is the number of seeds, 0..N-1), got {n}")
    return tuple(range(n))


def _check_common(scenes: Sequence[str], preset: str, views: Iterable[Optional[int]] = (None,)) -> dict[str, int]:
    """Refuse, before any cell runs (and in a dry run), what every cell would fail on: no or
    unknown scenes (neither a file nor a built-in name), an unknown preset, a view count below 1
    or above a scene's training views. Returns each scene's training views where view counts were
    given (for :func:`share_all_views`), else an empty dict."""
    from ..data.scenes import check_scene_spec
    from ..methods import PRESETS

    if not scenes:
        raise ConfigError("no scenes given; pass e.g. --scenes foot jaw")
    for scene in scenes:
        check_scene_spec(scene, "--scenes")
    if preset not in PRESETS:
        raise ConfigError(f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
    views = [v for v in views if v is not None]
    bad = [v for v in views if not (isinstance(v, int) and v >= 1)]
    if bad:
        raise ConfigError(f"view counts must be whole numbers >= 1, got {', '.join(map(str, bad))}")
    totals: dict[str, int] = {}
    if views:  # a count above a scene's training views would fail in every cell that asks for it
        from ..data.scenes import training_view_count

        for scene in scenes:
            total = totals[scene] = training_view_count(scene)
            if max(views) > total:
                raise ConfigError(f"--views {max(views)} is more than scene {scene}'s {total} training views; choose counts from 1 to {total}")
    return totals


def is_reference(method: str) -> bool:
    """True for a classical reference method (:data:`REFERENCE_METHODS`), or its oracle's group name (``asd-pocs@best``)."""
    return method.split(ORACLE_SUFFIX)[0] in REFERENCE_METHODS


def check_oracles(oracles: Iterable[str]) -> tuple[str, ...]:
    """The chosen oracle methods, each once; FDK (no iterations) and unknown names are an error."""
    oracles = tuple(dict.fromkeys(oracles))
    bad = [m for m in oracles if m == "fdk" or not is_reference(m)]
    if bad:
        raise ConfigError(f"--oracles takes iterative classical methods ({', '.join(m for m in REFERENCE_METHODS if m != 'fdk')}), "
                          f"not {', '.join(bad)}")
    return oracles


def check_references(references: Iterable[str]) -> tuple[str, ...]:
    """The chosen reference methods, each once, in the order given; unknown names are an error."""
    references = tuple(dict.fromkeys(references))
    unknown = [m for m in references if not is_reference(m)]
    if unknown:
        raise ConfigError(f"unknown reference method(s) {', '.join(unknown)}; the classical references are "
                          f"{', '.join(REFERENCE_METHODS)}")
    return references


def _reference_cells(scenes: Iterable[str], views: Iterable[Optional[int]], references: Sequence[str], preset: str,
                     extra: tuple[str, ...], oracles: Sequence[str] = ()) -> list[Cell]:
    """One cell per scene, view count and reference method, seed 0 (deterministic), no materials; then one
    oracle cell per scene, view count and method of ``oracles``."""
    references, oracles = check_references(references), check_oracles(oracles)
    return ([Cell(s, m, None, v, 0, preset, extra) for s in scenes for v in views for m in references]
            + [Cell(s, m, None, v, 0, preset, extra, oracle=True) for s in scenes for v in views for m in oracles])


def oracle_cells(scenes: Iterable[str], views: Iterable[Optional[int]], oracles: Sequence[str], preset: str,
                 extra: Sequence[str] = ()) -> list[Cell]:
    """One oracle cell per scene, view count and method of ``oracles`` (:class:`Cell` ``oracle``)."""
    return _reference_cells(scenes, views, (), preset, tuple(extra), oracles)


def _dedupe(cells: Iterable[Cell]) -> list[Cell]:
    seen, out = set(), []
    for c in cells:
        if c.id not in seen:
            seen.add(c.id)
            out.append(c)
    return out


def share_all_views(cells: Iterable[Cell], totals: dict[str, int]) -> list[Cell]:
    """``cells`` with :attr:`Cell.folder` set on each whose view count is all of its scene's training
    views (``totals``: scene -> count): it shares the folder of the same cell without a view count, so
    Table 2's 50-view cells on a 50-view scene are Table 1's and run once."""
    return [replace(c, folder=replace(c, views=None).id) if c.views is not None and c.views == totals.get(c.scene) else c
            for c in cells]


def procedure_args(procedure: Optional[str]) -> tuple[str, ...]:
    """The ``kneas-train`` arguments that fit a table's neural cells with ``procedure`` (None: the
    preset's own, no argument); an unknown procedure is refused before any cell runs. The classical
    references have no procedure: they run as they do in every table."""
    if procedure is None:
        return ()
    from ..presets import procedure_of

    procedure_of(procedure)  # raises ConfigError naming the known procedures
    return ("--procedure", procedure)


def table1(scenes: Sequence[str] = ("abdomen", "chest", "foot", "jaw"), seeds: Sequence[int] = (0, 1, 2), preset: str = "auto",
           ks: Sequence[int] = TABLE1_K, views: Optional[int] = None, references: Sequence[str] = REFERENCE_METHODS,
           extra: Sequence[str] = (), oracles: Sequence[str] = (), procedure: Optional[str] = None) -> list[Cell]:
    """Table 1: per scene NeAS 1M (neas-1m), NeAS 2M (neas-2m) and K-NeAS KM (k-neas, K in ``ks``),
    plus one cell per classical reference in ``references`` (empty: none)."""
    totals = _check_common(scenes, preset, [views])
    refs_extra, extra = tuple(extra), tuple(extra) + procedure_args(procedure)
    cells = []
    for s in scenes:
        for k in ks:
            if k < 1:
                raise ConfigError(f"material counts must be >= 1, got {k}")
            for seed in seeds:
                if k in (1, 2):
                    cells.append(Cell(s, f"neas-{k}m", k, views, seed, preset, extra))
                cells.append(Cell(s, "k-neas", k, views, seed, preset, extra))
    cells += _reference_cells(scenes, [views], references, preset, refs_extra, oracles)
    return share_all_views(_dedupe(cells), totals)


def views_table(scenes: Sequence[str] = ("chest",), seeds: Sequence[int] = (0, 1, 2), preset: str = "auto",
                views: Sequence[int] = VIEWS, k: int = 2, references: Sequence[str] = REFERENCE_METHODS,
                extra: Sequence[str] = (), oracles: Sequence[str] = (), found_k: bool = True,
                procedure: Optional[str] = None) -> list[Cell]:
    """Table 2: views x {neas-2m, k-neas with K = 2} per scene, plus each classical reference per scene and view count.

    ``found_k`` adds k-neas as a user runs it (no K given: K comes from the bounds), one cell per view count and seed.
    """
    totals = _check_common(scenes, preset, views)
    refs_extra, extra = tuple(extra), tuple(extra) + procedure_args(procedure)
    models = [("neas-2m", 2), ("k-neas", k)] + ([("k-neas", None)] if found_k else [])
    cells = [Cell(s, m, mk, v, seed, preset, extra) for s in scenes for v in views for m, mk in models for seed in seeds]
    cells += _reference_cells(scenes, views, references, preset, refs_extra, oracles)
    return share_all_views(_dedupe(cells), totals)


def ablation(scenes: Sequence[str] = ("foot",), seeds: Sequence[int] = (0,), preset: str = "auto", k: int = 2,
             methods: Sequence[str] = ABLATION_METHODS, views: Optional[int] = None, references: Sequence[str] = REFERENCE_METHODS,
             extra: Sequence[str] = (), oracles: Sequence[str] = (), procedure: Optional[str] = None) -> list[Cell]:
    """Table 3: the four-way ablation with K = 2, plus one cell per classical reference and scene."""
    totals = _check_common(scenes, preset, [views])
    refs_extra, extra = tuple(extra), tuple(extra) + procedure_args(procedure)
    # a classical method among ``methods`` is a reference (one run, no K), not an ablation variant
    cells = [Cell(s, m, k, views, seed, preset, extra) for s in scenes for m in methods if not is_reference(m) for seed in seeds]
    cells += _reference_cells(scenes, [views], [*references, *filter(is_reference, methods)], preset, refs_extra, oracles)
    return share_all_views(_dedupe(cells), totals)


def grid(scenes: Sequence[str], methods: Sequence[str], ks: Sequence[Optional[int]] = (None,), views: Sequence[Optional[int]] = (None,),
         seeds: Sequence[int] = (0,), preset: str = "auto", extra: Sequence[str] = (), procedure: Optional[str] = None) -> list[Cell]:
    """Any scenes x methods x K x views x seeds.

    K is ignored for the classical references and naf (and fixed to 1 / 2 for neas-1m /
    neas-2m); ``None`` in ``ks`` means the method's default K. The classical references
    (:data:`REFERENCE_METHODS`) are deterministic and run once (the first seed).
    """
    totals = _check_common(scenes, preset, views)
    if not methods:
        raise ConfigError("no methods given; pass e.g. --methods k-neas neas-2m fdk")
    refs_extra, extra = tuple(extra), tuple(extra) + procedure_args(procedure)
    cells = []
    for s in scenes:
        for m in methods:
            for v in views:
                if m in NO_MATERIALS:
                    mk: list[Optional[int]] = [None]
                elif m in FIXED_K:
                    mk = [FIXED_K[m]]
                else:
                    mk = list(ks)
                for k in mk:
                    for seed in (seeds[:1] if is_reference(m) else seeds):
                        cells.append(Cell(s, m, k, v, seed, preset, refs_extra if is_reference(m) else extra))
    return share_all_views(_dedupe(cells), totals)


def check_methods(methods: Iterable[str]) -> None:
    """Every method must be a registered kneas-train method (the classical references are)."""
    from .. import registry

    known = set(registry.methods()) | set(REFERENCE_METHODS)
    unknown = [m for m in methods if m not in known]
    if unknown:
        raise ConfigError(f"unknown method(s) {', '.join(unknown)}; available: {', '.join(sorted(known))}")
