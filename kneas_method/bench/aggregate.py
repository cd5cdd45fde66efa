"""Aggregate finished cells into the paper's tables (Markdown + CSV).

For each group of cells that differ only by seed: mean ± sample standard
deviation (ddof = 1) over the seeds that finished; a single seed shows the
mean alone, fewer seeds than asked for add ``(n=1/3)``, a group whose seeds all
failed shows ``failed``, one never run ``—``.

Layouts (``kneas-bench``):

- ``table1`` (paper Table 1): rows Scene x Config (1M..4M), per metric (2D PSNR,
  2D SSIM, 3D PSNR, 3D SSIM) a NeAS and a K-NeAS column. NeAS 1M = ``neas-1m``,
  NeAS 2M = ``neas-2m`` (no NeAS 3M/4M: ``—``), K-NeAS KM = ``k-neas`` with K
  materials. Best per scene and metric in bold (among the learned models).
- ``views`` (Table 2): rows Scene x #views, NeAS (``neas-2m``) and K-NeAS
  (``k-neas`` K = 2) columns, then a "K-NeAS, K found" row (``k-neas`` with no K
  given) where it ran; bold marks the best learned row at each view count.
- ``ablation`` (Table 3): one row per ablation method; bold = best per scene.
- ``grid``: one row per (scene, method, K, views); bold = best per scene.

Every table has one row per classical reference method that was run
(:data:`~.grid.REFERENCE_METHODS`: "FDK (ref.)", "SART (ref.)", "OS-SART (ref.)",
"CGLS (ref.)", "ASD-POCS (ref.)") per scene (and per view count): its values
sit in the first model column of each metric, and it is never bold. When a scene's runs used the public benchmark (``scene_source`` in
``metrics.json`` starts with "public benchmark"), the paper's published value
stands beside ours in a ``(paper)`` column; for built-in phantoms the paper
column stays empty, because the numbers are not comparable.
"""

from __future__ import annotations

import csv
import io
import math
import statistics
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path, PurePath
from typing import Any, Optional, Sequence

from ..engine import machine
from ..engine.code_version import describe
from ..engine.run_dir import read_json
from . import paper_results as paper
from .cells import cell_dir, find_metrics, read_cell_record
from .grid import ORACLE_ITERATIONS, ORACLE_SUFFIX, REFERENCE_METHODS, Cell, is_reference

METRICS = paper.METRICS  # shown in the tables
CSV_EXTRA_METRICS = ("psnr3d_ls",)  # also in the CSV files
PUBLIC_PREFIX = "public benchmark"  # metrics.json scene_source of NAF's published scenes
BUILTIN_PREFIX = "built-in phantom"  # ... and of the built-in phantoms
DECIMALS = 3
FOUND_K_LABEL = "K-NeAS, K found"  # Table 2's row of k-neas run without --num-materials


def _float(v: Any) -> Optional[float]:
    try:
        x = float(v)
    except (TypeError, ValueError):
        return None
    return x


@dataclass
class Group:
    """All seeds of one (scene, method, K, views)."""

    key: tuple
    expected: int = 0
    values: dict[str, list[float]] = field(default_factory=dict)
    failed: int = 0
    errors: list[str] = field(default_factory=list)
    sources: set[str] = field(default_factory=set)
    done: int = 0  # seeds with a metrics.json
    seconds: float = 0.0  # their recorded wall time, summed
    materials: set[int] = field(default_factory=set)  # the K each run used (metrics.json num_materials)
    code: Counter = field(default_factory=Counter)  # runs per code label (metrics.json code, engine.code_version.describe)
    machines: Counter = field(default_factory=Counter)  # runs per machine label (metrics.json machine, engine.machine.describe)
    days: set[str] = field(default_factory=set)  # the days (YYYY-MM-DD) their cells started on (cell.json started)

    @property
    def n(self) -> int:
        return max((len(v) for v in self.values.values()), default=0)

    @property
    def public(self) -> bool:
        return bool(self.sources) and all(s.startswith(PUBLIC_PREFIX) for s in self.sources)

    def mean(self, metric: str) -> Optional[float]:
        vals = [v for v in self.values.get(metric, []) if math.isfinite(v)]
        return statistics.fmean(vals) if vals else None

    def std(self, metric: str) -> Optional[float]:
        vals = [v for v in self.values.get(metric, []) if math.isfinite(v)]
        return statistics.stdev(vals) if len(vals) > 1 else None


def collect(output_dir: str | Path, cells: Sequence[Cell]) -> dict[tuple, Group]:
    """Read every cell's ``metrics.json`` (or its failure record) into groups over seeds."""
    groups: dict[tuple, Group] = {}
    for cell in cells:
        g = groups.setdefault(cell.group, Group(cell.group))
        g.expected += 1
        m = find_metrics(cell_dir(output_dir, cell), cell.method)
        if m is None:
            rec = read_cell_record(output_dir, cell)
            if rec and rec.get("status") == "failed":
                g.failed += 1
                g.errors.append(str(rec.get("error") or "")[:200])
            continue
        data = read_json(m, "metrics file")
        g.done += 1
        g.seconds += _float(data.get("wall_time_s")) or 0.0
        g.code[describe(data.get("code"))] += 1
        g.machines[machine.describe(data.get("machine"))] += 1
        started = (read_cell_record(output_dir, cell) or {}).get("started")
        if isinstance(started, str) and len(started) >= 10:
            g.days.add(started[:10])
        if isinstance(data.get("num_materials"), int):
            g.materials.add(data["num_materials"])
        if cell.oracle:  # the best count's 3D figures; the 2D ones are of the last count's volume, not shown
            data = {**(data.get("trace") or {}).get("best", {}), "scene_source": data.get("scene_source")}
        for metric in (*METRICS, *CSV_EXTRA_METRICS):
            x = _float(data.get(metric))
            if x is not None:
                g.values.setdefault(metric, []).append(x)
        if data.get("scene_source"):
            g.sources.add(str(data["scene_source"]))
    return groups


# ---------------------------------------------------------------------------- table model


@dataclass
class Row:
    labels: list[str]
    bold_scope: str  # rows with the same scope compete for bold
    entries: dict[tuple[str, str], Optional[tuple]]  # (metric, model column) -> group key
    paper: dict[tuple[str, str], Optional[float]] = field(default_factory=dict)
    reference: bool = False  # a classical reference row (never bold)
    scene: str = ""


@dataclass
class Table:
    name: str
    title: str
    label_headers: list[str]
    models: list[str]  # model columns per metric, e.g. ["NeAS", "K-NeAS"] or [""]
    rows: list[Row]
    notes: list[str] = field(default_factory=list)
    paper_columns: bool = False


def _fmt(x: Optional[float]) -> str:
    return "" if x is None else f"{x:.{DECIMALS}f}"


def _entry_text(g: Optional[Group], metric: str) -> str:
    if g is None:
        return "—"
    mean = g.mean(metric)
    if mean is None:
        return "failed" if g.failed else "—"
    text = _fmt(mean)
    sd = g.std(metric)
    if sd is not None:
        text += f" ± {_fmt(sd)}"
    if g.n < g.expected:
        text += f" (n={g.n}/{g.expected})"
    return text


def _bold(table: Table, groups: dict[tuple, Group]) -> set[tuple[int, str, str]]:
    """(row index, metric, model) entries that are the best of their scope (higher is better)."""
    best: dict[tuple[str, str], float] = {}
    for row in table.rows:
        if row.reference:
            continue
        for (metric, model), key in row.entries.items():
            g = groups.get(key) if key else None
            m = g.mean(metric) if g else None
            if m is not None:
                k = (row.bold_scope, metric)
                best[k] = max(best.get(k, -math.inf), round(m, DECIMALS))
    out = set()
    for i, row in enumerate(table.rows):
        if row.reference:
            continue
        for (metric, model), key in row.entries.items():
            g = groups.get(key) if key else None
            m = g.mean(metric) if g else None
            if m is not None and round(m, DECIMALS) == best.get((row.bold_scope, metric)):
                out.add((i, metric, model))
    return out


def _header(metric: str, model: str) -> str:
    label = paper.METRIC_LABELS[metric]
    return f"{label} {model}".strip()


def to_markdown(table: Table, groups: dict[tuple, Group]) -> str:
    bold = _bold(table, groups)
    headers = list(table.label_headers)
    for metric in METRICS:
        for model in table.models:
            headers.append(_header(metric, model))
            if table.paper_columns:
                headers.append(_header(metric, model) + " (paper)")
    lines = [f"## {table.title}", "", "| " + " | ".join(headers) + " |",
             "|" + "|".join([":--"] * len(table.label_headers) + ["--:"] * (len(headers) - len(table.label_headers))) + "|"]
    for i, row in enumerate(table.rows):
        cells = list(row.labels)
        if row.scene and cells[0] == row.scene:  # a scene file by its name: the CSV files keep the path
            cells[0] = scene_name(row.scene)
        for metric in METRICS:
            for model in table.models:
                key = row.entries.get((metric, model))
                g = groups.get(key) if key else None
                text = _entry_text(g, metric) if key else "—"
                if (i, metric, model) in bold:
                    text = f"**{text}**"
                cells.append(text)
                if table.paper_columns:
                    cells.append(_fmt(row.paper.get((metric, model))) or "—")
        lines.append("| " + " | ".join(cells) + " |")
    if table.notes:
        lines.append("")
        lines += [f"- {n}" for n in table.notes]
    return "\n".join(lines) + "\n"


def _csv_key(model: str) -> str:
    return {"NeAS": "neas", "K-NeAS": "kneas", "": ""}.get(model, model.lower().replace(" ", "_"))


def to_csv(table: Table, groups: dict[tuple, Group]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    header = [h.lower().replace(" ", "_").replace("#", "n") for h in table.label_headers] + ["reference"]
    metrics = (*METRICS, *CSV_EXTRA_METRICS)
    for metric in metrics:
        for model in table.models:
            base = "_".join(p for p in (metric, _csv_key(model)) if p)
            header += [f"{base}_mean", f"{base}_std", f"{base}_n"]
            if table.paper_columns and metric in METRICS:
                header.append(f"{base}_paper")
    header.append("scene_source")
    w.writerow(header)
    for row in table.rows:
        out: list[Any] = list(row.labels) + [int(row.reference)]
        sources: set[str] = set()
        for metric in metrics:
            for model in table.models:
                key = row.entries.get((metric, model)) or row.entries.get((METRICS[0], model))
                g = groups.get(key) if key else None
                if g is not None:
                    sources |= g.sources
                mean = g.mean(metric) if g else None
                sd = g.std(metric) if g else None
                out += ["" if mean is None else f"{mean:.6f}", "" if sd is None else f"{sd:.6f}", g.n if g else 0]
                if table.paper_columns and metric in METRICS:
                    p = row.paper.get((metric, model))
                    out.append("" if p is None else f"{p:.3f}")
        out.append("; ".join(sorted(sources)))
        w.writerow(out)
    return buf.getvalue()


# ---------------------------------------------------------------------------- layouts


def _scenes(cells: Sequence[Cell]) -> list[str]:
    return list(dict.fromkeys(c.scene for c in cells))


def scene_name(scene: str) -> str:
    """How a table names a scene: a built-in name as it is, a scene file by its file name."""
    return PurePath(scene).name


def _public_scenes(groups: dict[tuple, Group]) -> set[str]:
    return {key[0] for key, g in groups.items() if g.public}


def _source_note(groups: dict[tuple, Group], scenes: Sequence[str], with_paper: bool) -> list[str]:
    public = _public_scenes(groups)
    sources = {s: set().union(*(g.sources for k, g in groups.items() if k[0] == s)) for s in scenes if s not in public}
    builtin = [s for s, src in sources.items() if src and all(x.startswith(BUILTIN_PREFIX) for x in src)]
    own = [s for s, src in sources.items() if src and s not in builtin]
    notes = []
    if builtin:
        notes.append(f"{', '.join(map(scene_name, builtin))}: built-in synthetic phantom(s), not the public NAF benchmark; "
                     "the paper's published numbers are not comparable and are not shown for them.")
    if own:
        notes.append(f"{', '.join(map(scene_name, own))}: scene file(s) of their own, not the public NAF benchmark; "
                     "the paper's published numbers are not comparable and are not shown for them.")
    if with_paper:
        notes.append("(paper) columns: the published numbers of the K-NeAS paper for the public benchmark; its 3D PSNR "
                     "is computed after least-squares rescaling (our psnr3d_ls in the CSV), ours above uses the exact unit conversion.")
    return notes


def reference_label(method: str) -> str:
    """Display name of a classical reference row: ``fdk`` -> "FDK (ref.)", ``os-sart`` -> "OS-SART (ref.)",
    ``asd-pocs@best`` -> "ASD-POCS best of 1-40 (oracle)"."""
    if method.endswith(ORACLE_SUFFIX):
        return f"{method[:-len(ORACLE_SUFFIX)].upper()} best of 1-{ORACLE_ITERATIONS} (oracle)"
    return f"{method.upper()} (ref.)"


def _references(cells: Sequence[Cell]) -> list[str]:
    """The classical reference rows among ``cells``: the methods in :data:`REFERENCE_METHODS` order, then
    their oracles (``asd-pocs@best``)."""
    present = {c.group[1] for c in cells}
    return [m for m in REFERENCE_METHODS if m in present] + [m + ORACLE_SUFFIX for m in REFERENCE_METHODS if m + ORACLE_SUFFIX in present]


def _common_notes(cells: Sequence[Cell]) -> list[str]:
    seeds = sorted({c.seed for c in cells if not is_reference(c.method)})
    presets = sorted({c.preset for c in cells})
    spread = (f"mean ± sample std over seeds {', '.join(map(str, seeds))}" if len(seeds) > 1
              else f"one seed ({seeds[0]}): no spread" if seeds else "classical references only")
    note = f"{spread}; preset {', '.join(presets)}; bold = best of our learned models"
    refs = [m for m in _references(cells) if not m.endswith(ORACLE_SUFFIX)]
    oracles = [m[:-len(ORACLE_SUFFIX)] for m in _references(cells) if m.endswith(ORACLE_SUFFIX)]
    if refs or oracles:
        note += " (classical references excluded)"
    if refs:
        labels = ", ".join(m.upper() for m in refs)
        note += (f"; (ref.) rows = classical references {labels} (one deterministic run each, at the count a user gets by default; "
                 "their values are in the first column of each metric)")
    if oracles:
        note += (f"; (oracle) rows = {', '.join(m.upper() for m in oracles)} run {ORACLE_ITERATIONS} iterations with every count "
                 "scored against the truth, the best count's 3D figures (no user can pick it from the projections; the 2D "
                 "columns stay empty)")
    return [note + "."]


def table1(cells: Sequence[Cell], groups: dict[tuple, Group]) -> Table:
    models = ["NeAS", "K-NeAS"]
    public = _public_scenes(groups)
    ks = sorted({c.k for c in cells if c.method in ("neas-1m", "neas-2m", "k-neas") and c.k is not None})
    views = next((c.views for c in cells), None)
    rows = []
    for s in _scenes(cells):
        for k in ks:
            neas = (s, f"neas-{k}m", k, views) if k in (1, 2) else None
            kne = (s, "k-neas", k, views)
            entries, pap = {}, {}
            for metric in METRICS:
                entries[(metric, "NeAS")] = neas if neas in groups else None
                entries[(metric, "K-NeAS")] = kne if kne in groups else None
                if s in public and (views is None or views == 50):
                    pap[(metric, "NeAS")] = paper.table1_value(s, f"neas-{k}m", k, metric) if k in (1, 2) else None
                    pap[(metric, "K-NeAS")] = paper.table1_value(s, "k-neas", k, metric)
            rows.append(Row([s, f"{k}M"], s, entries, pap, scene=s))
        for ref in _references(cells):
            key = (s, ref, None, views)
            if key in groups:
                rows.append(Row([s, reference_label(ref)], s, {(m, "NeAS"): key for m in METRICS}, reference=True, scene=s))
    with_paper = bool(public)
    title = "Table 1: NeAS vs K-NeAS across scenes and material counts" + (f" ({views} views)" if views else "")
    return Table("table1", title, ["Scene", "Config"], models, rows,
                 _common_notes(cells) + _source_note(groups, _scenes(cells), with_paper), with_paper)


def views_k(cells: Sequence[Cell]) -> int:
    """The K that Table 2's K-NeAS rows were given (the found-K row has none; 2 when none ran)."""
    return next((c.k for c in cells if c.method == "k-neas" and c.k is not None), 2)


def views_table(cells: Sequence[Cell], groups: dict[tuple, Group]) -> Table:
    models = ["NeAS", "K-NeAS"]
    public = _public_scenes(groups)
    views = sorted({c.views for c in cells if c.views is not None})
    k = views_k(cells)
    rows = []
    for s in _scenes(cells):
        for v in views:
            entries, pap = {}, {}
            for metric in METRICS:
                for model, method in (("NeAS", "neas-2m"), ("K-NeAS", "k-neas")):
                    key = (s, method, 2 if method == "neas-2m" else k, v)
                    entries[(metric, model)] = key if key in groups else None
                    if s in public:
                        pap[(metric, model)] = paper.table2_value(s, method, key[2], v, metric)
            rows.append(Row([s, str(v)], f"{s}/{v}", entries, pap, scene=s))
            found = (s, "k-neas", None, v)  # k-neas as a user runs it: K from the bounds
            if found in groups:
                ks = "/".join(map(str, sorted(groups[found].materials))) or "?"
                rows.append(Row([s, f"{v} {FOUND_K_LABEL} (K = {ks})"], f"{s}/{v}", {(m, "K-NeAS"): found for m in METRICS}, scene=s))
        for v in views:
            for ref in _references(cells):
                key = (s, ref, None, v)
                if key in groups:
                    rows.append(Row([s, f"{v} {reference_label(ref)}"], f"{s}/{v}", {(m, "NeAS"): key for m in METRICS},
                                    reference=True, scene=s))
    notes = _common_notes(cells)
    notes[0] = notes[0].replace("bold = best of our learned models", "bold = the best learned row at each view count")
    return Table("table2_views", f"Table 2: sparse views, NeAS (neas-2m) vs K-NeAS (k-neas, K = {k})", ["Scene", "# Views"], models, rows,
                 notes + _source_note(groups, _scenes(cells), bool(public)), bool(public))


def ablation_table(cells: Sequence[Cell], groups: dict[tuple, Group]) -> Table:
    public = _public_scenes(groups)
    methods = list(dict.fromkeys(c.method for c in cells if not is_reference(c.method)))
    rows = []
    for s in _scenes(cells):
        for method in methods:
            keys = [key for key in groups if key[0] == s and key[1] == method]
            for key in keys:
                label = paper.ABLATION_ROWS.get(method, method)
                entries = {(m, ""): key for m in METRICS}
                pap = {(m, ""): paper.table3_value(s, method, key[2], m) for m in METRICS} if s in public and key[3] in (None, 50) else {}
                rows.append(Row([s, label, method, str(key[2])], s, entries, pap, scene=s))
        for ref in _references(cells):
            for key in [key for key in groups if key[0] == s and key[1] == ref]:
                rows.append(Row([s, reference_label(ref), ref, "—"], s, {(m, ""): key for m in METRICS}, reference=True, scene=s))
    return Table("table3_ablation", "Table 3: component ablation", ["Scene", "Variant", "Method", "K"], [""], rows,
                 _common_notes(cells) + _source_note(groups, _scenes(cells), bool(public)), bool(public))


def grid_table(cells: Sequence[Cell], groups: dict[tuple, Group]) -> Table:
    public = _public_scenes(groups)
    rows = []
    for s in _scenes(cells):
        for key in [k for k in groups if k[0] == s]:
            _, method, k, v = key
            entries = {(m, ""): key for m in METRICS}
            pap = {(m, ""): paper.paper_value(s, method, k, v, m) for m in METRICS} if s in public else {}
            rows.append(Row([s, method, "—" if k is None else str(k), "all" if v is None else str(v)], s, entries, pap,
                            reference=is_reference(method), scene=s))
    return Table("grid", "Grid results", ["Scene", "Method", "K", "Views"], [""], rows,
                 _common_notes(cells) + _source_note(groups, _scenes(cells), bool(public)), bool(public))


LAYOUTS = {"table1": table1, "views": views_table, "ablation": ablation_table, "grid": grid_table}


def cells_csv(output_dir: str | Path, cells: Sequence[Cell]) -> str:
    """One line per cell (per seed): its status and raw metrics."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    metrics = (*METRICS, *CSV_EXTRA_METRICS)
    w.writerow(["cell_id", "scene", "method", "k", "views", "seed", "preset", "status", *metrics, "wall_time_s", "steps", "scene_source", "run_dir"])
    for c in cells:
        m = find_metrics(cell_dir(output_dir, c), c.method)
        data: dict = {}
        status = "missing"
        if m is not None:
            data, status = read_json(m, "metrics file"), "done"
        else:
            rec = read_cell_record(output_dir, c)
            if rec:
                status = str(rec.get("status", "missing"))
        w.writerow([c.id, c.scene, c.method, "" if c.k is None else c.k, "" if c.views is None else c.views, c.seed, c.preset, status,
                    *[data.get(k, "") for k in metrics], data.get("wall_time_s", ""), data.get("steps", ""), data.get("scene_source", ""),
                    str(m.parent) if m else ""])
    return buf.getvalue()


def write_tables(output_dir: str | Path, layout: str, cells: Sequence[Cell],
                 procedure: Optional[str] = None) -> tuple[Table, dict[tuple, Group], list[Path]]:
    """Aggregate and write ``<name>.md``, ``<name>.csv`` and ``<name>_cells.csv`` into ``output_dir``, ``name``
    the table's own (``table1_k_materials``), followed by ``@procedure`` for a table run with another procedure."""
    from ..engine.run_dir import check_writable

    out = check_writable(output_dir, needed_bytes=0)
    groups = collect(output_dir, cells)
    table = LAYOUTS[layout](cells, groups)
    name = table.name + ("" if procedure is None else f"@{procedure}")
    md, cv = out / f"{name}.md", out / f"{name}.csv"
    per_cell = out / f"{name}_cells.csv"
    for path, text in ((md, to_markdown(table, groups)), (cv, to_csv(table, groups)), (per_cell, cells_csv(output_dir, cells))):
        tmp = path.with_suffix(path.suffix + ".tmp")
        tmp.write_text(text, encoding="utf-8")
        tmp.replace(path)
    return table, groups, [md, cv, per_cell]
