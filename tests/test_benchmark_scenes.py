"""The benchmark scripts' ``--scenes`` entries (``benchmarks/heldout.py``'s ``scene_from_spec``):
a mistake is one line, as in the commands, not a traceback."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from heldout import scene_from_spec  # noqa: E402


def test_unknown_scenes_are_one_line(tmp_path):
    with pytest.raises(SystemExit, match=r"^error: --scenes 'nosuch' is neither an existing file nor a built-in scene"):
        scene_from_spec("nosuch")
    with pytest.raises(SystemExit, match=r"^error: .*nosuch"):
        scene_from_spec("heldout:nosuch")
    bad = tmp_path / "bad.pickle"
    bad.write_bytes(b"junk")
    with pytest.raises(SystemExit, match=r"^error: .*bad\.pickle"):
        scene_from_spec(str(bad))
