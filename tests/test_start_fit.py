"""The classical start's fit to the training views (classical_start.start_fit): at the data's noise for a
start that leaves only the noise, above it for one far from the views; computed once and recorded."""

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


def _state(tmp_path, scene, start, projections, **settings):
    import time

    from kneas_method import presets, registry
    from kneas_method.stages import RunState

    scene.train.projections = np.asarray(projections, dtype=np.float32)
    settings = {"preset": "tiny", "num_materials": 2, **settings}
    cfg = presets.resolve(dataclasses.replace(registry.load("methods", "k-neas").config, method="k-neas", **settings))
    return RunState(config=cfg, scene=scene, run_dir=tmp_path, device="cpu", started=time.perf_counter(), loss_scale=1.0,
                    say=print, start=(np.asarray(start), "asd-pocs"))


def test_a_start_far_from_the_views_is_above_their_noise_and_one_that_leaves_the_noise_is_at_it(tmp_path):
    from kneas_method.stages.band_correction import NOISE_FACTOR
    from kneas_method.stages.classical_start import start_fit

    scene, truth, exact, noisy = _views()
    far = start_fit(_state(tmp_path / "far", scene, truth * 0.5, exact))  # half the truth: the views hold far more
    assert far["at_noise"] is False and far["mean_square"] > 10 * NOISE_FACTOR * far["noise_variance"]
    state = _state(tmp_path / "noisy", scene, truth, noisy)  # the truth: only the noise is left
    fit = start_fit(state)
    assert fit["at_noise"] is True and fit["mean_square"] <= NOISE_FACTOR * fit["noise_variance"]
    assert state.records["classical-start"]["fit"] is fit


def test_the_starts_fit_is_computed_once_and_none_without_a_start(tmp_path):
    from kneas_method.stages.classical_start import start_fit

    scene, truth, exact, _ = _views()
    state = _state(tmp_path, scene, truth * 0.5, exact)
    fit = start_fit(state)
    state.start = (np.asarray(truth), "asd-pocs")  # a later call reads the record, not the volume
    assert start_fit(state) is fit and not fit["at_noise"]
    assert start_fit(dataclasses.replace(state, records={}, start=None)) is None
    views = state.views()  # the training views as a tensor, made once for every stage that projects
    assert views is state.views() and views.dtype == torch.float32 and np.array_equal(views.numpy(), exact)


def test_the_anchor_holds_the_start_harder_where_it_fits_the_views_to_their_noise(tmp_path):
    from kneas_method.engine.trainer import Trainer
    from kneas_method.stages.anchor import AnchorConfig, anchor_weight, build_anchor

    scene, truth, exact, noisy = _views()
    config = AnchorConfig()
    assert config.weight_at_noise > config.weight
    assert anchor_weight(config, _state(tmp_path / "far", scene, truth * 0.5, exact)) == (config.weight, False)
    state = _state(tmp_path / "noisy", scene, truth, noisy)
    assert anchor_weight(config, state) == (config.weight_at_noise, True)
    assert anchor_weight(dataclasses.replace(config, weight_at_noise=None), state) == (config.weight, False)

    # the stage builds its loss term with that weight and records it
    trainer = Trainer(state.config, scene, tmp_path / "run", epochs=1, device="cpu", bounds=([0.1, 0.1], [0.25, 0.75]))
    state = dataclasses.replace(state, trainer=trainer, records=trainer.records)
    config.setup().run(state)
    assert state.records["anchor"] == {"weight": config.weight_at_noise, "at_noise": True}
    expected = build_anchor(trainer, truth, config.weight_at_noise, config.points, occupancy_weight=config.occupancy)
    draw = trainer.generator.get_state()
    with torch.no_grad():
        held = float(state.loss_terms["anchor"]())
        trainer.generator.set_state(draw)
        assert held == float(expected.loss(trainer.model, trainer.generator)) and held > 0


def test_the_bounds_are_told_whether_the_start_fits_the_views_to_their_noise(tmp_path, monkeypatch):
    """The pipeline passes ``start_fit``'s verdict to the bounds (whose at-noise K rule then decides on
    a noisy scan) and records the fit once, for the stages after it."""
    from kneas_method.engine import neural_pipeline

    told = []
    real = neural_pipeline.estimate_bounds

    def spy(*args, **kwargs):
        told.append(kwargs["start_at_noise"])
        return real(*args, **kwargs)

    monkeypatch.setattr(neural_pipeline, "estimate_bounds", spy)
    scene, truth, exact, noisy = _views()
    results = {}
    for name, start, views in (("far", truth * 0.5, exact), ("noisy", truth, noisy)):
        state = _state(tmp_path / name, scene, start, views, preset="cpu", num_materials=None, bounds_max_materials=3)
        (tmp_path / name).mkdir()
        results[name] = neural_pipeline.NeuralPipeline(state.config, scene=scene, run_dir=tmp_path / name, device="cpu").bounds(state)
        assert state.records["classical-start"]["fit"]["at_noise"] is (name == "noisy")
    assert told == [False, True]
    assert results["far"].details["at_noise_rule"] is None and results["noisy"].details["at_noise_rule"] == "bic"
