"""Experiments at scale: ``kneas-bench`` expands the paper's tables into cells
(each an ordinary ``kneas-train`` run), runs them on a backend (local, local
workers, Ray), skips complete cells, and aggregates the tables.

- :mod:`.grid`: cells and the table grids (Table 1, views, ablation, any grid).
- :mod:`.cells`: running and recording one cell (``OUT/cells/<id>/cell.json``).
- :mod:`.backends`: ``local`` (serial / N workers, one GPU each) and ``ray``.
- :mod:`.aggregate`: mean ± std over seeds, the paper's layouts, Markdown + CSV.
- :mod:`.paper_results`: the paper's published numbers.
- :mod:`.estimate`: dry-run cost estimates.
- :mod:`.page`: the results page (``kneas-bench page``): the tables run, the paper's beside, a verdict per claim.
- :mod:`.archive`: the tables' records without their volumes (``kneas-bench archive``), to keep or to continue elsewhere.
"""

from .grid import Cell

__all__ = ["Cell"]
