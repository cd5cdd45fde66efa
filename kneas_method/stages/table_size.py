"""The hash table's size follows the scan's noise (``--stages.table-size.*``).

A larger hash table carries more of real anatomy's texture where the views determine it, and fits more
of the noise where they do not: 2^19 entries a level against the cpu preset's 2^16 gained 0.3-1.0 dB on
clean real scans and stayed within 0.2 dB on the built-in phantoms or above, and lost 0.16-0.63 dB on
most noisy scans (docs/experiments.md, 2026-12-06 and 2026-12-07). Where the classical start's
projections fit the views to their noise (``classical_start.start_fit``), the views hold no more detail
than the start has, and the model keeps the preset's table; elsewhere the table is raised.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from ..config import at_least
from .base import RunState, Stage, StageConfig
from .classical_start import start_fit


@dataclass
class TableSizeConfig(StageConfig):
    """Where the classical start is above the data's noise (a clean scan), the model's hash table gets at
    least ``2**clean_log2_hashmap_size`` entries a level; where it is at the noise, the preset's. Models
    whose encoding has no hash table are left as they are. ``config.json`` records the table trained.

    Attributes:
        clean_log2_hashmap_size: log2 of the entries a level on a clean scan (the finest levels are hashed
            into them; the coarse, dense levels do not change).
    """

    _target = "kneas_method.stages.table_size:TableSize"
    name = "table-size"
    phase = "start"
    needs = ("classical-start",)
    clean_log2_hashmap_size: int = field(default=19, metadata=at_least(1))

    def describe(self) -> str:
        return (f"table size: the hash table raised to 2^{self.clean_log2_hashmap_size} entries a level where the start is above "
                "the data's noise (a clean scan's texture), the preset's where it is at the noise")


class TableSize(Stage):
    def run(self, state: RunState) -> None:
        model = state.config.model
        options = dict(model.encoding_options or {})
        fit = start_fit(state)
        if fit is None or "log2_hashmap_size" not in options:
            return
        size = int(options["log2_hashmap_size"])
        if not fit["at_noise"]:
            size = max(size, int(self.config.clean_log2_hashmap_size))
        state.records[self.name] = {"log2_hashmap_size": size, "start_at_noise": bool(fit["at_noise"])}
        if size == int(options["log2_hashmap_size"]):
            state.say(f"table size: 2^{size} entries a level (the preset's" + (": the start is at the data's noise)" if fit["at_noise"] else ")"))
            return
        options["log2_hashmap_size"] = size
        state.config = dataclasses.replace(state.config, model=dataclasses.replace(model, encoding_options=options))
        state.say(f"table size: 2^{size} entries a level, where the preset has 2^{int(model.encoding_options['log2_hashmap_size'])}: the start "
                  "is above the data's noise, so the views hold detail a larger table can carry (--skip-stages table-size keeps the preset's)")
