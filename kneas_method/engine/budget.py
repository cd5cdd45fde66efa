"""The run's time budget (``--trainer.time-budget``): small pure rules for what gives way.

A neural run's budget counts from the command's start (``engine.pipeline.train``). Training gives way
first, then the band-correction passes; the classical start and the evaluation never do.

* :func:`run_budget`: the seconds a run on a given grid may take.
* :func:`training_steps`: after ``TIMED_STEPS`` steps, how many training steps leave the passes their
  time before the budget runs out (training's last thousand steps are worth far less than the passes:
  abdomen 43.40 dB after 3000 steps and 12 passes, 43.46 after 4000; 41.57 after 4000 steps and 3 passes).
* :func:`pass_fits`: whether one more pass is expected to end in the time left.
"""

from __future__ import annotations

import math
from typing import Optional, Sequence

# Seconds of a run's time budget kept for what follows the passes: the smoothing (a projection and
# SURE; on a noisy scan its fit), the materials stage's mixtures, the evaluation and the report. On a
# clean scan they took 10 s (abdomen, 2-core Xeon, 75th stop); a noisy scan's passes stop at its noise
# long before any budget, and its refit of its materials (1-2 min) is not kept for.
TIME_RESERVE_S = 30.0
# The budget is for a volume of this many voxels or fewer; a larger one gets it in proportion to its voxels
# (the classical start, the passes and the evaluation grow with them: head-vox256's 256^3 grid took 20 min).
BUDGET_VOXELS = 128 ** 3
# What the training rule keeps for the passes, as a share of the whole training's time: the 12 passes
# took 0.56 (abdomen) and 0.60 (chest) of it on a 2-core Xeon (75th stop), 0.87 on head-256's 256²
# detector (AVX-512 EPYC, 73rd stop).
PASSES_SHARE = 0.9
# Steps timed before training's length is checked against the budget, and the least share of its
# steps training is cut to (where even that does not fit, the passes give way as well).
TIMED_STEPS = 100
MIN_STEPS_SHARE = 0.25


def run_budget(time_budget: Optional[float], n_voxel) -> Optional[float]:
    """Seconds a run on a grid of ``n_voxel`` (nx, ny, nz) voxels may take under ``--trainer.time-budget``
    ``time_budget`` (None or 0: no budget): the budget, times the grid's voxels over ``BUDGET_VOXELS``
    where it has more."""
    if not time_budget:
        return None
    return float(time_budget) * max(1.0, math.prod(int(n) for n in n_voxel) / BUDGET_VOXELS)


def training_steps(left: float, step: int, total: int, seconds_per_step: float, steps_per_epoch: int, passes: bool) -> int:
    """The training steps (whole epochs of ``steps_per_epoch``) that end with time left for the passes.

    ``left``: seconds until the budget runs out, less ``TIME_RESERVE_S``; ``step`` of ``total`` steps
    run, at ``seconds_per_step``; ``passes``: whether the run has band-correction passes, taken to cost
    ``PASSES_SHARE`` x the whole ``total`` steps' time. Returns ``total`` where everything fits, else
    the most whole epochs that do, at least ``MIN_STEPS_SHARE`` of ``total`` and the epoch under way.
    """
    kept = PASSES_SHARE * total * seconds_per_step if passes else 0.0
    fit = step + (left - kept) / max(float(seconds_per_step), 1e-9)
    if fit >= total:
        return int(total)
    least = max(math.ceil(MIN_STEPS_SHARE * total / steps_per_epoch), math.ceil(step / steps_per_epoch), 1)
    return int(min(total, max(int(fit // steps_per_epoch), least) * steps_per_epoch))


def pass_fits(left: float, seconds: Sequence[float], refreshed: Sequence[bool], refresh: bool) -> bool:
    """Whether a band-correction pass is expected to end within ``left`` seconds.

    ``seconds`` [n] and ``refreshed`` [n]: what each earlier pass took and whether it computed the
    discretisation error afresh (the dearest part of a pass); ``refresh``: whether this one will. Its
    cost is taken as the longest earlier pass of its kind, or of either kind where none is; the first
    pass needs only some time left.
    """
    if left <= 0:
        return False
    same = [s for s, r in zip(seconds, refreshed) if bool(r) == bool(refresh)]
    known = same or list(seconds)
    return not known or max(known) <= left
