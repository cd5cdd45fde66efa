import json
import shutil
import subprocess

import pytest

from kneas_method import __version__
from kneas_method.engine.code_version import PACKAGE_DIR, code_version, describe

from conftest import run, run_dir_of

needs_git = pytest.mark.skipif(shutil.which("git") is None, reason="git is not installed")


def _git(root, *args):
    return subprocess.run(["git", "-C", str(root), "-c", "user.name=t", "-c", "user.email=t@example.org", *args],
                          capture_output=True, text=True, check=True).stdout.strip()


def _checkout(root):
    """A git checkout with a ``kneas_method`` folder holding one committed file."""
    (root / "kneas_method").mkdir(parents=True)
    (root / "kneas_method" / "a.py").write_text("x = 1\n")
    _git(root, "init", "-q")
    _git(root, "add", ".")
    _git(root, "commit", "-q", "-m", "first")
    return root / "kneas_method"


@needs_git
def test_a_checkout_gives_its_commit_and_whether_the_package_was_edited(tmp_path):
    package = _checkout(tmp_path / "repo")
    head = _git(tmp_path / "repo", "rev-parse", "HEAD")
    assert code_version.__wrapped__(package) == {"kneas": __version__, "commit": head, "modified": False}
    (package.parent / "notes.txt").write_text("untracked, outside the package")
    assert code_version.__wrapped__(package)["modified"] is False
    (package / "a.py").write_text("x = 2\n")
    assert code_version.__wrapped__(package) == {"kneas": __version__, "commit": head, "modified": True}
    assert describe(code_version.__wrapped__(package)) == head[:12] + "+modified"


@needs_git
def test_a_package_inside_another_repository_or_none_has_no_commit(tmp_path):
    outer = _checkout(tmp_path / "outer")  # a repository whose kneas_method sits one level deeper is not kneas's
    nested = outer / "site-packages" / "kneas_method"
    nested.mkdir(parents=True)
    assert code_version.__wrapped__(nested) == {"kneas": __version__}
    plain = tmp_path / "plain" / "kneas_method"
    plain.mkdir(parents=True)
    assert code_version.__wrapped__(plain) == {"kneas": __version__}
    assert describe(code_version.__wrapped__(plain)) == f"kneas {__version__}"


def test_describe_labels():
    assert describe(None) == describe({}) == "not recorded"
    assert describe({"kneas": "0.1.0", "commit": "0123456789abcdef0123"}) == "0123456789ab"
    assert describe({"kneas": "0.1.0", "commit": "0123456789abcdef0123", "modified": True}) == "0123456789ab+modified"


def test_this_install_is_described():
    code = code_version()
    assert code["kneas"] == __version__ and code == code_version(PACKAGE_DIR)
    assert set(code) <= {"kneas", "commit", "modified"}


def test_a_run_keeps_the_code_it_started_with(tiny_scene, tmp_path, capsys, monkeypatch):
    """The record is taken as the run starts: a checkout that moves on while the run trains (a commit
    between two benchmark cells) does not relabel the run in its metrics.json."""
    from kneas_method.engine import code_version as cv
    from kneas_method.engine import pipeline

    head = {"commit": "a" * 40}
    answers = {"rev-parse --show-toplevel": lambda: str(PACKAGE_DIR.parent), "rev-parse HEAD": lambda: head["commit"],
               "status --porcelain --untracked-files=no -- .": lambda: ""}
    monkeypatch.setattr(cv, "_git", lambda root, *args: answers[" ".join(args)]())
    fitting_scene = pipeline.fitting_scene

    def moves_on(scene, **kw):  # the checkout moves on once the run has started
        head["commit"] = "b" * 40
        return fitting_scene(scene, **kw)

    monkeypatch.setattr(pipeline, "fitting_scene", moves_on)
    code_version.cache_clear()
    try:
        code, out, err = run(["fdk", "--scene", str(tiny_scene), "--output-dir", str(tmp_path)], capsys)
        assert code == 0, err
        assert head["commit"] == "b" * 40  # the checkout did move during the run
        metrics = json.loads((run_dir_of(out) / "metrics.json").read_text())
        assert metrics["code"]["commit"] == "a" * 40
    finally:
        code_version.cache_clear()
