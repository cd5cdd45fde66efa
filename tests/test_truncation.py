"""A scan whose object goes on beyond the box along the rotation axis is named in a warning (data.truncation)."""

import dataclasses
import json
import math

import numpy as np
import pytest
import torch

from kneas_method.data.naf import load_naf, save_naf
from kneas_method.data.scene import Views
from kneas_method.classical.options import ReconstructionOptions
from kneas_method.data.truncation import ROW_OBJECT_SHARE, axial_truncation, lateral_truncation, truncation_warning
from kneas_method.stages.classical_start import WIDE_START_ITERATIONS, classical_volume, start_options

from conftest import run, run_dir_of, simulated_foot


def test_axial_truncation_counts_the_views_whose_end_rows_see_the_object():
    p = np.zeros((4, 6, 20), dtype=np.float32)
    p[:, 2:4, 5:15] = 0.3  # the object in the middle rows only
    assert axial_truncation(p, 0.0) == 0.0
    p[:2, 0, 3:17] = 0.05  # two views' first row crosses it
    assert axial_truncation(p, 0.0) == 0.5
    assert axial_truncation(p, 0.1) == 0.0  # below the air threshold: noise in air
    p[2, -1, : int(ROW_OBJECT_SHARE * 20) - 1] = 0.05  # a few pixels of the last row: not the object going on
    assert axial_truncation(p, 0.0) == 0.5


def test_a_truncated_scan_is_named_in_a_warning_and_still_reconstructed(tmp_path, capsys):
    path = simulated_foot(tmp_path, "foot", 16, 15.0, n_train=4)
    scene = load_naf(path)
    assert truncation_warning(scene) is None
    cut = scene.train.projections.copy()
    cut[:, 0, :] = cut[:, 0, :] + 0.02  # tissue crosses the first row in every view
    truncated = dataclasses.replace(scene, train=Views(scene.train.angles, cut))
    assert "4 of 4 training views" in truncation_warning(truncated)
    save_naf(truncated, tmp_path / "long.pickle")
    code, out, _ = run(["fdk", "--scene", str(tmp_path / "long.pickle"), "--preset", "tiny", "--output-dir", str(tmp_path / "o")], capsys)
    assert code == 0 and "warning: the object reaches the detector's first or last row in 4 of 4 training views" in out
    code, out, _ = run(["fdk", "--scene", str(path), "--preset", "tiny", "--output-dir", str(tmp_path / "o")], capsys)
    assert code == 0 and "warning: the object reaches" not in out
    from kneas_method.cli import data as data_cli

    for scene_path, warned in ((tmp_path / "long.pickle", True), (path, False)):  # kneas-data inspect says it too
        with pytest.raises(SystemExit) as exc:
            data_cli.main(["inspect", str(scene_path)])
        out = capsys.readouterr().out
        assert exc.value.code == 0 and ("warning: the object reaches" in out) == warned


# ------------------------------------------------------------------ the longer box the views are fitted on
from kneas_method.classical.projector import forward  # noqa: E402
from kneas_method.classical.reconstruct import reconstruct  # noqa: E402
from kneas_method.data.scene import Scene  # noqa: E402
from kneas_method.data.truncation import axial_margin, extend_axially, fitting_scene  # noqa: E402
from kneas_method.engine.evaluate import evaluate_volume  # noqa: E402
from kneas_method.evaluation.metrics import volume_metrics  # noqa: E402
from kneas_method.geometry import Geometry  # noqa: E402


def _geometry(mode="cone", nz=16, off_z=0.0, rows=24, off_v=0.0):
    return Geometry.from_mm(mode=mode, DSD=600.0, DSO=400.0, nDetector=(24, rows), dDetector=(3.0, 3.0), nVoxel=(16, 16, nz),
                            dVoxel=(4.0, 4.0, 4.0), offOrigin=(0.0, 0.0, off_z), offDetector=(0.0, off_v))


def _reach_of_rays(geometry, samples=400) -> float:
    """The naive version: the largest |z| of points on every detector ray within the cylinder about
    the axis through the box's xy corners (model units)."""
    angles = np.array([0.0, 1.0])
    o, d = geometry.rays(angles, dtype=torch.float64)
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    hx, hy, _ = geometry.volume_half_size
    r = math.hypot(hx, hy)
    t = torch.linspace(0.0, 2.0 * geometry.dso, samples, dtype=torch.float64)
    p = o[:, None] + t[None, :, None] * d[:, None]
    inside = p[..., 0].hypot(p[..., 1]) <= r
    return float(p[..., 2].abs()[inside].max())


@pytest.mark.parametrize("mode,rows,off_v,added", [("cone", 24, 0.0, False), ("cone", 40, 0.0, True), ("cone", 32, 12.0, True),
                                                   ("cone", 80, 0.0, True), ("parallel", 40, 0.0, True)])
def test_the_longer_box_reaches_as_far_as_the_rays_or_the_fields_domain(mode, rows, off_v, added):
    g = _geometry(mode, rows=rows, off_v=off_v)
    n = axial_margin(g)
    assert (n > 0) == added
    half = g.volume_half_size[2]
    reach = _reach_of_rays(g)
    assert half + n * g.d_voxel[2] <= 1.0 + 1e-9  # within the fields' domain
    if half + (n + 1) * g.d_voxel[2] <= 1.0:  # not capped: the box holds every ray's stretch, and no more than a slice beyond
        assert half + n * g.d_voxel[2] >= reach - 1e-9
        assert n == 0 or half + (n - 1) * g.d_voxel[2] < reach
    assert axial_margin(g, reach=half) == 0  # no room: nothing added


def test_the_fitting_box_is_the_scene_itself_unless_the_object_goes_on(tmp_path):
    path = simulated_foot(tmp_path, "foot", 16, 15.0, n_train=4)
    scene = load_naf(path)
    box = fitting_scene(scene)
    assert box.scene is scene and box.slices == 0 and box.crop(scene.image) is scene.image
    longer = extend_axially(scene, 3)
    g, h = scene.geometry, longer.geometry
    assert h.n_voxel == (*g.n_voxel[:2], g.n_voxel[2] + 6) and h.scale == g.scale and h.d_voxel == g.d_voxel
    z, z_long = g.voxel_axes(dtype=torch.float64)[2], h.voxel_axes(dtype=torch.float64)[2]
    assert torch.allclose(z_long[3:-3], z)  # the scene's voxel centres are the longer box's middle ones
    assert longer.image is None and longer.train is scene.train


def _long_rod_scene():
    """A box of 16^3 voxels of 4 mm inside a rod twice as long: the object goes on beyond both ends."""
    g = _geometry(nz=16, rows=40)  # the detector sees more than the box's length
    long = dataclasses.replace(g, n_voxel=(16, 16, 48))
    x, y, _ = (a.numpy() for a in long.voxel_axes(dtype=torch.float64))
    rr = np.hypot(*np.meshgrid(x, y, indexing="ij"))
    rod = np.where(rr < 0.6 * g.volume_half_size[0], 0.5, 0.0)[..., None] + np.zeros(48)
    rod[(rr < 0.25 * g.volume_half_size[0])] = 1.0
    rod = rod.astype(np.float32)
    angles = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    val = np.array([0.1, 1.7])
    proj = forward(rod, long, angles)
    val_proj = forward(rod, long, val)
    return Scene("rod", g, Views(angles, proj), Views(val, val_proj), image=rod[..., 16:32].copy())


def test_fitting_a_truncated_scan_on_the_longer_box_mends_the_end_slices():
    scene = _long_rod_scene()
    box = fitting_scene(scene)
    assert box.slices > 0 and box.scene.geometry.n_voxel[2] == 16 + 2 * box.slices
    plain = reconstruct("sart", scene).volume
    longer = box.crop(np.asarray(reconstruct("sart", box.scene).volume))
    assert longer.shape == scene.image.shape
    ends = np.r_[0:3, 13:16]
    psnr = lambda v: volume_metrics(np.asarray(v)[..., ends], scene.image[..., ends], ssim=False)["psnr3d"]  # noqa: E731
    assert psnr(longer) > psnr(plain) + 3.0


def _eval(run_dir, capsys):
    from kneas_method.cli.eval import main as eval_main

    with pytest.raises(SystemExit) as exc:
        eval_main([str(run_dir), "--no-figures", "-o", str(run_dir / "ev")])
    assert exc.value.code == 0
    capsys.readouterr()
    return json.loads((run_dir / "ev" / "metrics.json").read_text())


def test_runs_on_a_truncated_scan_fit_the_longer_box_and_score_the_scenes(tmp_path, capsys):
    scene = _long_rod_scene()
    save_naf(scene, tmp_path / "rod.pickle")
    box = fitting_scene(load_naf(tmp_path / "rod.pickle"))
    code, out, _ = run(["sart", "--scene", str(tmp_path / "rod.pickle"), "--preset", "tiny", "--output-dir", str(tmp_path / "o")], capsys)
    assert code == 0 and f"fitted on a box {box.slices} slices" in out
    sart = run_dir_of(out)
    metrics = json.loads((sart / "metrics.json").read_text())
    assert metrics["fitting_box_extra_slices"] == box.slices
    volume = np.load(sart / "volume.npy")
    assert volume.shape == scene.image.shape  # the scene's box
    cropped_only = evaluate_volume(volume, scene)["psnr2d"]  # held-out views of the box alone miss the rod beyond it
    assert metrics["psnr2d"] > cropped_only + 5.0
    assert _eval(sart, capsys)["psnr2d"] == pytest.approx(metrics["psnr2d"], abs=1e-6)  # kneas-eval projects the longer box too

    code, out, _ = run(["k-neas", "--scene", str(tmp_path / "rod.pickle"), "--preset", "tiny", "--model.occupancy-grid", "True",
                        "--output-dir", str(tmp_path / "o")], capsys)
    assert code == 0
    neural = run_dir_of(out)
    metrics = json.loads((neural / "metrics.json").read_text())
    assert metrics["fitting_box_extra_slices"] == box.slices
    from kneas_method.engine.loading import load_run

    model = load_run(neural).model
    reach = box.scene.geometry.volume_half_size[2]
    assert model.occupancy_box[1, 2].item() == pytest.approx(reach, rel=1e-5)  # empty space carved over the longer box
    assert model.occupancy_box[1, 2].item() > scene.geometry.volume_half_size[2] * 1.1
    again = _eval(neural, capsys)
    assert again["psnr2d"] == pytest.approx(metrics["psnr2d"], abs=1e-4) and again["psnr3d"] == pytest.approx(metrics["psnr3d"], abs=1e-4)


def test_lateral_truncation_counts_the_outer_columns_only():
    p = np.zeros((4, 10, 12), dtype=np.float32)
    p[:, :, 2:10] = 0.3  # inside the field of view
    assert lateral_truncation(p, 0.0) == 0.0
    p[:3, :, 0] = 0.05  # three views' first column crosses the object
    assert lateral_truncation(p, 0.0) == 0.75
    assert lateral_truncation(p, 0.0, off_u=1.0) == 0.0  # an offset detector's shorter side crosses it by design
    assert lateral_truncation(p, 0.0, off_u=-1.0) == 0.75  # its outer side is the first column then
    assert lateral_truncation(p, 0.1) == 0.0  # below the air threshold: noise in air


def test_an_object_wider_than_the_field_of_view_is_named_in_a_warning(tmp_path):
    path = simulated_foot(tmp_path, "foot", 16, 15.0, n_train=4)
    scene = load_naf(path)
    lines = []
    box = fitting_scene(scene, say=lines.append)
    assert box.slices == 0 and not box.wider_than_view and lines == []
    wide = scene.train.projections.copy()
    wide[:, :, -1] += 0.02  # tissue at the last column in every view
    box = fitting_scene(dataclasses.replace(scene, train=Views(scene.train.angles, wide)), say=lines.append)
    assert box.slices == 0 and len(lines) == 1 and "wider than the field of view" in lines[0] and "4 of 4" in lines[0]
    assert box.wider_than_view and box.scene.geometry == scene.geometry  # the box is kept


def test_a_start_for_an_object_wider_than_the_view_runs_further_unless_a_count_is_given():
    default = ReconstructionOptions()
    assert start_options("asd-pocs", default, True).iterations == WIDE_START_ITERATIONS["asd-pocs"] == 40
    assert start_options("asd-pocs", default, False) is default  # the preset's count (10) elsewhere
    given = ReconstructionOptions(iterations=7)
    assert start_options("asd-pocs", given, True) is given  # the user's count wins
    assert start_options("sart", default, True) is default and start_options("fdk", default, True) is default
    # few views: the default count's single-view updates on 50 views (asd-pocs 10 x 50, sart 5 x 50), never fewer
    assert start_options("asd-pocs", default, False, 5).iterations == 100
    assert start_options("asd-pocs", default, False, 20).iterations == 25 and start_options("sart", default, False, 10).iterations == 25
    assert start_options("asd-pocs", default, False, 50) is default and start_options("asd-pocs", default, False, 360) is default
    assert start_options("asd-pocs", default, True, 5).iterations == 100 and start_options("asd-pocs", default, True, 25).iterations == 40
    assert start_options("asd-pocs", given, False, 5) is given and start_options("cgls", default, False, 5) is default


def test_a_cached_start_with_another_iteration_count_is_computed_again(tmp_path):
    scene = load_naf(simulated_foot(tmp_path, "foot", 16, 15.0, n_train=4))
    first = classical_volume("asd-pocs", ReconstructionOptions(iterations=1), scene, tmp_path, "cpu")
    again = classical_volume("asd-pocs", ReconstructionOptions(iterations=1), scene, tmp_path, "cpu")
    assert again.settings["iterations"] == 1 and np.array_equal(again.volume, first.volume)  # reused
    further = classical_volume("asd-pocs", ReconstructionOptions(iterations=3), scene, tmp_path, "cpu")
    assert further.settings["iterations"] == 3 and not np.array_equal(further.volume, first.volume)
    assert json.loads((tmp_path / "asd-pocs_volume.json").read_text())["settings"]["iterations"] == 3


def test_a_neural_runs_start_is_run_further_where_the_object_is_wider_than_the_view(tmp_path):
    from kneas_method import registry
    from kneas_method.stages import RunState
    from kneas_method.stages.classical_start import ClassicalStartConfig

    scene = load_naf(simulated_foot(tmp_path, "foot", 16, 15.0, n_train=25))
    config = registry.load("methods", "k-neas").config
    assert config.reconstruction.iterations is None
    for wide, count in ((False, 20), (True, 40)):  # 25 views: 10 x 50 / 25 single-view updates; wide: 40
        run_dir = tmp_path / f"run-{wide}"
        run_dir.mkdir()
        state = RunState(config=config, scene=scene, run_dir=run_dir, device="cpu", started=0.0, loss_scale=1.0, say=print,
                         fitting_wider_than_view=wide)
        ClassicalStartConfig(algorithm="asd-pocs").setup().run(state)
        assert state.records["classical-start"]["settings"]["iterations"] == count and state.start[1] == "asd-pocs"
