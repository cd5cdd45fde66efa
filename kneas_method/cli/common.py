"""Shared command-line plumbing: one-line errors, exit codes, the console."""

from __future__ import annotations

import argparse
import dataclasses
import sys
from typing import Callable

from rich.markup import escape

from ..console import EXIT_INTERRUPTED, EXIT_USER_ERROR, console, err_console
from ..errors import KneasError

__all__ = ["run_cli", "console", "err_console", "EXIT_INTERRUPTED", "EXIT_USER_ERROR"]


def run_cli(main: Callable[[], int | None]) -> None:
    """Run a command's body; user errors become ``error: ...`` and exit 2, Ctrl-C exits 130."""
    try:
        code = main()
    except KneasError as exc:
        # one line whatever the message quotes (a config key or a file name may hold a line break)
        message = str(exc).replace("\r", "\\r").replace("\n", "\\n")
        err_console.print(f"[bold red]error:[/] {escape(message)}", soft_wrap=True)
        sys.exit(EXIT_USER_ERROR)
    except KeyboardInterrupt:
        err_console.print("interrupted")
        sys.exit(EXIT_INTERRUPTED)
    sys.exit(code or 0)


def did_you_mean(word: str, choices, n: int = 3) -> str:
    """``"; did you mean X or Y?"`` from the closest of ``choices`` (empty when none is close)."""
    import difflib

    close = difflib.get_close_matches(word, list(choices), n=n, cutoff=0.6)
    return f"; did you mean {' or '.join(close)}?" if close else ""


class ArgumentParser(argparse.ArgumentParser):
    """argparse with one-line errors (``KneasError``, so ``run_cli`` prints ``error: ...`` and
    exits 2) that name the closest valid option or choice instead of a usage block."""

    def error(self, message: str):
        import re

        hint = ""
        m = re.search(r"unrecognized arguments: (\S+)", message)
        if m:
            hint = did_you_mean(m.group(1).split("=")[0], self._all_options())
        m = re.search(r"invalid choice: '([^']+)' \(choose from (.+)\)", message)
        if m:
            hint = did_you_mean(m.group(1), [c.strip(" '") for c in m.group(2).split(",")])
        raise KneasError(f"{self.prog}: {message}{hint} ({self.prog} --help lists the options)")

    def _all_options(self) -> list[str]:
        """Option strings of this parser and of its sub-commands' parsers."""
        out = []
        for action in self._actions:
            out += action.option_strings
            if isinstance(action, argparse._SubParsersAction):
                for parser in action.choices.values():
                    out += [o for a in parser._actions for o in a.option_strings]
        return sorted(set(out))


def _flags(config, prefix: str = "") -> set[str]:
    """The ``--flags`` tyro makes for a config dataclass (nested configs as ``--a.b``; booleans
    also as ``--no-...``)."""
    out: set[str] = set()
    for f in dataclasses.fields(config):
        name = prefix + f.name.replace("_", "-")
        value = getattr(config, f.name)
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            out |= _flags(value, name + ".")
            continue
        out.add("--" + name)
        if isinstance(value, bool):
            out.add("--" + prefix + "no-" + f.name.replace("_", "-"))
    return out


def _settings_flags(config, prefix: str = "") -> set[str]:
    """The ``--flags`` of a config's dict-typed fields (``--model.encoding-options``): each takes
    NAME VALUE pairs on the command line."""
    import typing

    out: set[str] = set()
    hints = typing.get_type_hints(type(config))
    for f in dataclasses.fields(config):
        name = prefix + f.name.replace("_", "-")
        value = getattr(config, f.name)
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            out |= _settings_flags(value, name + ".")
            continue
        hint = hints.get(f.name)
        kinds = typing.get_args(hint) if typing.get_origin(hint) is typing.Union else (hint,)
        if any(k is dict or typing.get_origin(k) is dict for k in kinds):
            out.add("--" + name)
    return out


def check_settings_pairs(argv: list[str], flags: set[str], prog: str) -> None:
    """Refuse, in one line naming the flag and the fix, a malformed ``--X-options`` value list:
    ``NAME=VALUE`` instead of ``NAME VALUE``, a name with no value, an empty name, a name given twice.
    (tyro's own message for these is a paragraph that names no fix.)"""
    i = 0
    while i < len(argv):
        flag, eq, first = argv[i].partition("=")
        if flag not in flags:
            i += 1
            continue
        values = [first] if eq else []
        i += 1
        while i < len(argv) and not argv[i].startswith("--"):
            values.append(argv[i])
            i += 1
        form = f"{flag} NAME VALUE [NAME VALUE ...]"
        if values == ["None"]:
            continue
        for token in values[0::2]:
            if "=" in token:
                name, _, value = token.partition("=")
                raise KneasError(f"{prog}: {flag} {token!r}: a setting is NAME VALUE with a space: {flag} {name} {value}")
            if not token.strip():
                raise KneasError(f"{prog}: {flag} has an empty setting name; give {form}")
        if len(values) % 2:
            raise KneasError(f"{prog}: {flag}: the setting {values[-1]!r} has no value; give {form}")
        names = values[0::2]
        twice = sorted({n for n in names if names.count(n) > 1})
        if twice:
            raise KneasError(f"{prog}: {flag} gives {', '.join(twice)} more than once; keep one value for each setting")


def tyro_cli(defaults: dict, descriptions: dict, argv: list[str], *, prog: str, description: str, what: str):
    """``tyro.cli`` over subcommands ``defaults`` (name -> config), with one-line errors: an
    unknown subcommand or option names the closest valid ones; any other parsing error is
    folded into one line. ``what`` names a subcommand in messages (``method``)."""
    import contextlib
    import io
    import re

    import tyro

    if argv and not argv[0].startswith("-") and argv[0] not in defaults:
        raise KneasError(f"{prog}: unknown {what} {argv[0]!r}{did_you_mean(argv[0], defaults)} "
                         f"(available: {', '.join(defaults)})")
    if argv and argv[0] in defaults and "-h" not in argv and "--help" not in argv:
        known = _flags(defaults[argv[0]])
        for token in argv[1:]:
            flag = token.split("=", 1)[0]
            if flag.startswith("--") and flag not in known:
                raise KneasError(f"{prog} {argv[0]}: unknown option {flag}{did_you_mean(flag, known)} "
                                 f"({prog} {argv[0]} --help lists the options)")
        check_settings_pairs(argv[1:], _settings_flags(defaults[argv[0]]), f"{prog} {argv[0]}")
    sub = tyro.extras.subcommand_type_from_defaults(defaults, descriptions)
    captured = io.StringIO()
    try:
        with contextlib.redirect_stderr(captured):
            return tyro.cli(sub, args=argv, prog=prog, description=description)
    except SystemExit as exc:
        if not exc.code:
            raise
        text = " ".join(re.sub(r"[\u2500-\u257f]+", " ", captured.getvalue()).split())  # no box drawing, one line
        choice = re.search(r"invalid choice '([^']*)' for argument '([^']*)'\. Expected one of \(([^)]*)\)", text)
        parsing = re.search(r"(Error parsing .*?)(?: Argument helptext:|$)", text)
        if choice:
            options = [c.strip(" '") for c in choice.group(3).split(",")]
            text = f"{choice.group(2)} {choice.group(1)!r} is not one of {', '.join(options)}{did_you_mean(choice.group(1), options)}"
        elif parsing:
            text = parsing.group(1).strip()
        else:
            text = re.sub(r"For full helptext.*$", "", text).strip()
        raise KneasError(f"{prog}: {text} ({prog} --help lists the options)") from None
