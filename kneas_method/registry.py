"""Entry-point discovery of methods and components.

Every built-in method and component is declared in ``pyproject.toml`` under an
entry-point group; a third-party package adds its own by declaring entry points
in the same groups, with no change to kneas:

    [project.entry-points."kneas.methods"]
    my-method = "my_package.methods:my_method"      # a MethodSpecification

    [project.entry-points."kneas.selectors"]
    my-selector = "my_package.selectors:MySelectorConfig"

Groups: ``kneas.methods``, ``kneas.encodings`` (hash grid, frequency),
``kneas.fields`` (SDF, NAF: :class:`~kneas_method.fields.base.Field`),
``kneas.attenuations`` (single, shared, independent), ``kneas.samplers``,
``kneas.selectors``, ``kneas.losses``, ``kneas.datamanagers``, ``kneas.stages`` (a procedure's
parts: :class:`~kneas_method.stages.base.StageConfig`) and ``kneas.procedures``
(:class:`~kneas_method.stages.procedures.Procedure`).
"""

from __future__ import annotations

import dataclasses
from importlib.metadata import EntryPoint, entry_points
from typing import Any

from .errors import ConfigError

GROUPS = ("methods", "encodings", "fields", "attenuations", "samplers", "selectors", "losses", "datamanagers", "stages",
          "procedures")


@dataclasses.dataclass
class MethodSpecification:
    """A named, described method: the full config tree of a training run."""

    config: Any
    description: str


def _group(group: str) -> str:
    if group not in GROUPS:
        raise ValueError(f"unknown registry group {group!r}; groups: {GROUPS}")
    return f"kneas.{group}"


def discover(group: str) -> dict[str, EntryPoint]:
    """Entry points declared in ``kneas.<group>``, by name (sorted)."""
    found: dict[str, EntryPoint] = {}
    for ep in entry_points(group=_group(group)):
        found.setdefault(ep.name, ep)
    return dict(sorted(found.items()))


def names(group: str) -> list[str]:
    """Registered names in a group."""
    return list(discover(group))


def load(group: str, name: str) -> Any:
    """Load the object registered as ``name`` in ``group``.

    Raises:
        ConfigError: when nothing is registered under that name (the message
        lists what is), or when the plugin fails to import.
    """
    found = discover(group)
    if name not in found:
        known = ", ".join(found) or "none"
        raise ConfigError(f"no {group[:-1] if group.endswith('s') else group} named {name!r}; available: {known}")
    try:
        return found[name].load()
    except Exception as exc:  # a broken plugin must not take kneas down with a traceback
        raise ConfigError(f"the {group} entry point {name!r} ({found[name].value}) failed to load: {exc}") from exc


def methods() -> dict[str, MethodSpecification]:
    """All registered methods, loaded."""
    out = {}
    for name in discover("methods"):
        spec = load("methods", name)
        if not isinstance(spec, MethodSpecification):
            raise ConfigError(f"entry point kneas.methods:{name} is not a MethodSpecification")
        out[name] = spec
    return out
