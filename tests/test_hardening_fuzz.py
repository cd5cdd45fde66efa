"""Fuzzing the loaders: scene pickles and run configurations never crash, never run code,
and always end in a valid scene or a one-line SceneError / ConfigError (exit status 2)."""

import copy
import dataclasses
import json
import pickle
import pickletools

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from kneas_method import registry
from kneas_method.cli import data as data_cli
from kneas_method.cli import train as train_cli
from kneas_method.config import to_dict
from kneas_method.data.naf import load_naf
from kneas_method.data.scene import Scene
from kneas_method.data.simulate import SimulationConfig, simulate_phantom
from kneas_method.data.naf import scene_to_dict
from kneas_method.errors import SceneError

# derandomize: the same examples on every run of one hypothesis release; print_blob: a failure prints the
# @reproduce_failure line that replays it exactly, and the config tests also print the file they ran
FUZZ = settings(max_examples=150, deadline=None, derandomize=True, print_blob=True, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                                         HealthCheck.too_slow])
MARKER = "KNEAS_FUZZ_PWNED"


@pytest.fixture(scope="module")
def base_dict():
    scene = simulate_phantom("foot", SimulationConfig(n_voxel=8, voxel_mm=30.0, n_detector=8, n_train=2, n_val=2))
    return scene_to_dict(scene)


@pytest.fixture(scope="module")
def fuzz_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("fuzz")


def load_outcome(path):
    """load_naf on ``path``: a Scene or a SceneError; anything else fails the test (a crash)."""
    try:
        scene = load_naf(path)
    except SceneError as exc:
        msg = str(exc)
        assert msg and "\n" not in msg and "Traceback" not in msg, msg
        return exc
    assert isinstance(scene, Scene)
    # loaded line integrals are finite and not clearly wrong (small negative noise values are allowed)
    for views in (scene.train, scene.val):
        assert np.all(np.isfinite(views.projections))
        if views.projections.size:
            assert np.any(views.projections) and float(np.median(views.projections)) >= -0.1
    assert scene.train.projections.shape[1:] == tuple(int(v) for v in scene.geometry.n_detector[::-1])
    return scene


def assert_no_marker(folder):
    assert not list(folder.glob(MARKER + "*")), "a fuzzed input ran code"


# ------------------------------------------------------------------ scene dict mutations
ODD_VALUES = st.one_of(
    st.none(), st.booleans(), st.integers(-3, 40), st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=5), st.binary(max_size=5), st.lists(st.integers(-2, 20), max_size=4),
    st.sampled_from([float("nan"), float("inf"), -1.0, 0.0, np.float32(-0.5), np.array([]), np.zeros((2, 2)),
                     np.array(["a", "b"]), np.array([1, None], dtype=object), {"angles": []}, {}, (1, 2, 3),
                     np.full(3, np.nan), np.array([16, 16, 16, 16]), np.complex64(1j), np.array([1e300, 1e300])]),
)
KEYS = ["mode", "DSD", "DSO", "nDetector", "dDetector", "nVoxel", "dVoxel", "offOrigin", "offDetector", "train", "val",
        "image", "labels", "numTrain", "phantom"]
VIEW_EDITS = ["nan", "inf", "negative", "drop_angles", "drop_projections", "transpose", "truncate", "extra_angle",
              "as_list", "int_dtype", "string_dtype", "empty", "2d"]


def _edit_views(views: dict, edit: str) -> dict:
    v = {"angles": np.array(views["angles"]), "projections": np.array(views["projections"])}
    p = v["projections"]
    if edit in ("nan", "inf", "negative"):
        p = v["projections"] = p.astype(np.float32)
        if p.size == 0:
            return v
    if edit == "nan":
        p.flat[0] = np.nan
    elif edit == "inf":
        p.flat[-1] = np.inf
    elif edit == "negative":
        p.flat[min(3, p.size - 1)] = -1.0
    elif edit == "drop_angles":
        del v["angles"]
    elif edit == "drop_projections":
        del v["projections"]
    elif edit == "transpose":
        v["projections"] = np.ascontiguousarray(p.transpose(0, 2, 1)[:, :-1])
    elif edit == "truncate":
        v["projections"] = p[:-1]
    elif edit == "extra_angle":
        v["angles"] = np.append(v["angles"], 0.3)
    elif edit == "as_list":
        v["projections"] = p.tolist()
    elif edit == "int_dtype":
        v["projections"] = (p * 10).astype(np.int16)
    elif edit == "string_dtype":
        v["projections"] = p.astype(str)
    elif edit == "empty":
        v = {"angles": np.zeros(0), "projections": np.zeros((0,) + p.shape[1:], np.float32)}
    elif edit == "2d":
        v = {"angles": v["angles"][:1], "projections": p[0] if len(p) else np.zeros(np.shape(p)[1:], np.float32)}
    return v


@FUZZ
@given(data=st.data())
def test_mutated_scene_dicts_load_or_fail_cleanly(base_dict, fuzz_dir, data):
    d = copy.deepcopy(base_dict)
    for _ in range(data.draw(st.integers(1, 3), label="n_mutations")):
        kind = data.draw(st.sampled_from(["drop", "set", "views", "image"]), label="kind")
        key = data.draw(st.sampled_from(KEYS), label="key")
        if kind == "drop":
            d.pop(key, None)
        elif kind == "set":
            d[key] = data.draw(ODD_VALUES, label="value")
        elif kind == "views":
            part = data.draw(st.sampled_from(["train", "val"]), label="part")
            if isinstance(d.get(part), dict) and "angles" in d[part] and "projections" in d[part]:
                d[part] = _edit_views(d[part], data.draw(st.sampled_from(VIEW_EDITS), label="edit"))
        elif kind == "image" and isinstance(d.get("image"), np.ndarray) and d["image"].dtype.kind == "f":
            img = d["image"]
            d["image"] = data.draw(st.sampled_from([img[:-1], img * np.nan, img.astype(str), img.astype(np.float64) * -1,
                                                   None, np.where(img > 0, np.inf, img)]), label="image")
    path = fuzz_dir / "mutated.pickle"
    path.write_bytes(pickle.dumps(d, protocol=data.draw(st.integers(2, 5), label="protocol")))
    load_outcome(path)


# ------------------------------------------------------------------ byte-level damage
@pytest.fixture(scope="module")
def valid_bytes(base_dict):
    return pickle.dumps(base_dict, protocol=4)


@FUZZ
@given(data=st.data())
def test_bit_flipped_and_truncated_pickles(valid_bytes, fuzz_dir, data):
    raw = bytearray(valid_bytes)
    ops = data.draw(st.lists(st.tuples(st.sampled_from(["flip", "set", "cut", "insert"]), st.integers(0, len(raw) - 1),
                                       st.integers(0, 255)), min_size=1, max_size=6), label="ops")
    for op, pos, byte in ops:
        pos = min(pos, max(len(raw) - 1, 0))
        if not raw:
            break
        if op == "flip":
            raw[pos] ^= 1 << (byte % 8)
        elif op == "set":
            raw[pos] = byte
        elif op == "cut":
            del raw[pos:]
        else:
            raw[pos:pos] = bytes([byte])
    path = fuzz_dir / "flipped.pickle"
    path.write_bytes(bytes(raw))
    load_outcome(path)


@FUZZ
@given(blob=st.binary(max_size=200))
def test_random_bytes(fuzz_dir, blob):
    path = fuzz_dir / "random.pickle"
    path.write_bytes(blob)
    assert isinstance(load_outcome(path), SceneError)


# ------------------------------------------------------------------ hand-crafted opcode streams
def _str(s: str) -> bytes:
    b = s.encode()
    return b"\x8c" + bytes([len(b)]) + b  # SHORT_BINUNICODE


GLOBALS = [("os", "system"), ("builtins", "eval"), ("builtins", "exec"), ("subprocess", "Popen"),
           ("posix", "system"), ("builtins", "getattr"), ("numpy", "load"), ("numpy.lib.npyio", "load"),
           ("numpy.core.multiarray", "_reconstruct"), ("numpy", "ndarray"), ("numpy", "dtype"), ("_codecs", "encode"),
           ("numpy.testing", "runstring"), ("torch", "load"), ("builtins", "__import__"), ("copyreg", "_reconstructor")]
ATOMS = [b"N", b"\x88", b"\x89", b"K\x05", b"J\xff\xff\xff\xff", b"G" + b"\x7f\xf8" + b"\x00" * 6, b"}", b"]", b")",
         b"(", b"t", b"u", b"a", b"e", b"s", b"R", b"\x81", b"b", b"\x85", b"\x86", b"\x87", b"0", b"2", b"\x94",
         b"h\x00", b"q\x00", b"C\x03abc", b"\x8c\x04cone", b"\x8c\x03DSD", b"\x8c\x05train", b"Q", b"\x92", b"\x93", b"i"]


@FUZZ
@given(data=st.data())
def test_hand_crafted_opcode_streams(fuzz_dir, monkeypatch, data):
    monkeypatch.chdir(fuzz_dir)
    parts = [b"\x80\x04"]
    for _ in range(data.draw(st.integers(1, 25), label="length")):
        if data.draw(st.booleans(), label="global?"):
            mod, name = data.draw(st.sampled_from(GLOBALS), label="global")
            if data.draw(st.booleans(), label="stack_global?"):
                parts += [_str(mod), _str(name), b"\x93"]  # STACK_GLOBAL
            else:
                parts.append(b"c" + mod.encode() + b"\n" + name.encode() + b"\n")  # GLOBAL
            if data.draw(st.booleans(), label="call?"):
                parts += [_str(f"touch {MARKER}"), b"\x85", b"R"]  # (arg,) REDUCE
        else:
            parts.append(data.draw(st.sampled_from(ATOMS), label="atom"))
    if data.draw(st.booleans(), label="stop?"):
        parts.append(b".")
    path = fuzz_dir / "opcodes.pickle"
    path.write_bytes(b"".join(parts))
    load_outcome(path)
    assert_no_marker(fuzz_dir)


class _Evil:
    def __reduce__(self):
        import os

        return (os.system, (f"touch {MARKER}-reduce",))


@pytest.mark.parametrize("protocol", [0, 2, 4, 5])
def test_payload_inside_valid_scene_refused(base_dict, tmp_path, monkeypatch, protocol):
    monkeypatch.chdir(tmp_path)
    d = dict(base_dict, accuracy=_Evil())
    path = tmp_path / "evil.pickle"
    path.write_bytes(pickle.dumps(d, protocol=protocol))
    assert any(op.name in ("GLOBAL", "STACK_GLOBAL") for op, _, _ in pickletools.genops(path.read_bytes()))
    with pytest.raises(SceneError, match="posix.system|os.system|refuses"):
        load_naf(path)
    assert_no_marker(tmp_path)


# ------------------------------------------------------------------ the CLI: kneas-data inspect
def inspect_cli(path, capsys):
    with pytest.raises(SystemExit) as exc:
        data_cli.main(["inspect", str(path)])
    out = capsys.readouterr()
    return exc.value.code, out.out, out.err


@settings(max_examples=40, deadline=None, derandomize=True, print_blob=True, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_kneas_data_inspect_on_damaged_pickles(valid_bytes, base_dict, fuzz_dir, capsys, data):
    if data.draw(st.booleans(), label="bytes?"):
        raw = bytearray(valid_bytes)
        for pos in data.draw(st.lists(st.integers(0, len(raw) - 1), min_size=1, max_size=4), label="flips"):
            raw[pos] ^= 0xFF
        blob = bytes(raw)
    else:
        d = copy.deepcopy(base_dict)
        d[data.draw(st.sampled_from(KEYS), label="key")] = data.draw(ODD_VALUES, label="value")
        blob = pickle.dumps(d, protocol=4)
    path = fuzz_dir / "inspect.pickle"
    path.write_bytes(blob)
    code, out, err = inspect_cli(path, capsys)
    assert code in (0, 2), (code, out, err)
    assert "Traceback" not in out + err
    if code == 2:
        assert err.strip().startswith("error:") and len(err.strip().splitlines()) == 1, err


def test_kneas_data_inspect_valid_scene(base_dict, tmp_path, capsys):
    path = tmp_path / "ok.pickle"
    path.write_bytes(pickle.dumps(base_dict, protocol=4))
    code, out, err = inspect_cli(path, capsys)
    assert code == 0, err


# ------------------------------------------------------------------ configuration files
@pytest.fixture(scope="module")
def base_config():
    cfg = dataclasses.replace(registry.load("methods", "k-neas").config, method="k-neas", preset="tiny")
    return to_dict(cfg)


def _leaves(d, prefix=()):
    for k, v in d.items():
        if isinstance(v, dict) and v:
            yield from _leaves(v, prefix + (k,))
        yield prefix + (k,)


JSON_VALUES = st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(-10, 5000), st.floats(-1e6, 1e6, allow_nan=False),
              st.sampled_from([1e308, -1e308, 0.0, -0.0, 2**53, "", "k-neas", "naf", "tiny", "paper", "cpu", "cuda",
                               "fdk", "auto", "hashgrid", "../../etc/passwd"]),
              st.text(max_size=6)),
    lambda inner: st.one_of(st.lists(inner, max_size=3), st.dictionaries(st.text(max_size=6), inner, max_size=3)),
    max_leaves=6,
)


def dry_run_cli(path, capsys):
    with pytest.raises(SystemExit) as exc:
        train_cli.main(["--config", str(path), "--dry-run"])
    out = capsys.readouterr()
    return exc.value.code, out.out, out.err


def check_dry_run(path, capsys):
    """The dry run on ``path`` ends in ``parameters:`` or one line ``error: ...``; a failure shows the
    file's text, so ``kneas-train --config FILE --dry-run`` on it reproduces it."""
    code, out, err = dry_run_cli(path, capsys)
    shown = f"config file that fails:\n{path.read_text()}\n--- output:\n{out}{err}"
    assert code in (0, 2), shown
    assert "Traceback" not in out + err, shown
    if code == 0:
        assert "parameters:" in out, shown
    else:
        line = err.strip()
        assert line.startswith("error:") and len(line.splitlines()) == 1, shown


@settings(max_examples=150, deadline=None, derandomize=True, print_blob=True, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_mutated_config_files_dry_run(base_config, fuzz_dir, capsys, data):
    cfg = copy.deepcopy(base_config)
    if data.draw(st.booleans(), label="naf_field"):  # a field with no surfaces under a K-material method
        cfg["model"]["field"] = "naf"
    leaves = list(_leaves(cfg))
    for _ in range(data.draw(st.integers(1, 3), label="n_mutations")):
        path = data.draw(st.sampled_from(leaves), label="leaf")
        parent = cfg
        for k in path[:-1]:
            parent = parent.get(k) if isinstance(parent, dict) else None
            if not isinstance(parent, dict):
                break
        if not isinstance(parent, dict):
            continue
        action = data.draw(st.sampled_from(["set", "set", "drop", "unknown"]), label="action")
        if action == "set":
            parent[path[-1]] = data.draw(JSON_VALUES, label="value")
        elif action == "drop":
            parent.pop(path[-1], None)
        else:
            parent[data.draw(st.text(min_size=1, max_size=6), label="new_key")] = 1
    text = json.dumps(cfg, allow_nan=data.draw(st.booleans(), label="allow_nan"))
    if data.draw(st.integers(0, 9), label="damage") == 0:
        text = text[: data.draw(st.integers(0, len(text)), label="cut")]
    path = fuzz_dir / "config.json"
    path.write_text(text)
    check_dry_run(path, capsys)


@settings(max_examples=60, deadline=None, derandomize=True, print_blob=True, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(blob=st.one_of(JSON_VALUES.map(json.dumps), st.text(max_size=40), st.binary(max_size=40)))
def test_random_config_files_dry_run(fuzz_dir, capsys, blob):
    path = fuzz_dir / "random.json"
    if isinstance(blob, bytes):
        path.write_bytes(blob)
    else:
        path.write_text(blob)
    code, out, err = dry_run_cli(path, capsys)
    assert code == 2 and err.strip().startswith("error:") and "Traceback" not in out + err, (code, out, err)
