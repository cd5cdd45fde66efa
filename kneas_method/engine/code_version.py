"""Which code made a run: the kneas version and, when kneas runs from a git checkout, its commit.

``metrics.json`` carries it as ``code`` so that figures measured over weeks (a benchmark table
filled over several sittings, a run compared with last month's) say which code each came from.
"""

from __future__ import annotations

import functools
import subprocess
from pathlib import Path
from typing import Optional

from .. import __version__

PACKAGE_DIR = Path(__file__).resolve().parents[1]


def _git(root: Path, *args: str) -> Optional[str]:
    """``git -C root ARGS``'s stdout, or None where git is missing, fails or hangs."""
    try:
        done = subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, timeout=10,
                              stdin=subprocess.DEVNULL)
    except (OSError, subprocess.SubprocessError):
        return None
    return done.stdout.strip() if done.returncode == 0 else None


@functools.lru_cache(maxsize=None)
def code_version(package_dir: Path = PACKAGE_DIR) -> dict:
    """``{"kneas": version}``, plus ``commit`` (full hash) and ``modified`` (tracked files of the
    package differ from that commit) when ``package_dir`` is the ``kneas_method`` folder of a git
    checkout (an editable install); an installed wheel has no commit to give."""
    out: dict = {"kneas": __version__}
    top = _git(package_dir, "rev-parse", "--show-toplevel")
    if top is None or Path(top).resolve() != package_dir.parent.resolve():
        return out  # not a checkout of kneas (e.g. site-packages inside some other repository)
    commit = _git(package_dir, "rev-parse", "HEAD")
    if commit is None:
        return out
    status = _git(package_dir, "status", "--porcelain", "--untracked-files=no", "--", ".")
    out["commit"] = commit
    if status is not None:
        out["modified"] = bool(status)
    return out


def describe(code: Optional[dict]) -> str:
    """A short label for a ``code`` record: ``a1b2c3d4e5f6``, ``a1b2c3d4e5f6+modified``,
    ``kneas 0.1.0`` without a commit, ``not recorded`` for runs that predate the record."""
    if not isinstance(code, dict) or not code:
        return "not recorded"
    commit = code.get("commit")
    if not isinstance(commit, str) or not commit:
        return f"kneas {code.get('kneas', '?')}"
    return commit[:12] + ("+modified" if code.get("modified") else "")
