"""User-facing errors.

Every problem a user can cause (a bad file, a wrong option, a missing optional
package) is raised as :class:`KneasError` with a one-line message that names the
problem and the fix. The command-line entry points print it as ``error: ...``
and exit with status 2, never with a traceback.
"""

from __future__ import annotations


class KneasError(Exception):
    """A problem the user can fix; the message is one line saying what and how."""


class SceneError(KneasError):
    """A scene file or scene definition is malformed or unsafe."""


class ConfigError(KneasError):
    """A configuration value or combination is invalid."""


class CheckpointError(KneasError):
    """A checkpoint is missing, damaged or belongs to another method/version."""


def missing_optional(package: str, extra: str, purpose: str) -> KneasError:
    """Error for an optional dependency that is not installed."""
    return KneasError(
        f"{purpose} needs the optional package '{package}', which is not installed; "
        f"install it with: pip install 'kneas[{extra}]' (in a kneas checkout: pip install -e '.[{extra}]')"
    )
