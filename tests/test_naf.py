"""NAF pickle IO: round trip, validation, and refusal of code-running pickles."""

import os
import pickle

import numpy as np
import pytest

from kneas_method.data.naf import load_naf, safe_load_pickle, save_naf
from kneas_method.data.scene import Scene
from kneas_method.errors import SceneError


def naf_dict(n_train=3, n_val=2, n_u=12, n_v=10, n_vox=(8, 9, 7), image=True):
    rng = np.random.default_rng(0)
    d = {
        "DSD": 1500.0, "DSO": 1000.0,
        "nDetector": np.array([n_u, n_v]), "dDetector": np.array([3.3, 3.1]),
        "nVoxel": np.array(n_vox), "dVoxel": np.array([2.0, 2.1, 1.9]),
        "offOrigin": np.array([0.5, 0.0, -0.25]), "offDetector": np.array([0.1, 0.0]),
        "accuracy": 0.5, "mode": "cone", "filter": None, "totalAngle": 180.0, "startAngle": 0.0,
        "numTrain": n_train, "numVal": n_val, "convert": False, "rescale_slope": 1.0, "rescale_intercept": 0.0,
        "normalize": True, "noise": 0, "randomAngle": True,
        "train": {"angles": np.linspace(0, np.pi, n_train, endpoint=False),
                  "projections": rng.random((n_train, n_v, n_u)).astype(np.float32)},
        "val": {"angles": np.sort(rng.random(n_val) * np.pi), "projections": rng.random((n_val, n_v, n_u)).astype(np.float32)},
    }
    if image:
        d["image"] = rng.random(n_vox).astype(np.float32)
    return d


def write(path, obj, protocol=4):
    path.write_bytes(pickle.dumps(obj, protocol=protocol))
    return path


def assert_same_scene(a: Scene, b: Scene):
    assert a.geometry == b.geometry
    for va, vb in ((a.train, b.train), (a.val, b.val)):
        np.testing.assert_array_equal(va.angles, vb.angles)
        np.testing.assert_array_equal(va.projections, vb.projections)
        assert va.projections.dtype == vb.projections.dtype == np.float32
    if a.image is None:
        assert b.image is None
    else:
        np.testing.assert_array_equal(a.image, b.image)
    assert set(a.meta) == set(b.meta)


@pytest.mark.parametrize("protocol", [2, 3, 4, 5])
def test_load_plain_numpy_data_all_protocols(tmp_path, protocol):
    d = naf_dict()
    d["extras"] = {
        "f64": np.arange(3, dtype=np.float64), "i32": np.arange(4, dtype=np.int32), "b": np.array([True, False]),
        "u8": np.zeros((2, 2), np.uint8), "scalar": np.float32(2.5), "iscalar": np.int64(7), "bscalar": np.bool_(True),
        "dtype": np.dtype("float32"), "list": [1, 2.0, "x", None], "tuple": (1, b"bytes"), "fortran": np.asfortranarray(np.ones((3, 2))),
    }
    scene = load_naf(write(tmp_path / "s.pickle", d, protocol))
    ex = scene.meta["extras"]
    assert ex["scalar"] == np.float32(2.5) and ex["iscalar"] == 7 and ex["bscalar"]
    assert ex["i32"].dtype == np.int32 and ex["b"].dtype == np.bool_ and ex["dtype"] == np.float32
    assert ex["tuple"] == (1, b"bytes") and ex["list"] == [1, 2.0, "x", None]
    np.testing.assert_array_equal(ex["fortran"], np.ones((3, 2)))
    np.testing.assert_array_equal(scene.train.projections, d["train"]["projections"])
    np.testing.assert_array_equal(scene.image, d["image"])
    assert scene.name == "s" and "s.pickle" in scene.source


def test_geometry_from_mm_keys(tmp_path):
    scene = load_naf(write(tmp_path / "s.pickle", naf_dict()))
    g = scene.geometry
    assert g.n_detector == (12, 10) and g.n_voxel == (8, 9, 7) and g.mode == "cone"
    back = g.to_mm()
    np.testing.assert_allclose(back["dDetector"], [3.3, 3.1])
    np.testing.assert_allclose(back["offOrigin"], [0.5, 0.0, -0.25], atol=1e-12)
    assert back["DSO"] == pytest.approx(1000.0)


def test_round_trip_identical(tmp_path):
    original = load_naf(write(tmp_path / "a.pickle", naf_dict()))
    save_naf(original, tmp_path / "b.pickle")
    again = load_naf(tmp_path / "b.pickle")
    assert_same_scene(original, again)
    for k, v in original.meta.items():
        if not isinstance(v, dict):
            assert again.meta[k] == v
    # a third generation is byte-identical to the second
    save_naf(again, tmp_path / "c.pickle")
    assert (tmp_path / "b.pickle").read_bytes() == (tmp_path / "c.pickle").read_bytes()
    # no temp files left behind
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.pickle", "b.pickle", "c.pickle"]


def test_round_trip_without_image_and_after_subsampling(tmp_path):
    scene = load_naf(write(tmp_path / "a.pickle", naf_dict(n_train=6, image=False)))
    assert scene.image is None
    sub = scene.subsample_views(3)
    save_naf(sub, tmp_path / "sub.pickle")
    back = load_naf(tmp_path / "sub.pickle")
    assert_same_scene(sub, back)
    assert back.meta["numTrain"] == 3


def test_geometry_edited_scene_saves_its_new_geometry(tmp_path):
    scene = load_naf(write(tmp_path / "a.pickle", naf_dict()))
    scene.geometry = scene.geometry.with_detector((6, 5))
    scene.train.projections = scene.train.projections[:, ::2, ::2].copy()
    scene.val.projections = scene.val.projections[:, ::2, ::2].copy()
    save_naf(scene, tmp_path / "b.pickle")
    back = load_naf(tmp_path / "b.pickle")
    assert back.geometry.n_detector == (6, 5)
    np.testing.assert_allclose(back.geometry.d_detector, scene.geometry.d_detector, rtol=1e-12)


def _mutate(fn):
    d = naf_dict()
    fn(d)
    return d


BAD = [
    ("missing DSD", lambda d: d.pop("DSD"), r"s\.pickle: key 'DSD' is missing"),
    ("missing train", lambda d: d.pop("train"), "key 'train' is missing"),
    ("missing projections", lambda d: d["val"].pop("projections"), r"val\.projections is missing"),
    ("wrong projection shape", lambda d: d["train"].update(projections=np.zeros((3, 12, 10), np.float32)),
     r"train\.projections has shape \(3, 12, 10\) but nDetector is \(12, 10\); expected \(3, 10, 12\)"),
    ("2-D projections", lambda d: d["train"].update(projections=np.zeros((10, 12), np.float32)), r"train\.projections has shape \(10, 12\)"),
    ("angle count", lambda d: d["train"].update(angles=np.zeros(5)), "train has 5 angles but 3 projections"),
    ("nan projection", lambda d: d["val"]["projections"].__setitem__((0, 0, 0), np.nan), r"val\.projections contains 1 NaN/inf"),
    ("inf image", lambda d: d["image"].__setitem__((0, 0, 0), np.inf), "image contains NaN or inf"),
    ("nan angle", lambda d: d["train"]["angles"].__setitem__(1, np.nan), r"train\.angles contains NaN"),
    ("log-intensities", lambda d: d["train"].update(projections=-d["train"]["projections"]), r"train\.projections have median -0\.\d+, far below 0"),
    ("wildly negative", lambda d: d["val"]["projections"].__setitem__((0, slice(0, 2)), -3.0), r"val\.projections are wildly negative"),
    ("all-zero projections", lambda d: d["train"].update(projections=np.zeros((3, 10, 12), np.float32)), r"train\.projections are all zero"),
    ("image shape", lambda d: d.update(image=np.zeros((8, 9, 8), np.float32)), r"image has shape \(8, 9, 8\) but nVoxel is \(8, 9, 7\)"),
    ("unknown mode", lambda d: d.update(mode="fan"), "mode is 'fan'; it must be 'cone' or 'parallel'"),
    ("zero DSO", lambda d: d.update(DSO=0.0), "DSO is 0.0; it must be one finite positive number"),
    ("negative DSD", lambda d: d.update(DSD=-5), "DSD is -5"),
    ("DSD < DSO", lambda d: d.update(DSD=500.0), r"DSD \(500 mm\) must be larger than DSO"),
    ("zero voxel", lambda d: d.update(dVoxel=np.array([2.0, 0.0, 2.0])), "dVoxel is .*finite positive"),
    ("bad nVoxel count", lambda d: d.update(nVoxel=np.array([8, 9])), "nVoxel has 2 entries; it must have 3"),
    ("fractional nDetector", lambda d: d.update(nDetector=np.array([12.5, 10])), "nDetector .* whole number"),
    ("negative detector pixel", lambda d: d.update(dDetector=[-1.0, 1.0]), "dDetector"),
    ("nan offset", lambda d: d.update(offOrigin=np.array([np.nan, 0, 0])), "offOrigin"),
    ("train not dict", lambda d: d.update(train=[1, 2]), "train is a list; it must be a dict"),
    ("string projections", lambda d: d["train"].update(projections=np.array(["a"])), r"train\.projections has dtype"),
    ("empty train", lambda d: d.update(train={"angles": np.zeros(0), "projections": np.zeros((0, 10, 12), np.float32)}), "train has no views"),
]


@pytest.mark.parametrize("case,mutate,message", BAD, ids=[b[0] for b in BAD])
def test_validation_errors_name_the_key(tmp_path, case, mutate, message):
    path = write(tmp_path / "s.pickle", _mutate(mutate))
    with pytest.raises(SceneError, match=message) as info:
        load_naf(path)
    assert "\n" not in str(info.value)


def test_scene_without_ground_truth_or_held_out_views(tmp_path):
    """Measured scans: no image, val with 0 views (or no val at all); they load, save and load back."""
    d = naf_dict(image=False)
    d["val"] = {"angles": np.zeros(0), "projections": np.zeros((0, 10, 12), np.float32)}
    scene = load_naf(write(tmp_path / "s.pickle", d))
    assert scene.image is None and len(scene.val) == 0 and scene.val.projections.shape == (0, 10, 12)
    assert len(scene.subsample_views(2).train) == 2 and len(scene.subsample_views(2).val) == 0
    back = load_naf(save_naf(scene, tmp_path / "b.pickle"))
    assert_same_scene(scene, back)
    assert back.meta["numVal"] == 0
    d.pop("val")
    d["val"] = {"angles": [], "projections": []}  # plain empty lists
    assert len(load_naf(write(tmp_path / "l.pickle", d)).val) == 0
    d.pop("val")
    assert len(load_naf(write(tmp_path / "n.pickle", d)).val) == 0


def test_small_negative_line_integrals_are_kept(tmp_path):
    """Noise in air gives slightly negative line integrals (as TIGRE's noise does); they load unchanged."""
    d = naf_dict()
    noise = np.random.default_rng(1).normal(0, 0.01, d["train"]["projections"].shape).astype(np.float32)
    d["train"]["projections"][:, :4] = noise[:, :4]  # a band of air with noise
    scene = load_naf(write(tmp_path / "s.pickle", d))
    assert scene.train.projections.min() < 0
    np.testing.assert_array_equal(scene.train.projections, d["train"]["projections"])


def test_non_dict_and_garbage_files(tmp_path):
    with pytest.raises(SceneError, match="holds a list, not a dict"):
        load_naf(write(tmp_path / "l.pickle", [1, 2, 3]))
    (tmp_path / "g.pickle").write_bytes(b"this is not a pickle at all")
    with pytest.raises(SceneError, match="g.pickle is not a readable scene pickle"):
        load_naf(tmp_path / "g.pickle")
    (tmp_path / "t.pickle").write_bytes(pickle.dumps(naf_dict())[:200])
    with pytest.raises(SceneError, match="not a readable scene pickle"):
        load_naf(tmp_path / "t.pickle")
    with pytest.raises(SceneError, match="no such file"):
        load_naf(tmp_path / "missing.pickle")
    (tmp_path / "proj.mha").write_text("ObjectType = Image\nNDims = 3\n")  # projections given as --scene
    with pytest.raises(SceneError, match=r"proj.mha is not a scene pickle but an image or geometry file; .*kneas-data import"):
        load_naf(tmp_path / "proj.mha")
    with pytest.raises(SceneError, match="is a directory"):
        load_naf(tmp_path)


# ----------------------------------------------------------------------------- malicious pickles
class _Exploit:
    def __init__(self, func, arg):
        self.func, self.arg = func, arg

    def __reduce__(self):
        return (self.func, (self.arg,))


class _Innocent:
    """A harmless user class: still refused (unpickling classes can run code)."""

    def __init__(self):
        self.x = 1


def _payloads(marker):
    import builtins
    import subprocess

    cmd = f"touch {marker}"
    return {
        "os.system": _Exploit(os.system, cmd),
        "eval": _Exploit(builtins.eval, f"open({str(marker)!r}, 'w').write('x')"),
        "exec": _Exploit(builtins.exec, f"open({str(marker)!r}, 'w').write('x')"),
        "subprocess": _Exploit(subprocess.Popen, ["touch", str(marker)]),
    }


@pytest.mark.parametrize("protocol", [0, 2, 4, 5])
@pytest.mark.parametrize("kind", ["os.system", "eval", "exec", "subprocess"])
def test_malicious_pickles_run_nothing(tmp_path, protocol, kind):
    marker = tmp_path / "pwned"
    payload = _payloads(marker)[kind]
    d = naf_dict()
    d["image"] = payload  # hidden deep inside an otherwise valid scene
    path = write(tmp_path / "evil.pickle", d, protocol)
    with pytest.raises(SceneError) as info:
        load_naf(path)
    msg = str(info.value)
    assert msg.startswith("evil.pickle is not a plain-data scene pickle: it asks for ")
    assert "refuses to load because unpickling it could run code" in msg and "\n" not in msg
    assert not marker.exists()
    # also at top level
    path2 = write(tmp_path / "evil2.pickle", payload, protocol)
    with pytest.raises(SceneError, match="not a plain-data scene pickle"):
        load_naf(path2)
    assert not marker.exists()


def test_refusal_names_the_global(tmp_path):
    path = write(tmp_path / "evil.pickle", {"x": _Exploit(os.system, "true")}, 2)
    with pytest.raises(SceneError, match=r"asks for (posix|nt|os)\.system"):
        safe_load_pickle(path)
    with pytest.raises(SceneError, match=r"asks for test_naf\._Innocent|asks for tests\.test_naf\._Innocent"):
        safe_load_pickle(write(tmp_path / "cls.pickle", {"x": _Innocent()}, 4))
    # _codecs.encode is allowed only for latin-1 text (protocol-2 bytes)
    import _codecs

    with pytest.raises(SceneError):
        safe_load_pickle(write(tmp_path / "codec.pickle", _Exploit(_codecs.encode, 123), 2))


def test_hand_crafted_protocol0_global(tmp_path):
    marker = tmp_path / "pwned"
    raw = f"cos\nsystem\n(S'touch {marker}'\ntR.".encode()
    (tmp_path / "raw.pickle").write_bytes(raw)
    with pytest.raises(SceneError, match=r"asks for os\.system"):
        load_naf(tmp_path / "raw.pickle")
    assert not marker.exists()


@pytest.mark.parametrize("start, kind", [(b"\x89PNG\r\n\x1a\n", "PNG image"), (b"\x93NUMPY\x01\x00", "NumPy .npy"),
                                         (b"\x1f\x8b\x08\x00", "gzip")])
def test_another_kind_of_file_named_pickle_is_named(tmp_path, start, kind):
    (tmp_path / "scan.pickle").write_bytes(start + bytes(64))
    with pytest.raises(SceneError, match=rf"scan.pickle is a {kind}.* file, not a scene pickle; .*kneas-data import"):
        load_naf(tmp_path / "scan.pickle")
