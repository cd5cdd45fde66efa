"""The CUDA path against the CPU path: same numbers, and a run trained on a GPU loads on a CPU.

These need a CUDA GPU (CI has none; they are run on one when one is at hand,
``benchmarks/gpu_check.sh``). Everything they compare is also tested on the CPU.
"""

import json

import numpy as np
import pytest
import torch

from kneas_method.classical import projector
from kneas_method.classical.iterative import asd_pocs, sart
from kneas_method.data.scenes import resolve_scene
from kneas_method.fields.hash_grid import HashGridConfig

from conftest import run, run_dir_of, tiny_config

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU (CI has none)")


def test_hash_grid_cuda_matches_cpu():
    torch.manual_seed(0)
    enc = HashGridConfig(num_levels=6, log2_hashmap_size=12, base_resolution=4, implementation="torch").setup()
    with torch.no_grad():
        enc.table.uniform_(-1.0, 1.0)
    x = torch.rand(4096, 3) * 2 - 1
    gpu = HashGridConfig(num_levels=6, log2_hashmap_size=12, base_resolution=4, implementation="torch").setup().cuda()
    gpu.load_state_dict(enc.state_dict())
    xc, xg = x.clone().requires_grad_(True), x.cuda().requires_grad_(True)
    out_c, out_g = enc(xc), gpu(xg)
    torch.testing.assert_close(out_g.cpu(), out_c, rtol=1e-5, atol=1e-5)
    w = torch.randn_like(out_c)
    (out_c * w).sum().backward()
    (out_g * w.cuda()).sum().backward()
    torch.testing.assert_close(gpu.table.grad.cpu(), enc.table.grad, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(xg.grad.cpu(), xc.grad, rtol=1e-3, atol=1e-3)


def test_projector_and_classical_cuda_match_cpu(tiny_scene):
    scene = resolve_scene(str(tiny_scene))
    g, angles = scene.geometry, scene.train.angles
    vol = torch.as_tensor(scene.image, dtype=torch.float32)
    fwd_c = projector.forward(vol, g, angles, device="cpu")
    fwd_g = projector.forward(vol.cuda(), g, angles, device="cuda")
    torch.testing.assert_close(fwd_g.cpu(), fwd_c, rtol=1e-4, atol=1e-4 * float(fwd_c.abs().max()))
    back_c = projector.back(fwd_c, g, angles, device="cpu")
    back_g = projector.back(fwd_g, g, angles, device="cuda")
    torch.testing.assert_close(back_g.cpu(), back_c, rtol=1e-4, atol=1e-4 * float(back_c.abs().max()))
    proj = scene.train.projections
    for algorithm in (sart, asd_pocs):
        on_cpu = np.asarray(algorithm(proj, g, angles, iterations=3, device="cpu"))
        on_gpu = np.asarray(algorithm(proj, g, angles, iterations=3, device="cuda"))
        np.testing.assert_allclose(on_gpu, on_cpu, rtol=1e-3, atol=1e-3 * float(np.abs(on_cpu).max()))


def test_model_outputs_cuda_match_cpu(tiny_scene):
    scene = resolve_scene(str(tiny_scene))
    cfg = tiny_config("k-neas", str(tiny_scene), num_materials=3)
    torch.manual_seed(0)
    model = cfg.model.setup(scale=scene.geometry.scale)
    model.set_bounds([0.1, 0.1, 0.1], [0.2, 0.5, 0.8])
    gpu = cfg.model.setup(scale=scene.geometry.scale).cuda()
    gpu.set_bounds([0.1, 0.1, 0.1], [0.2, 0.5, 0.8])
    gpu.load_state_dict(model.state_dict())
    pts = scene.geometry.voxel_centres().reshape(-1, 3).float()
    with torch.no_grad():
        on_cpu, on_gpu = model.query(pts), gpu.query(pts.cuda())
    for key in ("mu", "weights", "distances", "mu_materials"):
        torch.testing.assert_close(on_gpu[key].cpu(), on_cpu[key], rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("method, preset, extra", [
    ("k-neas", "tiny", []),
    # the cpu preset's stages on a GPU: ASD-POCS warm start and bounds, occupancy grid, band correction
    ("k-neas", "cpu", ["--trainer.epochs", "1", "--stages.warm-start.steps", "10", "--stages.correction.passes", "2"]),
    ("neas-2m", "tiny", []),  # the hard selector
    ("naf", "tiny", []),  # a field without surfaces
    ("sart", "tiny", []),  # a classical method's run folder
])
def test_run_on_cuda_evaluates_the_same_on_cpu(method, preset, extra, tiny_scene, tmp_path, capsys):
    from kneas_method.cli import eval as eval_cli

    code, out, err = run([method, "--scene", str(tiny_scene), "--preset", preset, "--device", "cuda",
                          "--output-dir", str(tmp_path / "out"), *extra], capsys)
    assert code == 0, err
    run_dir = run_dir_of(out)
    trained = json.loads((run_dir / "metrics.json").read_text())
    with pytest.raises(SystemExit) as exc:
        eval_cli.main([str(run_dir), "--device", "cpu", "--output", str(tmp_path / "cpu_eval"), "--no-figures"])
    assert exc.value.code == 0, capsys.readouterr().err
    again = json.loads((tmp_path / "cpu_eval" / "metrics.json").read_text())
    for key in ("psnr3d", "ssim3d", "psnr2d"):
        assert again[key] == pytest.approx(trained[key], abs=0.05), key
