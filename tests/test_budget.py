"""The run's time budget (kneas_method.stages.time_budget): its pure rules, and a trainer shortened by it.
The stage-level checks (a budget spent before the passes, counted from the run's start) are in
tests/test_correction.py."""

from __future__ import annotations

import dataclasses
import json

from conftest import sphere_scene
from kneas_method.data.simulate import SimulationConfig
from kneas_method.stages.time_budget import PASSES_SHARE, kept_after_training, pass_fits, run_budget, training_steps

SIM = SimulationConfig(n_voxel=16, voxel_mm=8.0, n_detector=24, n_train=8, n_val=2)


def test_the_budget_is_the_one_given_up_to_128_cubed_voxels_and_grows_with_them_beyond():
    assert run_budget(600, (128, 128, 128)) == 600 and run_budget(600, (64, 64, 100)) == 600
    assert run_budget(600, (256, 256, 256)) == 4800 and run_budget(600, (256, 128, 128)) == 1200
    assert run_budget(0, (128, 128, 128)) is None and run_budget(None, (8, 8, 8)) is None


def test_a_pass_is_started_only_where_its_kind_has_ended_in_the_time_left():
    assert pass_fits(5.0, [], [], True) and not pass_fits(0.0, [], [], True) and not pass_fits(-3.0, [], [], False)
    seconds, refreshed = [10.0, 4.0, 4.5], [True, False, False]  # a fresh discretisation estimate costs more
    assert not pass_fits(6.0, seconds, refreshed, True) and pass_fits(10.0, seconds, refreshed, True)
    assert pass_fits(6.0, seconds, refreshed, False) and not pass_fits(4.4, seconds, refreshed, False)
    assert not pass_fits(6.0, [10.0], [True], False) and pass_fits(6.0, [5.0], [False], True)  # no pass of its kind yet: either kind's


def test_training_leaves_the_passes_their_share_or_the_later_fits_their_steps():
    assert kept_after_training(0.06, 4000, passes=True) == PASSES_SHARE * 4000 * 0.06
    assert kept_after_training(0.06, 4000, passes=False) == 0.0
    assert kept_after_training(0.06, 4000, passes=False, fit_steps=1800, seconds=40.0) == 1800 * 0.06 + 40.0
    assert kept_after_training(0.06, 4000, passes=True, fit_steps=300, seconds=25.0) == (PASSES_SHARE * 4000 + 300) * 0.06 + 25.0


def test_training_is_cut_to_whole_epochs_that_leave_the_passes_their_time():
    passes = kept_after_training(0.06, 4000, passes=True)
    assert training_steps(1000.0, 100, 4000, 0.06, 50, passes) == 4000  # 100 + 3900 x 0.06 + 0.9 x 240 s < 1000 s: unchanged
    fit = 100 + (300.0 - PASSES_SHARE * 4000 * 0.06) / 0.06  # the steps that end with the passes' share left
    assert training_steps(300.0, 100, 4000, 0.06, 50, passes) == int(fit // 50) * 50
    assert training_steps(300.0, 100, 4000, 0.06, 50, 0.0) == 4000  # nothing to keep time for
    assert training_steps(300.0, 100, 4000, 0.06, 50, 100.0) == int((100 + 200.0 / 0.06) // 50) * 50
    assert training_steps(-50.0, 100, 4000, 0.06, 50, passes) == 1000  # never under a quarter of the steps
    assert training_steps(-50.0, 1100, 4000, 0.06, 50, passes) == 1100  # nor the epoch under way
    assert training_steps(-50.0, 1120, 4000, 0.06, 50, passes) == 1150


def budget_state(tmp_path, start, projections, smoothed, at_noise_rule=None):
    """A tiny k-neas run's state before training, with ``start`` [nx, ny, nz] as its classical start, the
    scene's training ``projections`` replaced, and bounds from the peaks rule's fallback or not."""
    import time

    import numpy as np

    from kneas_method import presets, registry
    from kneas_method.engine.bounds_stage import BoundsResult
    from kneas_method.engine.trainer import Trainer
    from kneas_method.stages import RunState
    from kneas_method.stages.correction import CorrectionConfig
    from kneas_method.stages.materials_refit import MaterialsRefitConfig
    from kneas_method.stages.smoothing import SmoothingConfig

    scene = sphere_scene(SIM)
    scene.train.projections = np.asarray(projections, dtype=np.float32)
    cfg = presets.resolve(dataclasses.replace(registry.load("methods", "k-neas").config, method="k-neas", preset="tiny", num_materials=2))
    cfg = dataclasses.replace(cfg, stages=dataclasses.replace(cfg.stages, correction=CorrectionConfig(), smoothing=SmoothingConfig(),
                                                              materials_refit=MaterialsRefitConfig()))
    trainer = Trainer(cfg, scene, tmp_path, epochs=4, device="cpu", bounds=([0.1, 0.1], [0.25, 0.75]))
    bounds = BoundsResult([0.1, 0.1], [0.25, 0.75], 2, "test", 0.0, {"smoothed": smoothed, "fit_time_s": 7.0, "at_noise_rule": at_noise_rule})
    return RunState(config=cfg, scene=scene, run_dir=tmp_path, device="cpu", started=time.perf_counter(), loss_scale=1.0,
                    say=print, records=trainer.records, trainer=trainer, bounds=bounds, start=(np.asarray(start), "asd-pocs"))


def test_a_start_at_the_datas_noise_leaves_the_later_fits_their_time_not_the_passes(tmp_path):
    import numpy as np
    import torch

    from kneas_method.classical.projector import Projector
    from kneas_method.stages.time_budget import SMOOTHING_CHOICE_S, after_training

    scene = sphere_scene(SIM)
    truth = np.asarray(scene.image, dtype=np.float32)
    exact = Projector(scene.geometry, scene.train.angles).forward(torch.as_tensor(truth)).numpy()
    noisy = exact + np.random.default_rng(0).normal(0.0, 0.05 * float(exact.max()), exact.shape)
    stages = budget_state(tmp_path / "a", truth, noisy, True).config.stages

    clean = after_training(budget_state(tmp_path / "clean", truth * 0.5, exact, False))  # half the truth: far from the views
    assert clean == {"passes": True}
    at_noise = after_training(budget_state(tmp_path / "noisy", truth, noisy, True))  # the truth: only the noise is left
    assert at_noise == {"passes": False, "fit_steps": stages.smoothing.steps + stages.materials_refit.steps,
                        "seconds": SMOOTHING_CHOICE_S + 7.0}
    peaks = after_training(budget_state(tmp_path / "peaks", truth, noisy, False))  # bounds from peaks: no refit follows
    assert peaks == {"passes": False, "fit_steps": stages.smoothing.steps, "seconds": SMOOTHING_CHOICE_S}
    ruled = after_training(budget_state(tmp_path / "ruled", truth, noisy, True, "bic"))  # the at-noise rule's bounds: no refit either
    assert ruled == peaks


def test_a_shortened_trainer_moves_its_learning_rate_step_and_its_config_with_it(tmp_path):
    from kneas_method import presets, registry
    from kneas_method.engine.run_dir import save_run_config
    from kneas_method.engine.trainer import Trainer

    scene = sphere_scene(SIM)
    cfg = presets.resolve(dataclasses.replace(registry.load("methods", "k-neas").config, method="k-neas", preset="tiny", num_materials=2))
    cfg = dataclasses.replace(cfg, trainer=dataclasses.replace(cfg.trainer, epochs=20))
    save_run_config(tmp_path, cfg)
    trainer = Trainer(cfg, scene, tmp_path, epochs=20, device="cpu", bounds=([0.1, 0.1], [0.25, 0.75]))
    spe, factor = trainer.steps_per_epoch, float(cfg.trainer.lr_decay_factor)
    assert trainer.decay_step == round(cfg.trainer.lr_decay_at * 20 * spe)
    trainer.shorten(8 * spe + 1)  # rounded down to whole epochs
    assert trainer.epochs == 8 and trainer.total_steps == 8 * spe and trainer.decay_step == round(cfg.trainer.lr_decay_at * 8 * spe)
    rate = trainer.scheduler.lr_lambdas[0]
    assert rate(trainer.decay_step - 1) == 1.0 and rate(trainer.decay_step) == factor  # the step moved with the count
    assert json.loads((tmp_path / "config.json").read_text())["trainer"]["epochs"] == 8 and trainer.config.trainer.epochs == 8
    trainer.train()
    assert trainer.step == 8 * spe and trainer.complete
