"""The run's time budget (kneas_method.stages.time_budget): its pure rules, and a trainer shortened by it.
The stage-level checks (a budget spent before the passes, counted from the run's start) are in
tests/test_correction.py."""

from __future__ import annotations

import dataclasses
import json

from conftest import sphere_scene
from kneas_method.data.simulate import SimulationConfig
from kneas_method.stages.time_budget import PASSES_SHARE, pass_fits, run_budget, training_steps

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


def test_training_is_cut_to_whole_epochs_that_leave_the_passes_their_time():
    assert training_steps(1000.0, 100, 4000, 0.06, 50, True) == 4000  # 100 + 3900 x 0.06 + 0.9 x 240 s < 1000 s: unchanged
    fit = 100 + (300.0 - PASSES_SHARE * 4000 * 0.06) / 0.06  # the steps that end with the passes' share left
    assert training_steps(300.0, 100, 4000, 0.06, 50, True) == int(fit // 50) * 50
    assert training_steps(300.0, 100, 4000, 0.06, 50, False) == 4000  # no passes to keep time for
    assert training_steps(-50.0, 100, 4000, 0.06, 50, True) == 1000  # never under a quarter of the steps
    assert training_steps(-50.0, 1100, 4000, 0.06, 50, True) == 1100  # nor the epoch under way
    assert training_steps(-50.0, 1120, 4000, 0.06, 50, True) == 1150


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
