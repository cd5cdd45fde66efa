"""kneas-train end to end on a tiny scene: prior -> GMM bounds -> K-model, FDK, run folders, bad numbers."""

import json
import math

import numpy as np
import pytest
import torch

from kneas_method.cli import train as cli
from kneas_method.errors import KneasError

from conftest import run, run_dir_of

METRIC_KEYS = ("psnr2d", "ssim2d", "psnr3d", "ssim3d", "psnr3d_ls", "parameters", "steps", "wall_time_s", "preset", "scene_source")


def test_k_neas_two_stage_pipeline(tiny_scene, tmp_path, capsys):
    outdir = tmp_path / "out"
    code, out, err = run(["k-neas", "--scene", str(tiny_scene), "--preset", "tiny", "--output-dir", str(outdir)], capsys)
    assert code == 0, err
    assert "preset 'tiny' as requested" in out and f"file {tiny_scene}" in out
    assert "prior: training the NeAS-1M prior" in out and "bounds: GMM (gmm)" in out and "BIC" in out
    run_dir = run_dir_of(out)
    assert run_dir.parent == outdir / "tinyfoot" / "k-neas"
    # bounds: K chosen by BIC, written in data units, recorded in the config
    bounds = json.loads((run_dir / "bounds.json").read_text())
    K = bounds["K"]
    assert K >= 1 and len(bounds["alphas"]) == len(bounds["betas"]) == K and bounds["k_chosen_by"] == "bic"
    assert all(a > 0 for a in bounds["alphas"]) and bounds["betas"][0] == 0.0
    config = json.loads((run_dir / "config.json").read_text())
    assert config["num_materials"] == K and config["model"]["num_materials"] == K
    # metrics
    metrics = json.loads((run_dir / "metrics.json").read_text())
    for key in METRIC_KEYS:
        assert key in metrics, key
    assert metrics["num_materials"] == K and metrics["preset"] == "tiny" and metrics["steps"] == 2 * 4
    assert metrics["n_views"] == 4 and len(metrics["psnr2d_per_view"]) == 4
    assert all(math.isfinite(metrics[k]) for k in ("psnr2d", "ssim2d", "psnr3d", "ssim3d"))
    np.testing.assert_allclose(metrics["alphas"], bounds["alphas"], rtol=1e-6)
    # figures and checkpoints
    for name in ("gmm_bounds.png", "loss_curves.png", "projection_val0.png", "slices.png"):
        assert (run_dir / "figures" / name).is_file(), name
    ckpts = sorted((run_dir / "checkpoints").glob("step-*.ckpt"))
    assert ckpts and ckpts[-1].name == "step-00000008.ckpt"
    # the prior is a complete run folder of its own
    prior = outdir / "tinyfoot" / "neas-1m-prior"
    (prior_dir,) = list(prior.iterdir())
    assert bounds["prior_run"] == str(prior_dir)
    for name in ("config.json", "metrics.json", "volume.npy"):
        assert (prior_dir / name).is_file()
    assert json.loads((prior_dir / "config.json").read_text())["method"] == "neas-1m"
    assert list((prior_dir / "checkpoints").glob("*.ckpt"))

    # the contract with kneas-eval: rebuild from config.json + checkpoint, same metrics
    from kneas_method.config import update_from_dict
    from kneas_method.data.scenes import resolve_scene
    from kneas_method.engine.checkpoint import load_latest_checkpoint
    from kneas_method.engine.evaluate import evaluate_model
    from kneas_method.methods import TrainConfig
    from kneas_method.model import CTModel

    cfg = update_from_dict(TrainConfig(), config)
    scene = resolve_scene(cfg.scene).subsample_views(cfg.views)
    model = CTModel(cfg.model, scale=scene.geometry.scale)
    state, _, _ = load_latest_checkpoint(run_dir / "checkpoints", method="k-neas")
    model.load_state_dict(state["model"])
    again = evaluate_model(model, scene, cfg, "cpu")
    for key in ("psnr2d", "ssim2d", "psnr3d", "ssim3d", "psnr3d_ls"):
        assert again[key] == pytest.approx(metrics[key], rel=1e-6, abs=1e-9), key

    # the saved config parses back (kneas-train --config FILE)
    parsed = cli.parse_args(["--config", str(run_dir / "config.json")])
    assert parsed.method == "k-neas" and parsed.num_materials == K and parsed.preset == "tiny"

    # same scene/views/preset/seed: the prior is reused, and neas-2m gets GMM bounds with K = 2 from it
    code, out, err = run(["neas-2m", "--scene", str(tiny_scene), "--preset", "tiny", "--output-dir", str(outdir)], capsys)
    assert code == 0, err
    assert "reusing the NeAS-1M prior" in out and str(prior_dir) in out.replace("\n", "")
    run2 = run_dir_of(out)
    b2 = json.loads((run2 / "bounds.json").read_text())
    assert b2["K"] == 2 and b2["k_chosen_by"] == "given" and b2["prior_reused"] is True
    assert json.loads((run2 / "metrics.json").read_text())["num_materials"] == 2


def test_num_materials_and_bounds_file(tiny_scene, tmp_path, capsys):
    outdir = tmp_path / "out"
    code, out, err = run(["k-neas", "--scene", str(tiny_scene), "--preset", "tiny", "--output-dir", str(outdir),
                          "--num-materials", "2", "--trainer.epochs", "1"], capsys)
    assert code == 0, err
    run_dir = run_dir_of(out)
    assert json.loads((run_dir / "bounds.json").read_text())["K"] == 2
    assert json.loads((run_dir / "config.json").read_text())["num_materials"] == 2
    # explicit bounds skip the prior
    bfile = tmp_path / "b.json"
    bfile.write_text(json.dumps({"alphas": [0.3, 0.5, 0.4], "betas": [0.0, 0.3, 0.8]}))
    code, out, err = run(["k-neas", "--scene", str(tiny_scene), "--preset", "tiny", "--output-dir", str(tmp_path / "o2"),
                          "--bounds", str(bfile), "--trainer.epochs", "1"], capsys)
    assert code == 0, err
    assert "prior" not in out.split("bounds: from")[0].split("device:")[1]
    run_dir = run_dir_of(out)
    m = json.loads((run_dir / "metrics.json").read_text())
    assert m["num_materials"] == 3 and m["alphas"] == pytest.approx([0.3, 0.5, 0.4])
    # a bounds file that disagrees with --num-materials is a one-line user error
    code, _, err = run(["k-neas", "--scene", str(tiny_scene), "--preset", "tiny", "--output-dir", str(tmp_path / "o3"),
                        "--bounds", str(bfile), "--num-materials", "2"], capsys)
    assert code == 2 and err.strip().startswith("error:") and "3 materials" in err


def test_fdk_method(tiny_scene, tmp_path, capsys):
    code, out, err = run(["fdk", "--dry-run", "--scene", str(tiny_scene)], capsys)
    assert code == 0 and "parameters: 0" in out.splitlines()
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # metrics.json records the session's thread count (it moves a neural run's figures)
    try:
        code, out, err = run(["fdk", "--scene", str(tiny_scene), "--output-dir", str(tmp_path)], capsys)
    finally:
        torch.set_num_threads(threads)
    assert code == 0, err
    run_dir = run_dir_of(out)
    assert run_dir.parent == tmp_path / "tinyfoot" / "fdk"
    vol = np.load(run_dir / "volume.npy")
    assert vol.shape == (16, 16, 16) and vol.dtype == np.float32
    m = json.loads((run_dir / "metrics.json").read_text())
    for key in METRIC_KEYS:
        assert key in m, key
    assert m["threads"] == 1
    from kneas_method.engine.code_version import code_version

    assert m["code"] == code_version() and m["code"]["kneas"] == __import__("kneas_method").__version__
    assert m["machine"]["torch"] == torch.__version__ and m["machine"]["cores"] >= 1 and "gpu" not in m["machine"]
    assert m["parameters"] == 0 and m["steps"] == 0 and not list((run_dir / "checkpoints").glob("*.ckpt"))
    assert json.loads((run_dir / "config.json").read_text())["algorithm"] == "fdk"
    from kneas_method.data.naf import load_naf
    from kneas_method.engine.evaluate import evaluate_volume

    again = evaluate_volume(vol, load_naf(tiny_scene))
    assert again["psnr3d"] == pytest.approx(m["psnr3d"]) and again["psnr2d"] == pytest.approx(m["psnr2d"])


def test_non_finite_losses_are_skipped_then_stop(tiny_scene, tmp_path):
    import dataclasses

    from kneas_method import presets, registry
    from kneas_method.data.naf import load_naf
    from kneas_method.engine.checkpoint import list_checkpoints, load_latest_checkpoint
    from kneas_method.engine.trainer import Trainer

    cfg = presets.resolve(dataclasses.replace(registry.load("methods", "neas-1m").config, method="neas-1m", preset="tiny"))
    cfg = dataclasses.replace(cfg, trainer=dataclasses.replace(cfg.trainer, epochs=4, eval_every=0, checkpoint_every=1))
    scene = load_naf(tiny_scene)
    (tmp_path / "checkpoints").mkdir()
    trainer = Trainer(cfg, scene, tmp_path, epochs=4, device="cpu", label="model")
    real = trainer.model.loss_dict
    calls = {"n": 0}

    def flaky(batch, progress, generator=None):
        calls["n"] += 1
        out = real(batch, progress, generator=generator)
        if calls["n"] == 2 or calls["n"] > 5:  # one isolated bad step, then bad forever
            out = {k: v * float("nan") for k, v in out.items()}
        return out

    trainer.model.loss_dict = flaky
    with pytest.raises(KneasError, match="5 non-finite losses in a row") as exc:
        trainer.train()
    # steps 5-7 were skipped, so the epoch-2 checkpoint (step 8) still holds finite, good parameters
    assert "last good checkpoint" in str(exc.value) and "step-00000008.ckpt" in str(exc.value)
    assert trainer.bad_steps == [1, 5, 6, 7, 8, 9] and trainer.step == 10
    assert [p.name for p in list_checkpoints(tmp_path / "checkpoints")] == ["step-00000004.ckpt", "step-00000008.ckpt"]
    state, _, _ = load_latest_checkpoint(tmp_path / "checkpoints")
    assert all(torch.isfinite(v).all() for v in state["model"].values() if v.is_floating_point())
    assert all(torch.isfinite(p).all() for p in trainer.model.parameters())  # bad steps were never applied


@pytest.mark.parametrize("method", ["fdk", "k-neas"])
def test_scan_without_ground_truth_or_held_out_views(method, tmp_path, capsys):
    """A real scan (noisy, no ``image``, no held-out views): every method trains and evaluates;
    the 2D metrics use training views held out of training, 3D metrics are absent, both said."""
    import dataclasses

    from kneas_method.data.naf import save_naf
    from kneas_method.data.scene import Views
    from kneas_method.data.simulate import SimulationConfig, simulate_phantom

    s = simulate_phantom("jaw", SimulationConfig(n_voxel=16, voxel_mm=15, n_detector=16, n_train=10, n_val=2, noise=True))
    assert s.train.projections.min() < 0  # noisy air
    s = dataclasses.replace(s, val=Views(np.zeros(0), np.zeros((0, 16, 16), np.float32)), image=None, labels=None, membership=None)
    path = tmp_path / "scan.pickle"
    save_naf(s, path)
    code, out, err = run([method, "--scene", str(path), "--preset", "tiny", "--output-dir", str(tmp_path / "o")], capsys)
    assert code == 0, err
    m = json.loads((run_dir_of(out) / "metrics.json").read_text())
    assert m["n_views"] == 1 and m["views"] == 9 and math.isfinite(m["psnr2d"]) and "psnr3d" not in m
    assert any("no ground-truth volume" in n for n in m["notes"]) and any("held out of training" in n for n in m["notes"])
    assert "note: the scene has no held-out views" in out


def test_learning_rate_drops_after_the_given_fraction_of_the_steps(tiny_scene, tmp_path):
    import dataclasses

    from kneas_method import presets, registry
    from kneas_method.data.naf import load_naf
    from kneas_method.engine.trainer import Trainer

    cfg = presets.resolve(dataclasses.replace(registry.load("methods", "neas-1m").config, method="neas-1m", preset="tiny"))
    cfg = dataclasses.replace(cfg, trainer=dataclasses.replace(cfg.trainer, epochs=4, eval_every=0, checkpoint_every=0,
                                                               lr=1e-3, lr_decay_at=0.75, lr_decay_factor=0.1))
    scene = load_naf(tiny_scene)
    trainer = Trainer(cfg, scene, tmp_path, epochs=4, device="cpu", label="model")
    rates = []
    trainer.train(step_hooks=[lambda t: rates.append(t.optimizer.param_groups[0]["lr"])])
    n = trainer.total_steps
    drop = round(0.75 * n)
    assert len(rates) == n and 0 < drop < n
    # the rate after step k is the one step k + 1 uses: 1e-3 for the first 75 % of the steps, 1e-4 after
    assert rates[:drop - 1] == pytest.approx([1e-3] * (drop - 1)) and rates[drop - 1:] == pytest.approx([1e-4] * (n - drop + 1))
