"""The two ways a model's held-out projections are made for its 2D metrics (``trainer.eval_projections``).

``rendered`` integrates the field along each ray; ``volume`` projects the field's volume at the voxel
centres with the Joseph projector, the operator that scores a classical volume. On a field that is
smooth at the voxel scale the two must agree, and a volume off by one voxel must not.
"""

import dataclasses

import numpy as np
import pytest

from kneas_method.classical.projector import forward
from kneas_method.data.simulate import SimulationConfig
from kneas_method.engine.evaluate import evaluate_model, evaluate_volume, render_views, sample_volume
from conftest import exact_sphere_model, sphere_scene, tiny_config


@pytest.fixture(scope="module")
def scene():
    # 32^3 voxels of 4 mm, 32^2 detector: the off-centre spheres make a mirrored or shifted volume visible
    return sphere_scene(SimulationConfig(n_voxel=32, voxel_mm=4.0, n_detector=32, n_train=4, n_val=3))


def _rms_of_max(a, b) -> float:
    return float(np.sqrt(np.mean((a - b) ** 2)) / np.abs(b).max())


def test_projected_volume_equals_rendered_field_when_smooth(scene):
    model = exact_sphere_model(scene, sharpness=30.0)  # surfaces blurred over about a voxel
    angles = np.asarray(scene.val.angles)
    rendered = render_views(model, scene, angles, n_samples=512)
    volume = sample_volume(model, scene.geometry)
    projected = forward(volume, scene.geometry, angles)
    assert rendered.max() > 0.02  # the rays cross material (sphere levels 0.3 and 0.8, data units)
    assert _rms_of_max(projected, rendered) < 0.003
    # the comparison has teeth: the same volume one voxel off, or mirrored, is far outside the tolerance
    assert _rms_of_max(forward(np.roll(volume, 1, axis=0), scene.geometry, angles), rendered) > 0.01
    assert _rms_of_max(forward(volume[::-1].copy(), scene.geometry, angles), rendered) > 0.01


def test_volume_mode_scores_a_model_as_a_classical_volume(scene):
    model = exact_sphere_model(scene, sharpness=30.0)
    config = tiny_config("k-neas", "unused", num_materials=2)
    as_volume = dataclasses.replace(config, trainer=dataclasses.replace(config.trainer, eval_projections="volume"))
    metrics, (proj, volume) = evaluate_model(model, scene, as_volume, "cpu", return_arrays=True)
    classical = evaluate_volume(volume, scene)
    assert metrics["projections_2d"] == "volume" and classical["projections_2d"] == "volume"
    for key in ("psnr2d", "ssim2d", "psnr3d", "ssim3d"):
        assert metrics[key] == pytest.approx(classical[key], rel=1e-9), key
    rendered = evaluate_model(model, scene, config, "cpu")  # the tiny preset renders, as the paper
    assert config.trainer.eval_projections == "rendered" and rendered["projections_2d"] == "rendered"
    assert rendered["psnr3d"] == pytest.approx(metrics["psnr3d"], rel=1e-9)  # same volume either way
    assert rendered["psnr2d"] != metrics["psnr2d"]
