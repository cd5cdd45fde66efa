"""`kneas-bench table1|views|ablation|grid|page`: run the paper's experiments, write its tables and the results page.

Each cell of a grid (scene x method x K x views x seed) is an ordinary
``kneas-train`` run in ``OUTPUT_DIR/cells/<cell id>/``; cells that already have
a ``metrics.json`` are skipped, so rerunning the same command continues where
the last one stopped (and trains nothing when all are done). The tables go to
``OUTPUT_DIR/<table>.md`` and ``.csv`` (mean ± std over seeds, best per scene
in bold, one row per classical reference (FDK, SART, OS-SART, CGLS, ASD-POCS;
``--references`` picks which), the paper's numbers beside ours for
public-benchmark scenes).

Examples::

    kneas-bench table1 --preset tiny --scenes foot jaw --seeds 2
    kneas-bench table1 --dry-run                                  # list cells and estimated costs
    kneas-bench views --seeds 3 --backend local --workers 4       # 4 GPUs: one run per GPU
    kneas-bench ablation --backend ray --address auto             # on a running Ray cluster
    kneas-bench grid --scenes foot --methods k-neas naf --num-materials 2 3 --views 10 50 --seeds 2
    kneas-bench table1 --references fdk sart                      # only these classical reference rows
    kneas-bench table1 --references                               # no classical reference rows
    kneas-bench page --output-dir outputs/bench                   # docs/paper_tables.md: every table run there, verdicts
    kneas-bench archive --output-dir outputs/bench --to benchmarks/results/paper   # the records only, to keep or move
"""

from __future__ import annotations

import shlex
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Optional, Sequence

from ..bench.grid import ORACLE_ITERATIONS, ORACLE_METHODS, REFERENCE_METHODS
from ..classical.options import Algorithm
from ..errors import ConfigError
from .common import console, run_cli


@dataclass
class _Common:
    """Options shared by every table."""

    seeds: int = 3
    """number of seeds: 0 .. N-1 (the classical references run once)"""
    preset: str = "auto"
    """kneas-train preset: auto (paper with a GPU, else cpu), paper, cpu, tiny"""
    output_dir: str = "outputs/bench"
    """cells go to OUTPUT_DIR/cells/<cell id>/, tables to OUTPUT_DIR/"""
    backend: Literal["local", "ray"] = "local"
    """local: runs on this machine (see --workers); ray: one Ray task per run"""
    workers: int = 1
    """local backend: runs at a time (one per GPU when GPUs exist, else CPU workers sharing the cores)"""
    address: Optional[str] = None
    """ray backend: 'auto' or HOST:PORT of a running cluster; without it a local Ray instance is started"""
    cpus_per_cell: int = 1
    """ray backend: CPUs each run asks for (on GPU clusters each run also asks for one GPU)"""
    dry_run: bool = False
    """list the cells with an estimated cost each; run nothing"""
    references: tuple[Algorithm, ...] = REFERENCE_METHODS
    """classical reference methods to add: one deterministic run (seed 0) each per scene and view count, a '(ref.)' row that is never bold; --references with no name adds none"""
    oracles: tuple[Algorithm, ...] = ORACLE_METHODS
    """classical methods that also get an oracle row: one run of 40 iterations per scene and view count, every count scored against the truth, the best one shown ('best of 1-40 (oracle)'); --oracles with no name adds none"""
    train_args: str = ""
    """extra kneas-train arguments for every cell, as one string with =: --train-args="--trainer.epochs 5" """
    procedure: Optional[str] = None
    """the fitting procedure of the neural cells (paper, refine-classical or a plugin's; default: the preset's): a table run with one is recorded as its own table (table1@paper) and shown after the default's on the page"""


@dataclass
class Table1(_Common):
    """Table 1: scenes x {NeAS 1M/2M, K-NeAS 1M..4M} x seeds."""

    scenes: tuple[str, ...] = ("abdomen", "chest", "foot", "jaw")
    """built-in scene names or NAF pickle paths"""
    num_materials: tuple[int, ...] = (1, 2, 3, 4)
    """material counts (rows 1M..4M; NeAS only has 1M and 2M)"""
    views: Optional[int] = None
    """training views (default: all, 50 on the benchmarks)"""


@dataclass
class Views(_Common):
    """Table 2: views x {NeAS (neas-2m), K-NeAS (k-neas K=2), K-NeAS with K found} x seeds."""

    scenes: tuple[str, ...] = ("chest",)
    """built-in scene names or NAF pickle paths"""
    views: tuple[int, ...] = (5, 10, 20, 50)
    """training view counts"""
    num_materials: int = 2
    """K of the k-neas runs (neas-2m is always 2)"""
    found_k: bool = True
    """also run k-neas as a user does, with no K given (K found from the bounds): one more row per view count"""


@dataclass
class Ablation(_Common):
    """Table 3: {kselector, kselector-floater, kselector-shared, k-neas} with K = 2."""

    scenes: tuple[str, ...] = ("foot",)
    """built-in scene names or NAF pickle paths"""
    seeds: int = 1
    """number of seeds (the paper reports a single run)"""
    num_materials: int = 2
    """K for every variant"""
    methods: tuple[str, ...] = ("kselector", "kselector-floater", "kselector-shared", "k-neas")
    """the ablation variants"""


@dataclass
class Grid(_Common):
    """Any grid: scenes x methods x K x views x seeds."""

    scenes: tuple[str, ...] = ("foot",)
    """built-in scene names or NAF pickle paths"""
    methods: tuple[str, ...] = ("k-neas",)
    """registered kneas-train methods (classical ones included; --references are added to them)"""
    num_materials: tuple[int, ...] = ()
    """material counts (empty: each method's default; ignored by the classical methods and naf, fixed for neas-1m/neas-2m)"""
    views: tuple[int, ...] = ()
    """training view counts (empty: all views)"""


@dataclass
class Page:
    """The results page: every table run in OUTPUT_DIR, the paper's numbers beside, a verdict per claim."""

    output_dir: str = "outputs/bench"
    """the folder the tables ran in (kneas-bench table1|views|ablation --output-dir)"""
    write: str = "docs/paper_tables.md"
    """where the page goes (Markdown)"""


@dataclass
class Archive:
    """Keep the tables' results without their volumes: copy the manifests and every cell's records (cell.json, train.log, each run's JSON files) from OUTPUT_DIR to TO.

    TO is an output folder too: the page reads it, and copied back (kneas-bench archive --output-dir TO --to outputs/bench)
    a table continues there, running only the cells it lacks."""

    output_dir: str = "outputs/bench"
    """the folder the tables ran in"""
    to: str = "benchmarks/results/paper"
    """where the records go (cells and manifests already there are kept; each manifest becomes the union of both)"""


# How a cell starts kneas-train (tests replace it with a stand-in trainer).
TRAIN_PREFIX: tuple[str, ...] = ()  # () = kneas_method.bench.grid.DEFAULT_TRAIN_PREFIX

SUBCOMMANDS = {"table1": Table1(), "views": Views(), "ablation": Ablation(), "grid": Grid(), "page": Page(), "archive": Archive()}
LAYOUT = {Table1: "table1", Views: "views", Ablation: "ablation", Grid: "grid"}


def parse_args(argv: Sequence[str]) -> "_Common | Page | Archive":
    from .common import tyro_cli

    descriptions = {k: (type(v).__doc__ or "").strip() for k, v in SUBCOMMANDS.items()}
    return tyro_cli(SUBCOMMANDS, descriptions, list(argv), prog="kneas-bench", what="table",
                    description="Run the paper's experiment grids as kneas-train runs and write its tables.")


def expand(args: _Common) -> list:
    """The cells of a parsed command."""
    from ..bench import grid

    seeds = grid.seeds_from_count(args.seeds)
    try:
        extra = tuple(shlex.split(args.train_args))
    except ValueError as exc:
        raise ConfigError(f"--train-args could not be split ({exc}); quote it as one string, e.g. --train-args=\"--trainer.epochs 5\"") from None
    for bad in ("--output-dir", "--seed", "--preset", "--scene", "--views", "--num-materials", "--procedure"):
        if any(a == bad or a.startswith(bad + "=") for a in extra):
            raise ConfigError(f"--train-args must not contain {bad}: kneas-bench sets it per cell; use the kneas-bench option instead")
    if isinstance(args, Table1):
        cells = grid.table1(args.scenes, seeds, args.preset, args.num_materials, args.views, args.references, extra, args.oracles,
                            args.procedure)
    elif isinstance(args, Views):
        cells = grid.views_table(args.scenes, seeds, args.preset, args.views, args.num_materials, args.references, extra, args.oracles,
                                 args.found_k, args.procedure)
    elif isinstance(args, Ablation):
        cells = grid.ablation(args.scenes, seeds, args.preset, args.num_materials, args.methods, None, args.references, extra, args.oracles,
                              args.procedure)
    else:
        references = grid.check_references(args.references)
        methods = list(args.methods) + ([m for m in references if m not in args.methods] if args.methods else [])
        cells = grid.grid(args.scenes, methods, args.num_materials or (None,), args.views or (None,), seeds, args.preset, extra,
                          args.procedure)
        cells += grid.oracle_cells(args.scenes, args.views or (None,), args.oracles, args.preset, extra)
    grid.check_methods({c.method for c in cells})
    return cells


def _labels(c) -> list[str]:
    return [c.scene, c.method + (f" (best of 1-{ORACLE_ITERATIONS})" if c.oracle else ""), "-" if c.k is None else str(c.k), "all" if c.views is None else str(c.views), str(c.seed)]


def dry_run(args: _Common, cells: list, output_dir: Path) -> int:
    from rich.table import Table

    from ..bench import estimate
    from ..bench.cells import cell_dir, find_metrics, read_cell_record

    kind = estimate.device_kind()
    measured = estimate.measured_here(output_dir, cells)
    speed, speed_how = estimate.machine_speed(kind)
    t = Table(title=f"kneas-bench {LAYOUT[type(args)]} — {len(cells)} cells (dry run)")
    for col in ("scene", "method", "K", "views", "seed", "status", "estimate", "how estimated"):
        t.add_column(col, overflow="fold")
    total, unknown, todo = 0.0, 0, 0
    for c in cells:
        if find_metrics(cell_dir(output_dir, c), c.method) is not None:
            t.add_row(*_labels(c), "complete (skipped)", "-", "")
            continue
        rec = read_cell_record(output_dir, c)
        status = "to run" + (f" (last: {rec.get('status')})" if rec else "")
        secs, how = estimate.estimate(c, kind, measured, speed)
        todo += 1
        if secs is None:
            unknown += 1
        else:
            total += secs
        t.add_row(*_labels(c), status, estimate.format_seconds(secs), how)
    console.print(t)
    console.print(f"{todo} of {len(cells)} cells to run; estimated {estimate.format_seconds(total)} of {kind.upper()} time run one after "
                  f"another{f' ({unknown} without an estimate)' if unknown else ''}. Estimates: seconds per training step measured once per "
                  "preset (kneas_method/bench/estimate.py) x views x (epochs + prior epochs) + a per-run overhead, scaled by this machine's "
                  f"speed ({speed_how}), or the median wall time of cells already complete here.")
    return 0


def run(args: _Common) -> int:
    from ..bench import aggregate, backends, page
    from ..bench.cells import cell_dir, is_complete, own_folders_first
    from ..engine.run_dir import check_writable

    if args.workers < 1:
        raise ConfigError(f"--workers must be at least 1 (runs at a time), got {args.workers}")
    layout = LAYOUT[type(args)]
    name = page.table_name(layout, args.procedure)
    output_dir = Path(args.output_dir)
    cells = own_folders_first(output_dir, expand(args))
    if args.dry_run:
        return dry_run(args, cells, output_dir)
    check_writable(output_dir)
    if layout in page.LAYOUTS:  # before any cell runs, so the page counts an interrupted table's cells too
        page.add_to_manifest(output_dir, name, cells)
    if args.backend == "local" and (args.address or args.cpus_per_cell != 1):
        raise ConfigError("--address and --cpus-per-cell are for the ray backend; add --backend ray")
    if args.backend == "ray" and args.workers != 1:
        raise ConfigError("--workers is for the local backend; Ray runs as many cells at a time as the cluster has room for")
    backend = backends.make_backend(args.backend, args.workers, args.address, args.cpus_per_cell)
    todo = [c for c in cells if not is_complete(output_dir, c)]
    console.print(f"kneas-bench {name}: {len(cells)} cells, {len(cells) - len(todo)} already complete, {len(todo)} to run "
                  f"on {backend.describe()}; output {output_dir}")
    counts = {"done": 0, "failed": 0}
    t0 = time.monotonic()
    if todo:
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

        def describe() -> str:
            left = len(todo) - counts["done"] - counts["failed"]
            return f"done {counts['done']} · failed {counts['failed']} · remaining {left}"

        with Progress(SpinnerColumn(), TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                      console=console) as progress:
            task = progress.add_task(describe(), total=len(todo))

            def on_result(cell, result) -> None:
                counts["done" if result.status in ("done", "skipped") else "failed"] += 1
                if result.status == "failed":
                    first = (result.error or "").strip().splitlines()
                    progress.console.print(f"[red]failed[/] {cell.id} ({result.wall_time_s:.0f} s): {first[0] if first else ''} "
                                           f"— see {cell_dir(output_dir, cell) / 'train.log'}")
                else:
                    progress.console.print(f"[green]done[/]   {cell.id} ({result.wall_time_s:.0f} s)")
                progress.update(task, advance=1, description=describe())

            from ..bench.grid import DEFAULT_TRAIN_PREFIX

            backend.run(todo, output_dir, prefix=TRAIN_PREFIX or DEFAULT_TRAIN_PREFIX, on_result=on_result)
    table, groups, paths = aggregate.write_tables(output_dir, layout, cells, procedure=args.procedure)
    console.print(Path(paths[0]).read_text(encoding="utf-8"), markup=False, highlight=False)
    console.print(f"{counts['done']} cells run, {counts['failed']} failed, {len(cells) - len(todo)} skipped as complete, "
                  f"in {time.monotonic() - t0:.0f} s; tables: {', '.join(str(p) for p in paths)}")
    if layout in page.LAYOUTS:
        console.print(f"the results page with the paper's numbers and a verdict per claim: kneas-bench page --output-dir {output_dir}")
    if counts["failed"]:
        console.print(f"rerun the same command to retry the failed cells (their errors are in {output_dir}/cells/<cell id>/cell.json)")
        return 1
    return 0


def write_page(args: Page) -> int:
    from ..bench import page
    from ..engine.run_dir import check_writable

    output_dir = Path(args.output_dir)
    if not output_dir.is_dir():
        raise ConfigError(f"{output_dir} does not exist; run a table first (kneas-bench table1|views|ablation --output-dir {output_dir})")
    if not page.table_names(output_dir):
        raise ConfigError(f"no table has run in {output_dir} (no {', '.join(l + page.MANIFEST_SUFFIX for l in page.LAYOUTS)}); "
                          "run kneas-bench table1|views|ablation --output-dir DIR first, or pass that DIR")
    check_writable(Path(args.write).parent, needed_bytes=0)
    path = page.write_page(output_dir, args.write, command=f"kneas-bench page --output-dir {args.output_dir} --write {args.write}")
    console.print(f"results page: {path}")
    return 0


def write_archive(args: Archive) -> int:
    from ..bench.archive import archive
    from ..engine.run_dir import check_writable

    source, target = Path(args.output_dir), Path(args.to)
    if not (source / "cells").is_dir():
        raise ConfigError(f"{source} holds no cells (no {source}/cells); pass the folder a table ran in (--output-dir DIR)")
    if source.resolve() == target.resolve():
        raise ConfigError(f"--output-dir and --to are the same folder ({source}); pass another --to")
    check_writable(target, needed_bytes=0, flag="--to")
    done = archive(source, target)
    console.print(f"archived {done.files} records of {done.cells} cells ({done.bytes / 1e6:.1f} MB) from {source} to {target}; "
                  f"{done.skipped} files left behind (volumes, checkpoints, meshes)")
    return 0


def main(argv: Optional[Sequence[str]] = None) -> None:
    """Console entry point ``kneas-bench``."""

    def body():
        from ..bench.backends import _sigterm_as_interrupt

        _sigterm_as_interrupt()
        args = parse_args(sys.argv[1:] if argv is None else argv)
        if isinstance(args, Page):
            return write_page(args)
        return write_archive(args) if isinstance(args, Archive) else run(args)

    run_cli(body)


if __name__ == "__main__":
    main()
