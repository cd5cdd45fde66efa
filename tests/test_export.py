"""Run loading and `kneas-export` (mesh, volume, figures) on hand-written tiny run folders."""

import dataclasses
import json
import shutil

import numpy as np
import pytest
import torch

from kneas_method.cli import export as export_cli
from kneas_method.engine.loading import convert_hash_tables, load_run
from kneas_method.errors import KneasError
from kneas_method.export.mesh import import_open3d
from kneas_method.export.volume import volume_affine

from conftest import sphere_scene_file, write_fdk_run, write_run

import nibabel as nib  # noqa: E402  (the [nifti] extra, part of the test install)

o3d = import_open3d()  # the [mesh] extra, part of the test install; libusb from PyPI's libusb-package


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    root = tmp_path_factory.mktemp("runs")
    scene_path = sphere_scene_file(root)
    return {"root": root, "scene": scene_path, "kneas": write_run(root / "a", "k-neas", scene_path, num_materials=2)}


def _cli(argv):
    with pytest.raises(SystemExit) as exc:
        export_cli.main(argv)
    return exc.value.code


# ------------------------------------------------------------------ loading
def test_load_run_and_moved_checkpoint(files, tmp_path):
    run = load_run(files["kneas"])
    assert run.model is not None and run.model.num_materials == 2 and run.step == 7 and not run.model.training
    assert run.config.method == "k-neas" and run.scene.name == "spheres_tiny"
    assert next(run.model.parameters()).device.type == "cpu"
    # a checkpoint moved to another machine: config.json next to the .ckpt, no checkpoints/ folder
    moved = tmp_path / "moved"
    moved.mkdir()
    shutil.copy(files["kneas"] / "config.json", moved)
    ckpt = next((files["kneas"] / "checkpoints").glob("step-*.ckpt"))
    shutil.copy(ckpt, moved / ckpt.name)
    again = load_run(moved / ckpt.name)
    assert again.checkpoint_path == moved / ckpt.name
    pts = torch.rand(20, 3) - 0.5
    assert torch.allclose(again.model.query(pts)["mu"], run.model.query(pts)["mu"])


def test_incomplete_runs_name_what_is_missing(files, tmp_path):
    bare = tmp_path / "bare"
    bare.mkdir()
    with pytest.raises(KneasError, match=r"no config\.json, so it is not a kneas run folder"):
        load_run(bare)
    shutil.copy(files["kneas"] / "config.json", bare)
    with pytest.raises(KneasError, match=r"no checkpoint.*kneas-train --resume"):
        load_run(bare)
    fdk = tmp_path / "fdk"
    fdk.mkdir()
    cfg = json.loads((files["kneas"] / "config.json").read_text())
    cfg["method"] = "fdk"
    (fdk / "config.json").write_text(json.dumps(cfg))
    with pytest.raises(KneasError, match=r"no volume\.npy.*kneas-train --resume"):
        load_run(fdk)
    with pytest.raises(KneasError, match="does not exist"):
        load_run(tmp_path / "nowhere")


def test_tcnn_tables_convert_to_torch(files):
    run = load_run(files["kneas"])
    state = run.model.state_dict()
    key = next(k for k in state if k.endswith("encoding.table"))
    tcnn_state = {(k[: -len("table")] + "encoding.params" if k == key else k): (v.reshape(-1) if k == key else v) for k, v in state.items()}
    back = convert_hash_tables(tcnn_state, run.model)
    assert set(back) == set(state) and torch.equal(back[key], state[key])


# -------------------------------------------------------------------- meshes
def test_mesh_export_kneas(files, tmp_path, capsys):
    out = tmp_path / "mesh"
    assert _cli(["mesh", str(files["kneas"]), "-o", str(out), "--resolution", "40"]) == 0
    text = capsys.readouterr().out
    info = json.loads((out / "meshes.json").read_text())
    assert info["kind"] == "sdf" and len(info["meshes"]) == 2 and info["combined"] is not None
    run = load_run(files["kneas"])
    g = run.scene.geometry
    half_mm = np.array(g.volume_half_size) * g.mm_per_unit
    total = 0
    for m in info["meshes"] + [info["combined"]]:
        mesh = o3d.io.read_triangle_mesh(m["path"])
        assert len(mesh.triangles) == m["triangles"] > 0 and len(mesh.vertices) == m["vertices"]
        v = np.asarray(mesh.vertices)
        assert (np.abs(v) <= half_mm + 1e-3).all()  # mm, inside the volume box
        assert f"{m['vertices']} vertices, {m['triangles']} triangles" in text
        assert isinstance(m["watertight"], bool)
        if m["name"] != "combined" and m["in_combined"]:
            total += m["triangles"]
    assert info["combined"]["triangles"] == total
    assert "(checked by: watertight when every part is)" in text


def test_visible_meshes_are_the_shell_free_fields_evaluation_scores(files, tmp_path, monkeypatch):
    """--surface visible contours the fields with partial-volume shells relabelled, the ones
    kneas-eval scores; raw contours each d_k."""
    from kneas_method.evaluation import surfaces
    from kneas_method.export import mesh as mesh_module

    calls = []
    real = surfaces.shell_free_fields
    monkeypatch.setattr(surfaces, "shell_free_fields", lambda *a, **k: calls.append(a[2]) or real(*a, **k))
    run = load_run(files["kneas"])
    grid, fields, kind = mesh_module.sample_fields(run, 40, surface="visible")
    assert kind == "sdf" and fields.shape == tuple(grid.n_voxel) + (2,) and len(calls) == 1
    assert np.allclose(calls[0], mesh_module.material_levels(run)[1])
    _, raw, _ = mesh_module.sample_fields(run, 40, surface="raw")
    assert len(calls) == 1 and not np.allclose(raw, fields)
    out = tmp_path / "visible"
    assert _cli(["mesh", str(files["kneas"]), "-o", str(out), "--resolution", "40", "--surface", "visible"]) == 0
    assert json.loads((out / "meshes.json").read_text())["meshes"][0]["source"] == "visible region of material 1"


def _ball(shape, centre, radius):
    idx = np.indices(shape).astype(np.float64)
    return np.sqrt(sum((i - c) ** 2 for i, c in zip(idx, centre))) <= radius


def test_outer_layers_finds_the_near_air_rim_only():
    from kneas_method.export.mesh import outer_layers

    shape = (40, 40, 40)
    body = _ball(shape, (20, 20, 20), 14)
    rim = _ball(shape, (20, 20, 20), 15.2) & ~body  # about one voxel thick, outside the body
    bone = _ball(shape, (20, 20, 20), 6)
    labels = np.zeros(shape, np.uint8)
    labels[rim], labels[body], labels[bone] = 1, 2, 3
    # the rim's attenuation (0.07) is nearer air's (0) than soft tissue's (0.28): a partial-volume layer
    assert outer_layers(labels, [0.07, 0.28, 0.9]) == [1]
    # the same thin layer with an attenuation nearer the tissue's is a material (a thin coat)
    assert outer_layers(labels, [0.2, 0.28, 0.9]) == []
    # a thick low-attenuation material (lung) is kept although its attenuation is near air's
    lung = np.zeros(shape, np.uint8)
    lung[body], lung[bone] = 2, 1
    assert outer_layers(lung, [0.04, 0.28, 0.9]) == []
    # a thin dense layer (enamel) is not near air
    enamel = labels.copy()
    enamel[rim] = 3
    enamel[bone] = 1
    assert outer_layers(enamel, [0.5, 0.28, 1.0]) == []


def test_mesh_export_leaves_the_outer_rim_out_of_the_combined_mesh(files, tmp_path, capsys, monkeypatch):
    from kneas_method.export import mesh as mesh_module

    monkeypatch.setattr(mesh_module, "outer_layers_of_run", lambda run, chunk=65536: [1])
    out = tmp_path / "rim"
    assert _cli(["mesh", str(files["kneas"]), "-o", str(out), "--resolution", "40"]) == 0
    text = capsys.readouterr().out
    info = json.loads((out / "meshes.json").read_text())
    first, second = info["meshes"]
    assert not first["in_combined"] and second["in_combined"] and (out / "material-1.ply").is_file()
    assert info["combined"]["triangles"] == second["triangles"]
    assert "partial-volume rim" in text and "not in the combined mesh" in text


def test_isosurface_of_exact_sphere_in_mm(files):
    from kneas_method.evaluation.surfaces import grid_points
    from kneas_method.export.mesh import drop_fragments, isosurface

    run = load_run(files["kneas"])
    grid, (xs, ys, zs) = grid_points(run.scene.geometry, resolution=48)
    mm = grid.mm_per_unit
    c, r = np.array([6.0, -4.0, 3.0]), 40.0
    X, Y, Z = np.meshgrid(xs.numpy() * mm, ys.numpy() * mm, zs.numpy() * mm, indexing="ij")
    field = np.sqrt((X - c[0]) ** 2 + (Y - c[1]) ** 2 + (Z - c[2]) ** 2) - r
    # a tiny separate blob, to be dropped as a fragment
    field = np.minimum(field, np.sqrt((X - 50) ** 2 + (Y - 50) ** 2 + (Z - 50) ** 2) - 3.0)
    mesh, extractor = isosurface(field, grid, 0.0)
    comps, dropped, _ = drop_fragments(mesh, 64)
    assert comps == 2 and dropped == 1
    v = np.asarray(mesh.vertices)
    assert np.allclose(np.linalg.norm(v - c, axis=1), r, atol=0.5)
    assert mesh.is_watertight()
    # outward-facing triangles: the signed volume is positive and close to the sphere's
    t = np.asarray(mesh.triangles)
    signed = np.einsum("ij,ij->i", v[t[:, 0]], np.cross(v[t[:, 1]], v[t[:, 2]])).sum() / 6.0
    assert signed == pytest.approx(4 / 3 * np.pi * r**3, rel=0.03)
    assert extractor


def test_mesh_of_an_imported_scene_lies_in_the_scanner_world(files, tmp_path):
    """An imported scan's meshes are written in its scanner world (LPS mm), like its .mha volumes:
    the same surface, moved by the scene's kneas -> world map."""
    from kneas_method.data.naf import load_naf, save_naf
    from kneas_method.data.rtk_geometry import WORLD_AFFINE_META

    world = np.array([[0.0, 1, 0, 5], [0, 0, 1, -7], [1, 0, 0, 11], [0, 0, 0, 1]])  # a cyclic axis permutation + shift
    scene = load_naf(files["scene"])
    scene.meta[WORLD_AFFINE_META] = world.tolist()
    scanned = tmp_path / "scanned.pickle"
    save_naf(scene, scanned)
    run = write_run(tmp_path / "r", "k-neas", scanned, num_materials=2)
    assert _cli(["mesh", str(files["kneas"]), "-o", str(tmp_path / "plain"), "--resolution", "24"]) == 0
    assert _cli(["mesh", str(run), "-o", str(tmp_path / "world"), "--resolution", "24"]) == 0
    plain = np.asarray(o3d.io.read_triangle_mesh(str(tmp_path / "plain" / "material-1.ply")).vertices)
    moved = np.asarray(o3d.io.read_triangle_mesh(str(tmp_path / "world" / "material-1.ply")).vertices)
    assert len(plain) == len(moved) > 0
    np.testing.assert_allclose(moved, plain @ world[:3, :3].T + world[:3, 3], atol=1e-3)
    info = json.loads((tmp_path / "world" / "meshes.json").read_text())
    assert any("scanner's world" in n for n in info["notes"])


@pytest.mark.parametrize("fmt", ["obj", "stl", "glb"])
def test_mesh_formats(files, tmp_path, fmt):
    out = tmp_path / fmt
    assert _cli(["mesh", str(files["kneas"]), "-o", str(out), "--resolution", "24", "--format", fmt]) == 0
    info = json.loads((out / "meshes.json").read_text())
    for m in info["meshes"]:
        assert m["path"].endswith("." + fmt)
        assert len(o3d.io.read_triangle_mesh(m["path"]).triangles) > 0


def test_mesh_naf_thresholds_and_says_so(files, tmp_path, capsys):
    run_dir = write_run(files["root"] / "naf", "naf", files["scene"])
    out = tmp_path / "naf"
    run = load_run(run_dir)
    from kneas_method.evaluation.surfaces import query_grid

    mu = query_grid(run.model, run.scene.geometry, keys=("mu",))["mu"]
    level = float(np.quantile(mu, 0.7))
    assert _cli(["mesh", str(run_dir), "-o", str(out), "--resolution", "24", "--threshold", str(level)]) == 0
    text = capsys.readouterr().out
    assert "no signed distance field: thresholded the attenuation" in text
    info = json.loads((out / "meshes.json").read_text())
    assert info["kind"] == "attenuation" and info["thresholds_data_units"] == [pytest.approx(level)]
    assert info["meshes"][0]["triangles"] > 0
    # default: Otsu threshold
    assert _cli(["mesh", str(run_dir), "-o", str(tmp_path / "naf2"), "--resolution", "24"]) == 0
    assert "Otsu" in capsys.readouterr().out
    # a level the attenuation never reaches: no file, the range named, and a failing exit code
    assert _cli(["mesh", str(run_dir), "-o", str(tmp_path / "naf3"), "--resolution", "24", "--threshold", str(10 * float(mu.max()) + 1)]) == 2
    out, err = capsys.readouterr()
    assert "the attenuation spans" in out and "no mesh was written" in err and "--threshold" in err, (out, err)
    assert not list((tmp_path / "naf3").glob("*.ply"))


def test_mesh_threshold_on_a_surface_run_is_said_unused(files, tmp_path, capsys):
    assert _cli(["mesh", str(files["kneas"]), "-o", str(tmp_path / "m"), "--resolution", "24", "--threshold", "0.3"]) == 0
    assert "--threshold (for methods without them" in " ".join(capsys.readouterr().out.split())


def test_mesh_user_errors(files, tmp_path, capsys):
    assert _cli(["mesh", str(tmp_path / "missing")]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert _cli(["mesh", str(files["kneas"]), "--resolution", "1", "-o", str(tmp_path / "x")]) == 2
    assert "--resolution" in capsys.readouterr().err


def test_missing_open3d_is_one_line(monkeypatch):
    import importlib.util

    from kneas_method.export import mesh as mesh_mod

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "open3d" else real(name, *a))
    with pytest.raises(KneasError, match=r"pip install 'kneas\[mesh\]'"):
        mesh_mod.import_open3d()


def test_open3d_that_cannot_load_names_the_real_cause(monkeypatch):
    """open3d installed, but its import fails on libusb with no libusb to load: the error says so
    (not "open3d is not installed") and names the pip fix."""
    import builtins

    from kneas_method.export import mesh as mesh_mod

    real = builtins.__import__

    def fake(name, *a, **kw):
        if name == "open3d":
            raise ImportError("libusb-1.0.so.0: cannot open shared object file: No such file or directory")
        return real(name, *a, **kw)

    monkeypatch.setattr(builtins, "__import__", fake)
    monkeypatch.setattr(mesh_mod, "load_libusb", lambda: None)
    with pytest.raises(KneasError) as exc:
        mesh_mod.import_open3d()
    msg = str(exc.value)
    assert "installed but cannot load" in msg and "libusb-1.0.so.0" in msg and "pip install libusb-package" in msg
    assert "\n" not in msg


def test_libusb_comes_from_pypi_when_the_system_has_none(monkeypatch):
    """The loading path open3d needs on a machine without the system library: libusb-package's copy."""
    import ctypes

    from kneas_method.export import mesh as mesh_mod

    real = ctypes.CDLL
    loaded = []

    def cdll(name, *a, **kw):
        if name == mesh_mod.LIBUSB_SONAME:  # no system libusb
            raise OSError(f"{name}: cannot open shared object file")
        loaded.append(name)
        return real(name, *a, **kw)

    monkeypatch.setattr(ctypes, "CDLL", cdll)
    where = mesh_mod.load_libusb()
    assert where is not None and where != "system" and where.endswith(".so") and loaded == [where]


# ------------------------------------------------------------------- volumes
def test_volume_export_nifti_affine(files, tmp_path):
    out = tmp_path / "vol"
    assert _cli(["volume", str(files["kneas"]), "-o", str(out)]) == 0
    run = load_run(files["kneas"])
    g = run.scene.geometry
    img = nib.load(str(out / "attenuation.nii.gz"))
    lab = nib.load(str(out / "labels.nii.gz"))
    assert img.shape == tuple(g.n_voxel) and lab.shape == tuple(g.n_voxel)
    assert np.allclose(img.header.get_zooms()[:3], np.array(g.d_voxel) * g.mm_per_unit)
    assert img.header.get_xyzt_units()[0] == "mm"
    centres_mm = g.voxel_centres(dtype=torch.float64).numpy() * g.mm_per_unit
    for aff in (img.affine, img.get_qform(), lab.affine):
        for idx in [(0, 0, 0), (3, 9, 14), (15, 15, 15)]:
            assert np.allclose(aff @ np.array([*idx, 1.0]), [*centres_mm[idx], 1.0], atol=1e-4)
    data = np.asarray(img.dataobj)
    assert np.array_equal(data, np.load(out / "attenuation.npy"))
    labels = np.asarray(lab.dataobj)
    assert labels.dtype == np.uint8 and set(np.unique(labels)) <= {0, 1, 2}
    assert np.array_equal(labels, np.load(out / "labels.npy"))
    info = json.loads((out / "volume.json").read_text())
    assert np.allclose(info["voxel_mm"], np.array(g.d_voxel) * g.mm_per_unit)
    # the volume is the model's mu at the voxel centres (data units)
    pts = g.voxel_centres()[2, 4, 6][None]
    assert data[2, 4, 6] == pytest.approx(float(run.model.query(pts)["mu"][0].detach()), abs=1e-5)


def test_volume_export_without_nibabel_writes_npy_and_says_how(files, tmp_path, monkeypatch, capsys):
    import sys

    from kneas_method.export.volume import export_volume

    monkeypatch.setitem(sys.modules, "nibabel", None)  # import nibabel now raises ImportError
    out = tmp_path / "vol"
    assert _cli(["volume", str(files["kneas"]), "-o", str(out), "--no-mha"]) == 0
    printed = capsys.readouterr().out
    assert (out / "attenuation.npy").exists() and (out / "labels.npy").exists()
    assert not list(out.glob("*.nii.gz"))
    assert "no NIfTI files" in printed and "pip install -e '.[nifti]'" in printed
    # asked for explicitly, NIfTI without nibabel is a one-line error naming the extra
    with pytest.raises(KneasError, match=r"nibabel.*pip install 'kneas\[nifti\]'"):
        export_volume(load_run(files["kneas"]), tmp_path / "v2", nifti=True, mha=False)


def test_affine_with_origin_offset(files):
    import dataclasses

    run = load_run(files["kneas"])
    g = dataclasses.replace(run.scene.geometry, off_origin=(0.01, -0.02, 0.03), n_voxel=(4, 5, 6))
    aff = volume_affine(g)
    c = g.voxel_centres(dtype=torch.float64).numpy() * g.mm_per_unit
    assert np.allclose(aff @ [3, 4, 5, 1], [*c[3, 4, 5], 1])
    assert np.allclose(aff[:3, 3], c[0, 0, 0])


def test_fdk_volume_and_mesh(files, tmp_path, capsys):
    from kneas_method.data.scenes import resolve_scene

    scene = resolve_scene(str(files["scene"]))
    run_dir = write_fdk_run(files["root"] / "fdk", files["scene"], scene.image)
    assert _cli(["volume", str(run_dir), "-o", str(tmp_path / "v"), "--threshold", "0.15", "--threshold", "0.55"]) == 0
    assert np.array_equal(np.load(tmp_path / "v" / "attenuation.npy"), scene.image)
    labels = np.load(tmp_path / "v" / "labels.npy")
    assert (labels == (scene.image > 0.15).astype(int) + (scene.image > 0.55)).all()
    assert _cli(["mesh", str(run_dir), "-o", str(tmp_path / "m"), "--resolution", "16", "--threshold", "0.15"]) == 0
    assert "thresholded the attenuation" in capsys.readouterr().out
    assert json.loads((tmp_path / "m" / "meshes.json").read_text())["meshes"][0]["triangles"] > 0


# ------------------------------------------------------------------- figures
def test_figures_export(files, capsys):
    assert _cli(["figures", str(files["kneas"]), "--views", "2"]) == 0
    out = files["kneas"] / "export"  # default: inside the run
    names = sorted(p.name for p in out.glob("*.png"))
    assert names == ["labels.png", "projection-000.png", "projection-002.png", "slices.png", "weights.png"]
    assert all((out / n).stat().st_size > 1000 for n in names)


def test_unfinished_checkpoints_are_named(files):
    from kneas_method.engine.loading import unfinished_notes

    config = load_run(files["kneas"]).config
    run_dir = files["kneas"]
    assert unfinished_notes({"step": 7}, config, run_dir) == []  # written outside kneas-train
    mid = {"step": 700, "extra": {"stage": "model", "complete": False, "total_steps": 2000}}
    (note,) = unfinished_notes(mid, config, run_dir)
    assert "step 700 of 2000" in note and f"kneas-train --resume {run_dir}" in note
    prior = {"step": 50, "extra": {"stage": "prior", "complete": True, "total_steps": 50}}
    assert "prior model" in unfinished_notes(prior, config, run_dir)[0]
    trained = {"step": 2000, "extra": {"stage": "model", "complete": True, "total_steps": 2000, "correction": None}}
    from kneas_method.stages.correction import CorrectionConfig

    with_passes = dataclasses.replace(config, stages=dataclasses.replace(config.stages, correction=CorrectionConfig(passes=12)),
                                      skip_stages=())
    assert "12 correction passes" in unfinished_notes(trained, with_passes, run_dir)[0]
    done = {"step": 2000, "extra": {"stage": "model", "complete": True, "total_steps": 2000, "stages": {"correction": {"passes": []}}}}
    assert unfinished_notes(done, with_passes, run_dir) == []
    older = {"step": 2000, "extra": {"stage": "model", "complete": True, "total_steps": 2000, "correction": []}}  # before the stages
    assert unfinished_notes(older, with_passes, run_dir) == []


def test_the_exported_label_volume_is_the_one_evaluation_scores():
    """kneas-export volume's labels: the selector's, with partial-volume shells relabelled."""
    from kneas_method.evaluation.surfaces import labels_from_weights, query_grid, voxel_labels
    from kneas_method.export.volume import label_volume

    from conftest import sphere_scene
    from test_surfaces import ShellModel

    scene = sphere_scene()
    q = query_grid(ShellModel(scene.geometry), scene.geometry, keys=("mu", "weights", "mu_materials"))
    labels = label_volume(q)
    raw = labels_from_weights(q["weights"])
    assert (labels == voxel_labels(q)[0]).all()
    assert (labels != raw).sum() == sum(voxel_labels(q)[2].values()) > 0
    assert (labels[raw != 2] == raw[raw != 2]).all()  # only the shell material's cells move
