"""The materials of a noisy scan found again on its trained volume (stages.materials_refit)."""

import dataclasses
import json

import numpy as np
import pytest
import torch

from conftest import tiny_config
from kneas_method.data.naf import save_naf
from kneas_method.data.simulate import SimulationConfig, simulate_phantom
from kneas_method.engine.bounds_stage import BoundsResult
from kneas_method.engine.loading import load_run
from kneas_method.engine.run_dir import create_run_dir, save_run_config
from kneas_method.engine.trainer import Trainer
from kneas_method.stages import RunState
from kneas_method.stages.materials_refit import MaterialsRefitConfig, refit_bounds

SMOOTHED = {"filter": "bilateral", "sigma_voxels": 3.0, "range_fraction": 0.1}


@pytest.fixture(scope="module")
def scene_path(tmp_path_factory):
    path = tmp_path_factory.mktemp("scene") / "foot32.pickle"
    save_naf(simulate_phantom("foot", SimulationConfig(n_voxel=32, voxel_mm=8.0, n_detector=32, n_train=4, n_val=2)), path)
    return path


def three_levels(n=32):
    """Nested balls of 0.2, 0.5 and 0.9 in air on the n^3 grid: (levels [3], volume [n, n, n])."""
    g = (np.arange(n) - (n - 1) / 2) / (n / 2)
    x, y, z = np.meshgrid(g, g, g, indexing="ij")
    v = np.where(np.sqrt(x ** 2 + y ** 2 + z ** 2) < 0.85, 0.2, 0.0)
    v = np.where(np.sqrt((x - 0.25) ** 2 + y ** 2 + z ** 2) < 0.45, 0.5, v)
    v = np.where(np.sqrt((x + 0.4) ** 2 + y ** 2 + z ** 2) < 0.25, 0.9, v)
    return np.array([0.2, 0.5, 0.9]), v.astype(np.float32)


def materials_stage(trainer, scene, config, bounds, run_dir, steps=80):
    """The materials-refit stage run on ``trainer`` -> (the run's config, its bounds) afterwards."""
    state = RunState(config=config, scene=scene, run_dir=run_dir, device="cpu", started=0.0, loss_scale=1.0, say=print,
                     records=trainer.records, bounds=bounds, trainer=trainer)
    MaterialsRefitConfig(steps=steps).setup().run(state)
    return state.config, state.bounds


def trained(scene_path, tmp_path, K, smoothed=SMOOTHED, at_noise_rule=None):
    """A finished tiny k-neas run with K materials over [0, 1] whose bounds came (or not) from the
    fallback: (config, scene, trainer, bounds, run_dir)."""
    from kneas_method.data.scenes import resolve_scene

    config = tiny_config("k-neas", scene_path, num_materials=K)
    config = dataclasses.replace(config, model=dataclasses.replace(config.model, num_materials=K))
    scene = resolve_scene(str(scene_path))
    run_dir = create_run_dir(tmp_path, scene.name, "k-neas")
    save_run_config(run_dir, config)
    edges = np.linspace(0.0, 1.0, K + 1)
    bounds = BoundsResult(list(np.diff(edges)), list(edges[:-1]), K, "gmm (gmm) on the ASD-POCS", 0.0,
                          {"volume": "asd-pocs", "smoothed": smoothed, "at_noise_rule": at_noise_rule})
    (run_dir / "bounds.json").write_text(json.dumps(bounds.to_json()))
    trainer = Trainer(config, scene, run_dir, epochs=1, device="cpu", bounds=(bounds.alphas, bounds.betas))
    trainer.step, trainer.complete = trainer.total_steps, True
    trainer.save(complete=True)
    return config, scene, trainer, bounds, run_dir


def test_more_materials_on_the_trained_volume_replace_the_model(scene_path, tmp_path, monkeypatch):
    levels, target = three_levels()
    monkeypatch.setattr("kneas_method.engine.evaluate.sample_volume", lambda model, geometry, **kw: target)
    config, scene, trainer, bounds, run_dir = trained(scene_path, tmp_path, K=1)
    old = trainer.model
    config2, bounds2 = materials_stage(trainer, scene, config, bounds, run_dir)
    K = bounds2.K  # the three levels, and their blurred edges' values next to air (0 < mu < 0.2) may make a fourth
    assert K in (3, 4) and config2.num_materials == K and config2.model.num_materials == K
    assert trainer.model is not old and trainer.model.num_materials == K
    b = np.array(trainer.records["materials-refit"]["boundaries"])
    assert len(b) == K + 1 and np.unique(np.searchsorted(b, levels)).size == 3  # each level in a material of its own
    assert trainer.records["materials-refit"]["refit"] and trainer.records["materials-refit"]["start_K"] == 1
    # bounds.json, config.json and the checkpoint name the new K, the start's bounds kept
    saved = json.loads((run_dir / "bounds.json").read_text())
    assert saved["K"] == K and saved["start_bounds"]["K"] == 1 and saved["smoothed"] == SMOOTHED
    assert saved["gmm"]["boundaries"] == pytest.approx(list(b)) and "trained volume" in saved["k_chosen_by"]
    assert json.loads((run_dir / "config.json").read_text())["num_materials"] == K
    assert (run_dir / "figures" / "gmm_bounds_trained.png").is_file()
    loaded = load_run(run_dir)
    assert loaded.model.num_materials == K
    # the fit moved the fresh model towards the trained volume
    from kneas_method.evaluation.surfaces import query_grid

    mu = query_grid(loaded.model, scene.geometry, keys=("mu",))["mu"]
    assert np.mean((mu - target) ** 2) < 0.25 * np.mean(target ** 2)
    # a resumed run does not redo it
    trainer2 = Trainer(config2, scene, run_dir, epochs=1, device="cpu", bounds=(bounds2.alphas, bounds2.betas))
    assert trainer2.resume() is not None and trainer2.records["materials-refit"]["K"] == K
    same = trainer2.model
    assert materials_stage(trainer2, scene, config2, bounds2, run_dir) == (config2, bounds2) and trainer2.model is same


def test_as_many_materials_keep_the_model_and_clean_starts_skip_the_stage(scene_path, tmp_path, monkeypatch):
    _, target = three_levels()
    calls = []
    monkeypatch.setattr("kneas_method.engine.evaluate.sample_volume", lambda model, geometry, **kw: calls.append(1) or target)
    config, scene, trainer, bounds, run_dir = trained(scene_path, tmp_path, K=4)  # the trained volume shows 3 or 4
    before = {k: v.clone() for k, v in trainer.model.state_dict().items()}
    model = trainer.model
    assert materials_stage(trainer, scene, config, bounds, run_dir) == (config, bounds)
    assert trainer.model is model and all(torch.equal(before[k], v) for k, v in model.state_dict().items())
    assert trainer.records["materials-refit"]["K"] <= 4 and not trainer.records["materials-refit"]["refit"] and calls == [1]
    assert json.loads((run_dir / "bounds.json").read_text())["K"] == 4
    # bounds from the histogram's peaks (a clean start): nothing is computed
    config, scene, trainer, bounds, run_dir = trained(scene_path, tmp_path, K=1, smoothed=None)
    assert materials_stage(trainer, scene, config, bounds, run_dir) == (config, bounds)
    assert "materials-refit" not in trainer.records and trainer.model.num_materials == 1
    # bounds from the at-noise rule's mixtures on the filtered start: they counted its materials already
    config, scene, trainer, bounds, run_dir = trained(scene_path, tmp_path, K=1, at_noise_rule="bic")
    assert materials_stage(trainer, scene, config, bounds, run_dir) == (config, bounds)
    assert "materials-refit" not in trainer.records and trainer.model.num_materials == 1
    assert calls == [1]


def test_an_interrupted_materials_stage_is_redone_on_resume(tiny_scene, tmp_path, capsys, monkeypatch):
    from conftest import run, run_dir_of
    from kneas_method.stages.materials_refit import MaterialsRefit

    real, calls = MaterialsRefit.run, []

    def interrupted(self, state):
        calls.append(1)
        raise KeyboardInterrupt

    monkeypatch.setattr(MaterialsRefit, "run", interrupted)
    args = ["k-neas", "--scene", str(tiny_scene), "--preset", "tiny", "--trainer.epochs", "1", "--trainer.eval-every", "0",
            "--bounds-source", "wide", "--add-stages", "materials-refit", "--output-dir", str(tmp_path / "o")]
    code, out, err = run(args, capsys)
    run_dir = run_dir_of(out)
    assert code == 130 and calls == [1] and "interrupted during the materials-refit stage" in out
    assert f"kneas-train --resume {run_dir}" in out.replace("\n", "") and not (run_dir / "metrics.json").exists()
    monkeypatch.setattr(MaterialsRefit, "run", lambda self, state: calls.append(2) or real(self, state))
    code, out, err = run(["--resume", str(run_dir)], capsys)
    assert code == 0 and calls == [1, 2] and (run_dir / "metrics.json").is_file(), err


def test_a_run_stopped_between_the_refits_checkpoint_and_bounds_json_resumes_with_the_new_k(scene_path, tmp_path, monkeypatch):
    _, target = three_levels()
    monkeypatch.setattr("kneas_method.engine.evaluate.sample_volume", lambda model, geometry, **kw: target)
    config, scene, trainer, bounds, run_dir = trained(scene_path, tmp_path, K=1)
    config2, bounds2 = materials_stage(trainer, scene, config, bounds, run_dir)
    assert bounds2.K > 1
    # the stop: the checkpoint holds the new model, bounds.json and config.json still the start's K
    (run_dir / "bounds.json").write_text(json.dumps(bounds.to_json()))
    save_run_config(run_dir, config)
    mended = refit_bounds(BoundsResult.from_json(json.loads((run_dir / "bounds.json").read_text())), run_dir, config.method)
    assert mended.K == bounds2.K and mended.alphas == pytest.approx(bounds2.alphas) and mended.betas == pytest.approx(bounds2.betas)
    assert json.loads((run_dir / "bounds.json").read_text())["K"] == bounds2.K and mended.details["start_bounds"]["K"] == 1
    k = mended.K  # the trainer rebuilt with that K resumes from the checkpoint
    config3 = dataclasses.replace(config, num_materials=k, model=dataclasses.replace(config.model, num_materials=k))
    resumed = Trainer(config3, scene, run_dir, epochs=1, device="cpu", bounds=(mended.alphas, mended.betas))
    assert resumed.resume() is not None and resumed.records["materials-refit"]["K"] == k
    assert refit_bounds(mended, run_dir, config.method) is mended  # nothing more to mend
