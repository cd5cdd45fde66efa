"""Keeping a table's results without its volumes: ``kneas-bench archive``.

A table's output folder holds every cell's volumes and checkpoints (hundreds of
MB); the tables and the results page need only the records: the manifests
(``table1.cells.json``, ...), each cell's ``cell.json`` and ``train.log``, and
each run's JSON files (``metrics.json``, ``config.json``, ``bounds.json``, ...).
:func:`archive` copies those from one output folder to another. The copy is
itself an output folder: ``kneas-bench page`` reads it, and copied back into a
working folder it lets a table continue on another machine, since a cell with a
``metrics.json`` is complete and never runs again.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

from .cells import CELLS, is_finished
from .page import add_to_manifest, read_manifest, table_names

RECORD_SUFFIXES = (".json", ".log")
# A record larger than this is not a record (a run's JSON and logs are a few KB); it stays behind.
MAX_RECORD_BYTES = 1 << 20


@dataclass
class ArchiveResult:
    cells: int  # cell folders with at least one record copied
    files: int  # files copied
    bytes: int
    skipped: int  # files left behind (volumes, checkpoints, meshes, oversized records)


def is_record(path: Path) -> bool:
    return path.suffix in RECORD_SUFFIXES and path.stat().st_size <= MAX_RECORD_BYTES


def archive(source: str | Path, target: str | Path) -> ArchiveResult:
    """Copy the manifests and the records of every finished cell under ``source`` to ``target``.

    A record already in ``target`` is replaced by ``source``'s; cells only in
    ``target`` are kept, and each manifest in ``target`` becomes the union of both
    (so archiving the cells of several sittings, or machines, into one folder
    keeps every table whole).
    """
    source, target = Path(source), Path(target)
    cells = files = size = skipped = 0
    for name in table_names(source):
        add_to_manifest(target, name, read_manifest(source, name) or [])
    root = source / CELLS
    for folder in sorted(p for p in root.iterdir() if p.is_dir()) if root.is_dir() else []:
        if not is_finished(folder):  # a running or interrupted cell's records are partial: it reruns or resumes
            continue
        copied = 0
        for path in sorted(p for p in folder.rglob("*") if p.is_file()):
            if not is_record(path):
                skipped += 1
                continue
            dest = target / path.relative_to(source)
            dest.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(path, dest)
            copied += 1
            size += path.stat().st_size
        cells += copied > 0
        files += copied
    return ArchiveResult(cells, files, size, skipped)
