"""The table-size stage (kneas_method.stages.table_size): the hash table raised where the classical start
is above the data's noise, the preset's where it is at it, and nothing for an encoding without a table;
and the start's fit to the views (classical_start.start_fit) computed once and recorded."""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from conftest import sphere_scene
from kneas_method.data.simulate import SimulationConfig

SIM = SimulationConfig(n_voxel=16, voxel_mm=8.0, n_detector=24, n_train=8, n_val=2)


def _views():
    """The sphere scene, its exact training views and the same with white noise."""
    from kneas_method.classical.projector import Projector

    scene = sphere_scene(SIM)
    truth = np.asarray(scene.image, dtype=np.float32)
    exact = Projector(scene.geometry, scene.train.angles).forward(torch.as_tensor(truth)).numpy()
    noisy = exact + np.random.default_rng(0).normal(0.0, 0.05 * float(exact.max()), exact.shape)
    return scene, truth, exact, noisy.astype(np.float32)


def _state(tmp_path, scene, start, projections, encoding="hashgrid"):
    import time

    from kneas_method import presets, registry
    from kneas_method.stages import RunState

    scene.train.projections = np.asarray(projections, dtype=np.float32)
    cfg = presets.resolve(dataclasses.replace(registry.load("methods", "k-neas").config, method="k-neas", preset="tiny", num_materials=2))
    if encoding != "hashgrid":
        cfg = dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, encoding=encoding, encoding_options={}))
    return RunState(config=cfg, scene=scene, run_dir=tmp_path, device="cpu", started=time.perf_counter(), loss_scale=1.0,
                    say=print, start=(np.asarray(start), "asd-pocs"))


def _run(state):
    from kneas_method.stages.table_size import TableSizeConfig

    TableSizeConfig().setup().run(state)
    return state.config.model.encoding_options.get("log2_hashmap_size")


def test_a_start_far_from_the_views_raises_the_table_and_one_at_their_noise_keeps_the_presets(tmp_path):
    from kneas_method import presets

    scene, truth, exact, noisy = _views()
    preset = presets.TABLE["tiny"]["hashgrid"]["log2_hashmap_size"]
    assert preset < 19
    clean = _state(tmp_path / "clean", scene, truth * 0.5, exact)  # half the truth: the views hold far more
    assert _run(clean) == 19
    assert clean.records["table-size"] == {"log2_hashmap_size": 19, "start_at_noise": False}
    assert clean.records["classical-start"]["fit"]["at_noise"] is False
    noisy_state = _state(tmp_path / "noisy", scene, truth, noisy)  # the truth: only the noise is left
    assert _run(noisy_state) == preset
    assert noisy_state.records["table-size"] == {"log2_hashmap_size": preset, "start_at_noise": True}


def test_the_starts_fit_is_computed_once_and_an_encoding_without_a_table_is_left_alone(tmp_path):
    from kneas_method.stages.classical_start import start_fit

    scene, truth, exact, _ = _views()
    state = _state(tmp_path, scene, truth * 0.5, exact, encoding="frequency")
    assert _run(state) is None and "table-size" not in state.records
    fit = start_fit(state)
    assert fit["mean_square"] > 1.5 * fit["noise_variance"] and not fit["at_noise"]
    state.start = (np.asarray(truth), "asd-pocs")  # a later call reads the record, not the volume
    assert start_fit(state) is fit
    state.start = None
    assert start_fit(dataclasses.replace(state, records={})) is None
