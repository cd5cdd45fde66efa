"""Procedures and their stages (kneas_method.stages): the paper's runs only the paper's stages, each
stage can be left out end to end, and the config that says so reads back the same."""

import dataclasses
import json

import numpy as np
import pytest

from conftest import run, run_dir_of
from kneas_method import presets, registry
from kneas_method.config import to_dict
from kneas_method.engine.legacy_config import upgrade
from kneas_method.engine.loading import config_from_dict, read_run_config
from kneas_method.errors import ConfigError
from kneas_method.stages import BUILT_IN, PAPER, REFINE_CLASSICAL

# small settings of every stage, so that the refine-classical procedure runs in seconds on the tiny scene
SMALL = ["--stages.warm-start.steps", "5", "--stages.warm-start.points", "512", "--stages.anchor.points", "256",
         "--stages.correction.passes", "1", "--stages.correction.steps", "3", "--stages.correction.points", "256",
         "--stages.smoothing.steps", "3", "--stages.smoothing.points", "256", "--stages.materials-refit.steps", "3",
         "--stages.materials-refit.points", "256", "--reconstruction.iterations", "2", "--trainer.epochs", "2",
         "--trainer.eval-every", "0"]


def stage_classes():
    return {name: registry.load("stages", name) for name in BUILT_IN}


def test_the_built_in_procedures_and_stages_are_registered():
    assert set(presets.procedures()) >= {"paper", "refine-classical"}
    assert set(registry.names("stages")) >= set(BUILT_IN)
    assert PAPER.stages == () and set(REFINE_CLASSICAL.stages) == set(BUILT_IN)
    for name, cls in stage_classes().items():
        assert cls.name == name and dataclasses.is_dataclass(cls)


def test_presets_pick_a_procedure_and_the_paper_one_has_no_stage():
    base = registry.load("methods", "k-neas").config
    cpu = presets.resolve(dataclasses.replace(base, preset="cpu"))
    assert cpu.procedure == "refine-classical" and presets.stage_names(cpu) == list(REFINE_CLASSICAL.stages)
    assert (cpu.model.s_init, cpu.model.lambda_eikonal, cpu.model.occupancy_grid, cpu.trainer.lr_decay_at) == (100.0, 1e-5, True, 0.85)
    paper_on_cpu = presets.resolve(dataclasses.replace(base, preset="cpu", procedure="paper"))
    assert presets.stage_names(paper_on_cpu) == [] and all(getattr(paper_on_cpu.stages, f) is None for f in BUILT_IN.values())
    # the paper's fitting settings, the cpu preset's compute
    assert (paper_on_cpu.model.s_init, paper_on_cpu.model.lambda_eikonal, paper_on_cpu.model.occupancy_grid) == (20.0, 0.01, False)
    assert (paper_on_cpu.trainer.lr_decay_at, paper_on_cpu.bounds_k_rule, paper_on_cpu.bounds_max_materials,
            paper_on_cpu.bounds_gmm_restarts) == (0.5, "bic", 4, 1)
    assert paper_on_cpu.trainer.epochs == cpu.trainer.epochs and paper_on_cpu.model.encoding_options == cpu.model.encoding_options
    assert presets.resolve(dataclasses.replace(base, preset="tiny")).procedure == "paper"
    # the user's settings win over the procedure's
    told = presets.resolve(dataclasses.replace(base, preset="cpu", model=dataclasses.replace(base.model, s_init=30.0)))
    assert told.model.s_init == 30.0


def test_paper_procedure_on_the_cpu_preset_runs_only_the_papers_stages(tiny_scene, tmp_path, capsys, monkeypatch):
    """No classical start, warm start, anchor, correction, smoothing, refit or budget: the only classical
    reconstruction is the FDK that measures the scan's loss unit (engine.loss_scale)."""
    from kneas_method.classical import reconstruct as reconstruct_module

    ran, algorithms = [], []
    for name, cls in stage_classes().items():
        module, attr = cls._target.split(":")  # the stage class the config builds
        monkeypatch.setattr(f"{module}.{attr}.run", lambda self, state, name=name: ran.append(name))
    real = reconstruct_module.reconstruct
    monkeypatch.setattr(reconstruct_module, "reconstruct", lambda algorithm, *a, **kw: algorithms.append(algorithm) or real(algorithm, *a, **kw))
    code, out, err = run(["k-neas", "--scene", str(tiny_scene), "--preset", "cpu", "--procedure", "paper", "--trainer.epochs", "1",
                          "--trainer.prior-epochs", "1", "--trainer.eval-every", "0", "--output-dir", str(tmp_path / "o")], capsys)
    assert code == 0, err
    assert ran == [] and algorithms == ["fdk"]
    assert "procedure: paper" in out and "1. bounds: K by BIC, K = 1..4, on the voxel values of a NeAS-1M prior" in out
    assert "; the top bound 1.15 x the 99.5th percentile" in out
    assert "whichever is higher" not in out  # the paper's top bound has no floor
    assert "settings beside the paper's" not in out and "prior: training the NeAS-1M prior" in out
    run_dir = run_dir_of(out)
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics["procedure"] == "paper" and metrics["stages"] == {}
    saved = json.loads((run_dir / "config.json").read_text())
    assert saved["procedure"] == "paper" and all(saved["stages"][f] is None for f in BUILT_IN.values())


def _needs_off(stage: str) -> list[str]:
    """The stages that must go with ``stage`` (those that work on its result)."""
    return [name for name, cls in stage_classes().items() if stage in cls.needs]


@pytest.mark.parametrize("stage", list(REFINE_CLASSICAL.stages))
def test_each_stage_left_out_end_to_end(stage, tiny_scene, tmp_path, capsys):
    skip = [stage] + _needs_off(stage)
    code, out, err = run(["k-neas", "--scene", str(tiny_scene), "--preset", "tiny", "--procedure", "refine-classical", *SMALL,
                          "--skip-stages", *skip, "--output-dir", str(tmp_path / "o")], capsys)
    assert code == 0, err
    run_dir = run_dir_of(out)
    metrics = json.loads((run_dir / "metrics.json").read_text())
    running = [s for s in REFINE_CLASSICAL.stages if s not in skip]
    assert list(metrics["stages"]) == running  # every stage it ran, in order, and no other
    for name in skip:
        assert name not in metrics["stages"]
    recorded = {"classical-start": "algorithm", "warm-start": "steps", "correction": "passes", "smoothing": "filter",
                "time-budget": "time_budget_s"}
    for name in running:
        if name in recorded:
            assert recorded[name] in metrics["stages"][name], (name, metrics["stages"][name])
    config = read_run_config(run_dir)  # reads back as the same run: the left-out stages are skipped
    assert set(skip) <= set(config.skip_stages) and presets.stage_names(presets.resolve(config)) == running
    if stage == "classical-start":
        assert "prior: training the NeAS-1M prior" in out  # no start: the paper's bounds


def test_a_stage_without_the_stage_it_works_on_is_refused(capsys, tmp_path):
    code, out, err = run(["k-neas", "--preset", "tiny", "--procedure", "refine-classical", "--skip-stages", "classical-start",
                          "--dry-run"], capsys)
    assert code == 2 and "stages warm-start and anchor work on the classical-start stage's result" in err
    assert "add --skip-stages warm-start anchor too" in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("argv,words", [
    (["--procedure", "papr"], ["--procedure 'papr' is not a procedure", "did you mean paper"]),
    (["--skip-stages", "corection"], ["--skip-stages corection", "did you mean correction"]),
    (["--procedure", "paper", "--skip-stages", "correction"], ["procedure 'paper' has no such stage", "its stages: none"]),
    (["--add-stages", "nothing-here"], ["no stage named 'nothing-here'"]),
    (["--stages.correction.passes", "0"], ["--stages.correction.passes must be a whole number >= 1, got 0"]),
    (["--stages.anchor.weight", "-1"], ["--stages.anchor.weight must be a number >= 0"]),
    (["--stages.correction.ring", "1.5"], ["--stages.correction.ring must be a number >= 0 and <= 1"]),
    (["--stages.correction.weights", "gradient", "--stages.correction.ring", "0.2"], ["weights the band's outer ring"]),
    (["--stages.time-budget.seconds", "0"], ["--stages.time-budget.seconds must be a number > 0"]),
])
def test_procedure_and_stage_mistakes_are_one_line(argv, words, capsys):
    code, out, err = run(["k-neas", "--preset", "cpu", "--dry-run", *argv], capsys)
    line = err.strip()
    assert code == 2 and line.startswith("error:") and len(line.splitlines()) == 1, err
    for word in words:
        assert word in line, (word, line)


def test_a_resolved_config_reads_back_as_the_same_run():
    base = registry.load("methods", "k-neas").config
    resolved = presets.resolve(dataclasses.replace(base, preset="cpu", skip_stages=("smoothing",)))
    text = json.dumps(to_dict(resolved))
    again = presets.resolve(config_from_dict(json.loads(text), "config.json"))
    assert presets.stage_names(again) == presets.stage_names(resolved) and to_dict(again) == to_dict(resolved)


def test_older_config_files_map_their_flat_settings_onto_the_stages():
    old = {"method": "k-neas", "preset": "cpu", "bounds_volume": "asd-pocs",
           "trainer": {"epochs": 80, "warm_start": "asd-pocs", "warm_start_steps": 300, "warm_start_points": 16384,
                       "warm_start_occupancy": 0.01, "warm_start_anchor": 0.01, "anchor_points": 4096, "anchor_occupancy": 0.03,
                       "anchor_edge_contrast": 0.0, "anchor_region": "box", "anchor_outside": "skip", "fit_outside": "skip",
                       "correction_passes": 12, "correction_iterations": 4, "correction_weights": "ring", "correction_ring": None,
                       "correction_refresh": 3, "correction_noise_factor": 1.5, "correction_steps": 75, "correction_lr": 1e-4,
                       "correction_points": 8192, "correction_curvature": 0.003, "denoise": "sure", "denoise_steps": 300,
                       "denoise_lr": 1e-3, "materials_refit_steps": 1500, "time_budget": 600.0}}
    config = config_from_dict(upgrade(old, lambda method, model: False), "old.json")
    fresh = presets.resolve(dataclasses.replace(registry.load("methods", "k-neas").config, preset="cpu"))
    assert config.procedure == "refine-classical" and config.trainer.epochs == 80
    # the default stages, as the cpu preset gives them today, but the anchor's one weight on every scan
    one_weight = dataclasses.replace(fresh.stages, anchor=dataclasses.replace(fresh.stages.anchor, weight_at_noise=None))
    assert to_dict(config.stages) == to_dict(one_weight)
    stages = {"anchor": {k: v for k, v in to_dict(fresh.stages.anchor).items() if k != "weight_at_noise"}}
    before = config_from_dict({"method": "k-neas", "preset": "cpu", "procedure": "refine-classical", "stages": stages}, "old.json")
    assert before.stages.anchor == one_weight.anchor  # a run of the anchor's one weight resumes with it
    paper = config_from_dict(upgrade({"method": "k-neas", "bounds_volume": "prior",
                                      "trainer": {"warm_start": "none", "warm_start_steps": 0, "correction_passes": 0,
                                                  "time_budget": 0.0}}, lambda m, x: False), "old.json")
    assert paper.procedure == "paper" and presets.stage_names(presets.resolve(paper)) == []
    with pytest.raises(ConfigError, match="unknown setting"):
        config_from_dict({"method": "k-neas", "trainer": {"no_such_setting": 1}}, "bad.json")


def test_settings_of_a_stage_the_run_does_not_run_are_named(capsys):
    code, out, err = run(["k-neas", "--preset", "tiny", "--dry-run", "--stages.correction.passes", "3"], capsys)
    assert code == 0 and "note: --stages.correction.* settings are given, but this run does not run the correction stage" in out
    code, out, err = run(["k-neas", "--preset", "tiny", "--dry-run", "--add-stages", "correction", "--stages.correction.passes", "3"], capsys)
    assert code == 0 and "note:" not in out and "correction: up to 3 passes" in out


def test_the_top_bound_follows_the_procedure_or_the_user():
    from kneas_method.engine.bounds_stage import run_mixtures

    base = registry.load("methods", "k-neas").config
    cpu = presets.resolve(dataclasses.replace(base, preset="cpu"))
    paper = presets.resolve(dataclasses.replace(base, preset="cpu", procedure="paper"))
    assert (cpu.bounds_upper_percentile, cpu.bounds_upper_factor) == (99.5, 1.15)  # SPEC §4's, as the paper's
    assert cpu.bounds_cover_percentile == 99.99 and paper.bounds_cover_percentile == 0.0
    capped = presets.resolve(dataclasses.replace(base, preset="cpu", bounds_cover_percentile=0.0))
    whole = presets.resolve(dataclasses.replace(base, preset="cpu", bounds_upper_percentile=100.0, bounds_upper_factor=1.0,
                                                bounds_cover_percentile=0.0))
    # a tail of dense voxels above the 99.5th percentile (0.2 % of the values, as a real scan's bone)
    values = np.r_[np.full(5000, 0.2), np.full(5000, 0.5), np.linspace(0.6, 1.0, 20)]
    top_paper = run_mixtures(paper, K=2).fit(values).boundaries_[-1]
    assert top_paper == pytest.approx(1.15 * np.percentile(values[values > 0.05], 99.5), rel=1e-6) and top_paper < 0.6
    assert run_mixtures(capped, K=2).fit(values).boundaries_[-1] == pytest.approx(top_paper)
    assert run_mixtures(whole, K=2).fit(values).boundaries_[-1] == pytest.approx(1.0)  # the whole range by percentile
    # the default covers the tail up to its 99.99th percentile
    kept = values[values > 0.05 * np.percentile(values, 99.5)]
    top = run_mixtures(cpu, K=2).fit(values).boundaries_[-1]
    assert top == pytest.approx(np.percentile(kept, 99.99)) and top > 0.95
