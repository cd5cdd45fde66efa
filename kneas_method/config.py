"""Configuration base classes (the nerfstudio ``_target`` / ``setup()`` pattern).

A component is a dataclass config whose class attribute ``_target`` names the
class it builds; ``config.setup(**kwargs)`` returns ``_target(config, **kwargs)``.
``_target`` is a class, or a ``"module:attr"`` string resolved on first use (so a
config can be declared before the class it builds).

Configs are plain dataclasses of numbers, strings, tuples and nested configs, so
:func:`to_dict` / :func:`update_from_dict` round-trip them through JSON exactly.
"""

from __future__ import annotations

import dataclasses
import importlib
import typing
from typing import Any, ClassVar

from .errors import ConfigError


def resolve_target(target: Any) -> Any:
    """A class, or a ``"package.module:attr"`` string, -> the object."""
    if isinstance(target, str):
        module, _, attr = target.partition(":")
        obj = importlib.import_module(module)
        for part in attr.split("."):
            obj = getattr(obj, part)
        return obj
    return target


@dataclasses.dataclass
class InstantiateConfig:
    """Base config: ``setup(**kwargs)`` builds ``_target(self, **kwargs)``."""

    _target: ClassVar[Any] = None

    def setup(self, **kwargs):
        target = resolve_target(type(self)._target)
        if target is None:
            raise ConfigError(f"{type(self).__name__} has no _target to build")
        return target(self, **kwargs)


def to_dict(config: Any) -> Any:
    """Dataclass tree -> JSON-able dict (tuples become lists)."""
    if dataclasses.is_dataclass(config) and not isinstance(config, type):
        return {f.name: to_dict(getattr(config, f.name)) for f in dataclasses.fields(config)}
    if isinstance(config, (list, tuple)):
        return [to_dict(v) for v in config]
    if isinstance(config, dict):
        return {k: to_dict(v) for k, v in config.items()}
    if hasattr(config, "__fspath__"):
        return str(config)
    return config


def _describe(hint: Any) -> str:
    """A type hint in a config file's words: ``Optional[dict[str, int]]`` -> 'null or a mapping of settings'."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if hint is type(None):
        return "null"
    if origin is typing.Union or (origin is not None and str(origin) == "<class 'types.UnionType'>"):
        return " or ".join(dict.fromkeys(_describe(a) for a in args))
    if origin is typing.Literal:
        return f"one of {list(args)}"
    if origin in (tuple, list):
        return "a list"
    if origin is dict or hint is dict:
        return 'a mapping of settings (a JSON object such as {"name": 1})'
    words = {bool: "true or false", int: "an integer", float: "a number", str: "a string"}
    return words.get(hint, getattr(hint, "__name__", str(hint)))


def _coerce(value: Any, hint: Any, where: str) -> Any:
    origin = typing.get_origin(hint)
    args = typing.get_args(hint)
    if value is None:
        return None
    if origin is typing.Union or (origin is not None and str(origin) == "<class 'types.UnionType'>"):
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _coerce(value, arg, where)
            except (ConfigError, TypeError, ValueError):
                continue
        raise ConfigError(f"config value {where} = {value!r} must be {_describe(hint)}")
    if origin is typing.Literal:
        if value not in args:
            raise ConfigError(f"config value {where} = {value!r} must be one of {list(args)}")
        return value
    if origin in (tuple, list):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"config value {where} must be a list, got {value!r}")
        inner = args[0] if args else Any
        items = [_coerce(v, inner, f"{where}[{i}]") for i, v in enumerate(value)]
        return tuple(items) if origin is tuple else items
    if origin is dict or hint is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"config value {where} must be a mapping of settings, got {value!r}")
        key_hint, value_hint = args if len(args) == 2 else (Any, Any)
        return {_coerce(k, key_hint, f"{where} key"): _coerce(v, value_hint, f"{where}.{k}") for k, v in value.items()}
    if hint is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"config value {where} must be true or false, got {value!r}")
        return value
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"config value {where} must be an integer, got {value!r}")
        return value
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"config value {where} must be a number, got {value!r}")
        return float(value)
    if hint is str:
        if not isinstance(value, str):
            raise ConfigError(f"config value {where} must be a string, got {value!r}")
        return value
    return value


def _nested_config_type(hint: Any):
    """The dataclass of a field typed ``SomeConfig`` or ``Optional[SomeConfig]`` (possibly
    ``Annotated``), else None."""
    if typing.get_origin(hint) is typing.Annotated:
        hint = typing.get_args(hint)[0]
    args = typing.get_args(hint) if typing.get_origin(hint) is typing.Union else (hint,)
    classes = [a for a in args if isinstance(a, type) and dataclasses.is_dataclass(a)]
    return classes[0] if len(classes) == 1 else None


def update_from_dict(config: Any, data: dict, where: str = "config") -> Any:
    """Return a copy of dataclass ``config`` with the values of ``data`` applied.

    Unknown keys and values of the wrong type raise :class:`ConfigError` naming
    the key. Nested dataclasses are updated recursively.
    """
    if not isinstance(data, dict):
        raise ConfigError(f"{where} must be a mapping of settings, got {type(data).__name__}")
    hints = typing.get_type_hints(type(config))
    names = {f.name for f in dataclasses.fields(config)}
    changes = {}
    for key, value in data.items():
        if key not in names:
            known = f"known settings: {', '.join(sorted(names))}" if names else "it takes no settings"
            name = key if isinstance(key, str) and key.isprintable() and key.strip() == key and key else repr(key)
            raise ConfigError(f"unknown setting {where}.{name}; {known}")
        current = getattr(config, key)
        nested = _nested_config_type(hints.get(key))
        if nested is not None and (value is None or current is None):  # an optional part: off (null) or on
            if value is None and type(None) in typing.get_args(hints.get(key)):
                changes[key] = None
                continue
            current = nested()
        if dataclasses.is_dataclass(current) and not isinstance(current, type):
            changes[key] = update_from_dict(current, value, f"{where}.{key}")
        else:
            changes[key] = _coerce(value, hints.get(key, Any), f"{where}.{key}")
    return dataclasses.replace(config, **changes)


# ------------------------------------------------------------------ validation
def at_least(lowest: float, *, whole: bool = False, strict: bool = False, at_most: float | None = None) -> dict:
    """Field metadata: the setting is a number ``>= lowest`` (``> lowest`` with ``strict``),
    ``<= at_most`` when given, a whole number with ``whole``; None is not checked (the
    preset's or the procedure's value, or unused). :func:`check_ranges` reads it."""
    return {"range": (float(lowest), bool(whole), bool(strict), at_most)}


def check_ranges(config: Any, prefix: str) -> None:
    """One-line ConfigError for the first field of ``config`` out of the range its metadata gives
    (:func:`at_least`), named as its command-line flag ``--{prefix}{name}``."""
    import math

    for f in dataclasses.fields(config):
        rule = f.metadata.get("range")
        value = getattr(config, f.name)
        if rule is None or value is None:
            continue
        lowest, whole, strict, at_most = rule
        number = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
        if whole:
            number = number and float(value).is_integer()
        fits = number and (value > lowest if strict else value >= lowest) and (at_most is None or value <= at_most)
        if not fits:
            what = ("a whole number" if whole else "a number") + (" > " if strict else " >= ") + f"{lowest:g}"
            if at_most is not None:
                what += f" and <= {at_most:g}"
            raise ConfigError(f"--{prefix}{f.name.replace('_', '-')} must be {what}, got {value!r}")


def check_tree(config: Any, prefix: str = "") -> None:
    """Check a config tree: every dataclass in it checks itself, its own ``check(prefix)`` where it
    has one (its ranges and the rules between its settings), else :func:`check_ranges`; nested
    configs are checked under ``prefix`` + their field's name (``trainer.``, ``stages.correction.``)."""
    if hasattr(config, "check"):
        config.check(prefix)
    else:
        check_ranges(config, prefix)
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            check_tree(value, f"{prefix}{f.name.replace('_', '-')}.")
