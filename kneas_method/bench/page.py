"""The results page of the paper's three experiments: ``kneas-bench page`` writes ``docs/paper_tables.md``.

Each table run (``kneas-bench table1|views|ablation``) leaves a manifest of its
cells in its output folder (``table1.cells.json``, ...; a table run with another fitting
procedure than the preset's, ``--procedure paper``, is its own table: ``table1@paper.cells.json``,
shown after the default's with its own verdicts). The page is built from
those manifests and the cells' ``metrics.json`` alone, never typed: for each
table present, our table in the paper's layout (:mod:`.aggregate`), the paper's
published table beside it (:mod:`.paper_results`), and one verdict line per
claim of the paper: *holds*, *does not hold* or *not comparable*, with why.

A claim compares two rows of ours the way the paper compares them (3D PSNR,
the paper's headline metric; the sign of the difference is what is checked,
since our scenes are not the paper's data). Two rows closer than the seed
spread cannot decide a claim: with several seeds, closer than one sample
standard deviation; with one seed, closer than :data:`ONE_SEED_SPREAD_DB`.
Missing or failed cells make a claim *not comparable*, and the line says which.

Scenes are matched to the paper's scene of the same anatomy by name (``foot``,
``abdomen``, ``ts-chest.pickle`` -> Chest): only to put the paper's numbers and
claims beside ours, never to change how a scene is run.
"""

from __future__ import annotations

import math
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence

from ..engine.run_dir import read_json, write_json
from . import aggregate
from . import paper_results as paper
from .aggregate import Group
from .grid import Cell, is_reference

LAYOUTS = ("table1", "views", "ablation")
MANIFEST_SUFFIX = ".cells.json"
# Two one-seed rows closer than this cannot decide a claim: the default procedure's runs moved by
# 0.1-0.9 dB between seeds on the built-in scenes (docs/results.md, "The seed").
ONE_SEED_SPREAD_DB = 0.3
CLAIM_METRIC = "psnr3d"
HOLDS, FAILS, NOT_COMPARABLE = "holds", "does not hold", "not comparable"


# ---------------------------------------------------------------------------- manifests


PROCEDURE_SEP = "@"  # table1@paper: Table 1 with its neural cells fitted by the paper's procedure


def table_name(layout: str, procedure: Optional[str] = None) -> str:
    """The name a table run is recorded under: ``table1``, or ``table1@paper`` with ``--procedure paper``."""
    return layout if procedure is None else f"{layout}{PROCEDURE_SEP}{procedure}"


def split_table_name(name: str) -> tuple[str, Optional[str]]:
    """``table1@paper`` -> ``("table1", "paper")``; ``table1`` -> ``("table1", None)``."""
    layout, _, procedure = name.partition(PROCEDURE_SEP)
    return layout, procedure or None


def table_names(output_dir: str | Path) -> list[str]:
    """Every table recorded in ``output_dir``, in :data:`LAYOUTS` order, each layout's default procedure first."""
    out = []
    for layout in LAYOUTS:
        if manifest_path(output_dir, layout).is_file():
            out.append(layout)
        out += sorted(p.name[:-len(MANIFEST_SUFFIX)] for p in Path(output_dir).glob(f"{layout}{PROCEDURE_SEP}*{MANIFEST_SUFFIX}"))
    return out


def manifest_path(output_dir: str | Path, layout: str) -> Path:
    """The manifest of the table recorded as ``layout`` (a :func:`table_name`)."""
    return Path(output_dir) / f"{layout}{MANIFEST_SUFFIX}"


def write_manifest(output_dir: str | Path, layout: str, cells: Sequence[Cell]) -> Path:
    """Record which cells make up ``layout``'s table (the page reads it back)."""
    return write_json(manifest_path(output_dir, layout), {"layout": layout, "cells": [c.to_dict() for c in cells]})


def add_to_manifest(output_dir: str | Path, layout: str, cells: Sequence[Cell]) -> Path:
    """Add ``cells`` to ``layout``'s manifest (a table grown over several runs keeps every cell it had; a cell
    given again is recorded as given now, its shared folder included)."""
    given = {c.id: c for c in cells}
    known = [given.pop(c.id, c) for c in read_manifest(output_dir, layout) or []]
    return write_manifest(output_dir, layout, [*known, *given.values()])


def read_manifest(output_dir: str | Path, layout: str) -> Optional[list[Cell]]:
    """The cells of ``layout``'s table as its last run recorded them, or None when it never ran here."""
    path = manifest_path(output_dir, layout)
    if not path.is_file():
        return None
    data = read_json(path, "table manifest")
    return [Cell(d["scene"], d["method"], d.get("k"), d.get("views"), int(d["seed"]), d["preset"], tuple(d.get("extra") or ()),
                 bool(d.get("oracle", False)), d.get("folder")) for d in data.get("cells", [])]


# ---------------------------------------------------------------------------- scenes and rows


@dataclass
class Verdict:
    """One claim of the paper checked on one of our scenes."""

    claim: str
    scene: str
    status: str  # HOLDS, FAILS or NOT_COMPARABLE
    why: str

    def line(self) -> str:
        return f"- **{self.status}** — {self.claim} — on {aggregate.scene_name(self.scene)}: {self.why}"


def _mean(g: Optional[Group], metric: str = CLAIM_METRIC) -> Optional[float]:
    return g.mean(metric) if g is not None else None


def _missing(groups: dict[tuple, Group], keys: Sequence[tuple], names: Sequence[str]) -> Optional[str]:
    """Why some of ``keys`` have no value (never run, failed), or None when all have one."""
    out = []
    for key, name in zip(keys, names):
        g = groups.get(key)
        if g is None or _mean(g) is None:
            out.append(f"{name} {'failed' if g is not None and g.failed else 'not run'}")
    return "; ".join(out) or None


def _fmt(x: float) -> str:
    return f"{x:.2f}"


def compare(groups: dict[tuple, Group], a: tuple, b: tuple, name_a: str, name_b: str,
            paper_diff: Optional[float], expect_above: bool) -> tuple[str, str]:
    """``(status, why)`` of the claim "row a is above row b" (``expect_above``) or "below", in 3D PSNR.

    ``paper_diff`` (a - b in the paper, dB) is quoted in the reason when known.
    """
    missing = _missing(groups, [a, b], [name_a, name_b])
    if missing:
        return NOT_COMPARABLE, missing
    ga, gb = groups[a], groups[b]
    diff = _mean(ga) - _mean(gb)
    quoted = f"{name_a} − {name_b} = {diff:+.2f} dB ({_fmt(_mean(ga))} vs {_fmt(_mean(gb))})"
    if paper_diff is not None:
        quoted += f", paper {paper_diff:+.2f} dB"
    spreads = [g.std(CLAIM_METRIC) for g in (ga, gb)]
    if all(s is not None for s in spreads):
        spread = max(spreads)
        if abs(diff) <= spread:
            return NOT_COMPARABLE, f"{quoted}: within one standard deviation ({spread:.2f} dB over {min(ga.n, gb.n)} seeds)"
        seeds = f" ({min(ga.n, gb.n)} seeds, std ≤ {spread:.2f} dB)"
    else:
        if abs(diff) < ONE_SEED_SPREAD_DB:
            return NOT_COMPARABLE, (f"{quoted}: closer than the seed spread ({ONE_SEED_SPREAD_DB} dB) with one seed; "
                                    "rerun with --seeds 3")
        seeds = " (one seed)"
    holds = diff > 0 if expect_above else diff < 0
    return (HOLDS if holds else FAILS), quoted + seeds


# ---------------------------------------------------------------------------- claims per table


def _paper_best(scene: str, model: str) -> tuple[Optional[float], Optional[str]]:
    rows = paper.TABLE1[scene]
    vals = [(rows[c][model]["psnr3d"], c) for c in rows if model in rows[c]]
    return max(vals) if vals else (None, None)


def table1_verdicts(cells: Sequence[Cell], groups: dict[tuple, Group]) -> list[Verdict]:
    """Claim 1: K-NeAS (its best K) against NeAS (its best of 1M/2M) per scene, in the paper's direction for
    that anatomy; and on abdomen, that K = 3 is K-NeAS's best."""
    out = []
    scenes = list(dict.fromkeys(c.scene for c in cells))
    views = next((c.views for c in cells), None)
    for s in scenes:
        ps = paper.scene_key(s, same_anatomy=True)
        neas = [k for k in ((s, "neas-1m", 1, views), (s, "neas-2m", 2, views)) if _mean(groups.get(k)) is not None]
        kneas = [k for k in groups if k[0] == s and k[1] == "k-neas" and k[3] == views and _mean(groups[k]) is not None]
        if ps is None:
            out.append(Verdict("K-NeAS against NeAS", s, NOT_COMPARABLE, "the paper has no scene of this anatomy"))
            continue
        p_k, p_kc = _paper_best(ps, "K-NeAS")
        p_n, p_nc = _paper_best(ps, "NeAS")
        above = p_k > p_n
        claim = (f"{ps}: K-NeAS {'above' if above else 'below'} NeAS (paper: best K-NeAS {p_k:.2f} at {p_kc} "
                 f"vs best NeAS {p_n:.2f} at {p_nc})")
        if not neas or not kneas:
            lacking = [name for name, have in (("NeAS", neas), ("K-NeAS", kneas)) if not have]
            out.append(Verdict(claim, s, NOT_COMPARABLE, f"no {' or '.join(lacking)} cell complete"))
        else:
            best_n = max(neas, key=lambda k: _mean(groups[k]))
            best_k = max(kneas, key=lambda k: _mean(groups[k]))
            status, why = compare(groups, best_k, best_n, f"K-NeAS {best_k[2]}M", f"NeAS {best_n[2]}M", p_k - p_n, above)
            out.append(Verdict(claim, s, status, why))
        if ps == "Abdomen":
            claim = f"Abdomen: K-NeAS best at K = 3 (paper: 3M {p_k:.2f}, next best {sorted(paper.TABLE1[ps][c]['K-NeAS']['psnr3d'] for c in paper.TABLE1[ps])[-2]:.2f})"
            three = (s, "k-neas", 3, views)
            others = [k for k in kneas if k[2] != 3]
            if _mean(groups.get(three)) is None or not others:
                out.append(Verdict(claim, s, NOT_COMPARABLE, _missing(groups, [three], ["K-NeAS 3M"]) or "no other K was run"))
            else:
                rival = max(others, key=lambda k: _mean(groups[k]))
                status, why = compare(groups, three, rival, "K-NeAS 3M", f"K-NeAS {rival[2]}M", None, True)
                out.append(Verdict(claim, s, status, why))
    return out


def views_verdicts(cells: Sequence[Cell], groups: dict[tuple, Group]) -> list[Verdict]:
    """Claim 2: K-NeAS above NeAS at 5/10/20 views, NeAS ahead at 50 (chest, K = 2); and the bar a user sets:
    K-NeAS (at K = 2, and with K found when that row ran) at or above the best classical reference at every
    view count, in 3D PSNR and 3D SSIM."""
    out = []
    k = aggregate.views_k(cells)
    views = sorted({c.views for c in cells if c.views is not None})
    for s in dict.fromkeys(c.scene for c in cells):
        ps = paper.scene_key(s, same_anatomy=True)
        for v in views:
            kn, ne = (s, "k-neas", k, v), (s, "neas-2m", 2, v)
            row = paper.TABLE2.get(v) if ps == paper.TABLE2_SCENE else None
            if row is not None:
                pd = row["K-NeAS"]["psnr3d"] - row["NeAS"]["psnr3d"]
                claim = f"{v} views: K-NeAS {'above' if pd > 0 else 'below'} NeAS (paper {row['K-NeAS']['psnr3d']:.2f} vs {row['NeAS']['psnr3d']:.2f})"
                status, why = compare(groups, kn, ne, f"K-NeAS {k}M", "NeAS 2M", pd, pd > 0)
                out.append(Verdict(claim, s, status, why))
            refs = [key for key in groups if key[0] == s and key[3] == v and is_reference(key[1]) and _mean(groups[key]) is not None]
            found = (s, "k-neas", None, v)
            rows = [(kn, f"K-NeAS {k}M")] + ([(found, aggregate.FOUND_K_LABEL)] if found in groups else [])
            for key, name in rows:
                claim = f"{v} views: {name} at or above the best classical row, oracle included (3D PSNR and 3D SSIM)"
                out.append(Verdict(claim, s, *_above_classical(groups, key, name, refs)))
    return out


def _above_classical(groups: dict[tuple, Group], key: tuple, name: str, refs: Sequence[tuple]) -> tuple[str, str]:
    """``(status, why)`` of "row ``key`` is at or above the best of ``refs`` in 3D PSNR and in 3D SSIM"."""
    if _mean(groups.get(key)) is None or not refs:
        return NOT_COMPARABLE, _missing(groups, [key], [name]) or "no classical reference run"
    parts, ok = [], True
    for metric, label, unit in (("psnr3d", "3D PSNR", " dB"), ("ssim3d", "3D SSIM", "")):
        best = max(refs, key=lambda r: groups[r].mean(metric) if groups[r].mean(metric) is not None else -math.inf)
        ours, theirs = groups[key].mean(metric), groups[best].mean(metric)
        if ours is None or theirs is None:
            parts.append(f"{label} missing")
            ok = False
            continue
        ok = ok and ours >= theirs
        parts.append(f"{label} {ours:.3f} vs {theirs:.3f} ({aggregate.reference_label(best[1])}, {ours - theirs:+.3f}{unit})")
    return (HOLDS if ok else FAILS), "; ".join(parts)


def ablation_verdicts(cells: Sequence[Cell], groups: dict[tuple, Group]) -> list[Verdict]:
    """Claim 3: each component adds: the floater regulariser and the shared body each above K-Selector alone,
    and the full K-NeAS at or above both."""
    out = []
    t3 = {label: row["psnr3d"] for label, row in paper.TABLE3.items()}
    for s in dict.fromkeys(c.scene for c in cells):
        keys = {c.method: c.group for c in cells if c.scene == s and not is_reference(c.method)}
        pairs = (("kselector-floater", "kselector"), ("kselector-shared", "kselector"), ("k-neas", "kselector-floater"),
                 ("k-neas", "kselector-shared"))
        for a, b in pairs:
            la, lb = paper.ABLATION_ROWS[a], paper.ABLATION_ROWS[b]
            pd = t3[la] - t3[lb]
            claim = f"{la} above {lb} (paper {t3[la]:.2f} vs {t3[lb]:.2f}, {paper.TABLE3_SCENE})"
            if a not in keys or b not in keys:
                out.append(Verdict(claim, s, NOT_COMPARABLE, f"{a if a not in keys else b} is not in this table"))
                continue
            status, why = compare(groups, keys[a], keys[b], la, lb, pd, True)
            out.append(Verdict(claim, s, status, why))
    return out


VERDICTS = {"table1": table1_verdicts, "views": views_verdicts, "ablation": ablation_verdicts}


# ---------------------------------------------------------------------------- the paper's tables


def _paper_table1() -> str:
    lines = ["| Scene | Config | 3D PSNR NeAS | 3D PSNR K-NeAS | 3D SSIM NeAS | 3D SSIM K-NeAS | 2D PSNR NeAS | 2D PSNR K-NeAS |",
             "|:--|:--|--:|--:|--:|--:|--:|--:|"]
    for scene, rows in paper.TABLE1.items():
        for config, models in rows.items():
            def v(model, metric):
                return f"{models[model][metric]:.3f}" if model in models else "—"
            lines.append(f"| {scene} | {config} | {v('NeAS', 'psnr3d')} | {v('K-NeAS', 'psnr3d')} | {v('NeAS', 'ssim3d')} | "
                         f"{v('K-NeAS', 'ssim3d')} | {v('NeAS', 'psnr2d')} | {v('K-NeAS', 'psnr2d')} |")
    return "\n".join(lines)


def _paper_table2() -> str:
    lines = ["| # Views | 3D PSNR NeAS | 3D PSNR K-NeAS | 3D SSIM NeAS | 3D SSIM K-NeAS | 2D PSNR NeAS | 2D PSNR K-NeAS |",
             "|:--|--:|--:|--:|--:|--:|--:|"]
    for v, row in paper.TABLE2.items():
        lines.append(f"| {v} | {row['NeAS']['psnr3d']:.3f} | {row['K-NeAS']['psnr3d']:.3f} | {row['NeAS']['ssim3d']:.3f} | "
                     f"{row['K-NeAS']['ssim3d']:.3f} | {row['NeAS']['psnr2d']:.3f} | {row['K-NeAS']['psnr2d']:.3f} |")
    return "\n".join(lines)


def _paper_table3() -> str:
    lines = ["| Variant | 3D PSNR | 3D SSIM | 2D PSNR | 2D SSIM |", "|:--|--:|--:|--:|--:|"]
    for label, row in paper.TABLE3.items():
        lines.append(f"| {label} | {row['psnr3d']:.3f} | {row['ssim3d']:.3f} | {row['psnr2d']:.3f} | {row['ssim2d']:.3f} |")
    return "\n".join(lines)


SECTIONS = {
    "table1": ("Table 1: K materials per scene", _paper_table1,
               "The paper's Table 1 (NAF's real-patient scenes, 50 views, mean of 3 runs, GPU)"),
    "views": ("Table 2: sparse views", _paper_table2,
              f"The paper's Table 2 ({paper.TABLE2_SCENE}, 2 materials, GPU)"),
    "ablation": ("Table 3: component ablation", _paper_table3,
                 f"The paper's Table 3 ({paper.TABLE3_SCENE}, 2 materials, one run, GPU)"),
}


# ---------------------------------------------------------------------------- the page


def render(output_dir: str | Path, command: str = "kneas-bench page") -> str:
    """The page's Markdown, from the manifests and cells under ``output_dir``."""
    parts = ["# The paper's experiments, run by kneas", "",
             f"Generated by `{command}` on {time.strftime('%Y-%m-%d')} from the cells under `{output_dir}`; do not edit by hand "
             "(rerun the tables, then the page). Our numbers are on the scenes named in each table (built-in phantoms, "
             "real patients' CT volumes projected as NAF's data are), the paper's on NAF's scenes: the absolute values "
             "are not comparable, the orderings the paper claims are, and each verdict line checks one.", ""]
    found = 0
    verdict_counts = {HOLDS: 0, FAILS: 0, NOT_COMPARABLE: 0}
    recorded = table_names(output_dir)
    for layout in LAYOUTS:
        title, paper_table, paper_title = SECTIONS[layout]
        names = [n for n in recorded if split_table_name(n)[0] == layout]
        if not names:
            parts += [f"## {title}", "", f"Not run here yet: `kneas-bench {layout} --output-dir {output_dir}` runs it.", ""]
            continue
        for name in names:
            procedure = split_table_name(name)[1]
            heading = title if procedure is None else f"{title}, the {procedure} procedure"
            parts += [f"## {heading}", ""]
            if procedure is not None:
                parts += [f"The neural cells fitted by `--procedure {procedure}` (`kneas-bench {layout} --procedure {procedure}`) "
                          "at the same preset; the classical rows are the same runs as the default table's.", ""]
            found += 1
            verdict_counts = _render_table(output_dir, layout, read_manifest(output_dir, name) or [], paper_table, paper_title,
                                           parts, verdict_counts)
    if not found:
        parts += ["No table has been run in this folder: run `kneas-bench table1|views|ablation --output-dir DIR`, "
                  "then `kneas-bench page --output-dir DIR`.", ""]
    summary = ", ".join(f"{n} {s}" for s, n in verdict_counts.items())
    parts.insert(4, f"Verdicts: {summary}.\n")
    return "\n".join(parts).rstrip() + "\n"


def _render_table(output_dir, layout: str, cells: list, paper_table, paper_title: str, parts: list, verdict_counts: dict) -> dict:
    """Append one table's section (ours, the paper's, the claims) to ``parts``; returns the verdict counts."""
    from .estimate import format_seconds

    groups = aggregate.collect(output_dir, cells)
    table = aggregate.LAYOUTS[layout](cells, groups)
    seconds, done = sum(g.seconds for g in groups.values()), sum(g.done for g in groups.values())
    ours = aggregate.to_markdown(table, groups).replace(f"## {table.title}", f"### Ours: {table.title}", 1)
    parts += [f"{done} of {len(cells)} cells complete, {format_seconds(seconds)} of recorded run time"
              + (f"; {provenance_line(groups)}." if done else "."), "", ours,
              f"### {paper_title}", "", paper_table(), "", "### Claims", ""]
    verdicts = VERDICTS[layout](cells, groups)
    for v in verdicts:
        verdict_counts[v.status] += 1
    parts += [v.line() for v in verdicts] or ["- no cells to check a claim on"]
    parts.append("")
    return verdict_counts


def provenance_line(groups: dict[tuple, Group]) -> str:
    """When, on which code and on which machines the complete cells ran: ``run 2026-12-04 to 2026-12-06;
    code: <commit> (n cells), not recorded (m cells); machines: <processor, cores, torch> (n cells), ...``,
    most cells first."""
    def counted(attr: str) -> str:
        counts = sum((getattr(g, attr) for g in groups.values()), Counter())
        return ", ".join(f"{label} ({n} cell{'s' if n != 1 else ''})" for label, n in counts.most_common())

    days = sorted(set().union(*(g.days for g in groups.values())))
    when = f"run {days[0]}" + (f" to {days[-1]}" if len(days) > 1 else "") + "; " if days else ""
    return when + "code: " + counted("code") + "; machines: " + counted("machines")


def write_page(output_dir: str | Path, path: str | Path, command: str = "kneas-bench page") -> Path:
    """Render the page and write it to ``path`` (atomically)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(render(output_dir, command), encoding="utf-8")
    tmp.replace(path)
    return path
