"""Shared fixtures and builders of the tests (no tests here).

* ``run(argv, capsys)`` / ``run_dir_of(out)``: ``kneas-train`` in process, and the run folder it printed;
* ``simulated_foot(...)`` and the ``tiny_scene`` fixture: a tiny built-in foot scene pickle;

* a tiny two-sphere phantom scene with exact membership (known-answer surfaces);
* a tiny built-in ``foot`` scene pickle (so a run folder can name it by path);
* run folders written by hand as the trainer writes them: ``config.json``
  (``to_dict`` of a tiny resolved TrainConfig), ``checkpoints/step-*.ckpt``
  (``save_checkpoint``), ``bounds.json``; FDK runs with ``volume.npy``.
"""

from __future__ import annotations

import math

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from kneas_method import presets, registry
from kneas_method.config import to_dict
from kneas_method.data.naf import save_naf
from kneas_method.data.phantoms import Phantom, Primitive
from kneas_method.data.simulate import SimulationConfig, simulate_phantom
from kneas_method.engine.checkpoint import save_checkpoint
from kneas_method.fields.base import Field, FieldConfig, FieldOutputs

TINY_SIM = SimulationConfig(n_voxel=16, voxel_mm=8.0, n_detector=16, n_train=4, n_val=3)

# Two nested spheres (mm): material 1 (level 0.3) and material 2 (0.8) inside it.
BIG = ((6.0, -4.0, 3.0), 40.0)
SMALL = ((14.0, 2.0, -2.0), 18.0)
LEVELS = (0.3, 0.8)


def sphere_phantom() -> Phantom:
    return Phantom(
        name="spheres", description="two nested spheres", materials=("soft", "bone"), levels=LEVELS,
        primitives=(
            Primitive("ellipsoid", BIG[0], (BIG[1],) * 3, material=1, priority=1, name="big"),
            Primitive("ellipsoid", SMALL[0], (SMALL[1],) * 3, material=2, priority=2, name="small"),
        ),
    )


def sphere_scene(cfg: SimulationConfig = TINY_SIM):
    return simulate_phantom(sphere_phantom(), cfg)


def sphere_sdf_model_units(points: torch.Tensor, geometry, spheres=(BIG, SMALL), shift_mm=(0.0, 0.0, 0.0)) -> torch.Tensor:
    """Exact signed distances [P, K] (model units) of the spheres at points [P, 3] (model units)."""
    mm = geometry.mm_per_unit
    out = []
    for centre, radius in spheres:
        c = (torch.tensor(centre, dtype=points.dtype) + torch.tensor(shift_mm, dtype=points.dtype)) / mm
        out.append((points - c).norm(dim=-1) - radius / mm)
    return torch.stack(out, -1)


class AnalyticSDF(Field):
    """Stands in for a model's SDF field: exact sphere distances, zero features."""

    def __init__(self, geometry, feature_dim: int, spheres=(BIG, SMALL), shift_mm=(0.0, 0.0, 0.0)):
        super().__init__(FieldConfig())
        self.geometry, self.feature_dim, self.spheres, self.shift_mm = geometry, feature_dim, spheres, shift_mm
        self.num_materials = self.num_distances = len(spheres)

    def get_outputs(self, points, with_gradients=False):
        d = sphere_sdf_model_units(points, self.geometry, self.spheres, self.shift_mm)
        return FieldOutputs(distances=d, features=torch.zeros(len(points), self.feature_dim))


def tiny_config(method: str, scene_path: str, **kw):
    spec = registry.methods()[method]
    cfg = dataclasses.replace(spec.config, method=method, scene=str(scene_path), preset="tiny", device="cpu", **kw)
    return presets.resolve(cfg)


def exact_sphere_model(scene, shift_mm=(0.0, 0.0, 0.0), sharpness: float = 1e4):
    """A real tiny k-neas CTModel (K = 2) whose SDF field is replaced by the exact sphere SDFs;
    its attenuation bounds put material 1 near 0.3 and material 2 near 0.8."""
    cfg = tiny_config("k-neas", "unused", num_materials=2)
    torch.manual_seed(0)
    model = cfg.model.setup(scale=scene.geometry.scale)
    model.set_bounds([0.1, 0.1], [0.25, 0.75])
    model.field = AnalyticSDF(scene.geometry, model.field.feature_dim, shift_mm=shift_mm)
    with torch.no_grad():
        model.boundary.log_s.fill_(math.log(sharpness) / model.boundary.LOG_SCALE)
    return model.eval()


def calibrate_surfaces(model, geometry) -> None:
    """Shift a (random, untrained) SDF model's distance biases so that d_k < 0 on a share of
    the voxel centres (1/2 for material 1, less for higher ones): real surfaces to export,
    without training (a forward pass, no optimisation)."""
    with torch.no_grad():
        d = model.field.distances(geometry.voxel_centres().reshape(-1, 3))
        K = d.shape[-1]
        for k in range(K):
            q = 0.5 / (k + 1)
            model.field.mlp[-1].bias[k] -= torch.quantile(d[:, k], q)


def foot_scene_file(folder: Path) -> Path:
    """A tiny built-in ``foot`` scene pickle (membership re-attached on load)."""
    path = Path(folder) / "foot_tiny.pickle"
    if not path.is_file():
        save_naf(simulate_phantom("foot", TINY_SIM), path)
    return path


def sphere_scene_file(folder: Path) -> Path:
    path = Path(folder) / "spheres_tiny.pickle"
    if not path.is_file():
        save_naf(sphere_scene(), path)
    return path


def write_run(folder: Path, method: str, scene_path: Path, *, fit: bool = True, step: int = 7, **kw) -> Path:
    """A run folder as the trainer writes it (config.json, checkpoints/, bounds.json, metrics.json, figures/)."""
    from kneas_method.data.scenes import resolve_scene

    run = Path(folder) / "spheres" / method / "20250101-000000"
    (run / "checkpoints").mkdir(parents=True)
    (run / "figures").mkdir()
    cfg = tiny_config(method, scene_path, **kw)
    (run / "config.json").write_text(json.dumps(to_dict(cfg), indent=2))
    scene = resolve_scene(str(scene_path))
    torch.manual_seed(0)
    model = cfg.model.setup(scale=scene.geometry.scale)
    if model.has_surfaces:
        K = model.num_materials
        alphas, betas = [0.1] * K, list(np.linspace(0.25, 0.75, K))
        model.set_bounds(alphas, betas)
        (run / "bounds.json").write_text(json.dumps({"alphas": alphas, "betas": betas}))
        if fit:
            calibrate_surfaces(model, scene.geometry)
    save_checkpoint(run / "checkpoints", {"method": method, "step": step, "epoch": 1, "model": model.state_dict()})
    (run / "metrics.json").write_text("{}")
    return run


def write_fdk_run(folder: Path, scene_path: Path, volume: np.ndarray) -> Path:
    run = Path(folder) / "spheres" / "fdk" / "20250101-000000"
    run.mkdir(parents=True)
    data = to_dict(tiny_config("fdk", scene_path))
    (run / "config.json").write_text(json.dumps(data))
    np.save(run / "volume.npy", volume.astype(np.float32))
    return run


def simulated_foot(folder, name: str, n: int, voxel_mm: float, n_train: int, n_val: int = 4):
    """The built-in foot phantom simulated at n^3 voxels / n^2 detector, saved as ``folder/name.pickle``."""
    path = folder / f"{name}.pickle"
    cfg = SimulationConfig(n_voxel=n, voxel_mm=voxel_mm, n_detector=n, n_train=n_train, n_val=n_val)
    save_naf(simulate_phantom("foot", cfg), path)
    return path


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    return simulated_foot(tmp_path_factory.mktemp("scene"), "tinyfoot", 16, 15.0, n_train=4)


def run(argv, capsys):
    """``kneas-train argv`` in process: ``(exit code, stdout, stderr)``."""
    from kneas_method.cli import train as cli

    with pytest.raises(SystemExit) as exc:
        cli.main(argv)
    out = capsys.readouterr()
    return exc.value.code, out.out, out.err


def run_dir_of(out: str) -> Path:
    """The run folder ``kneas-train`` printed last (``run folder: ...``)."""
    lines = [line for line in out.splitlines() if line.startswith("run folder: ")]
    assert lines, out
    return Path(lines[-1].split("run folder: ", 1)[1].strip())
