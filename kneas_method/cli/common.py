"""Shared command-line plumbing: one-line errors, exit codes, the console."""

from __future__ import annotations

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
        err_console.print(f"[bold red]error:[/] {escape(str(exc))}", soft_wrap=True)
        sys.exit(EXIT_USER_ERROR)
    except KeyboardInterrupt:
        err_console.print("interrupted")
        sys.exit(EXIT_INTERRUPTED)
    sys.exit(code or 0)
