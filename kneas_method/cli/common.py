"""Shared command-line plumbing: one-line errors, exit codes, the console."""

from __future__ import annotations

import sys
from typing import Callable

from rich.console import Console
from rich.markup import escape

from ..errors import KneasError

console = Console(stderr=False, highlight=False)
err_console = Console(stderr=True, highlight=False)

EXIT_USER_ERROR = 2
EXIT_INTERRUPTED = 130


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


def not_built_yet(command: str, issue: str) -> Callable[[], None]:
    """Entry point for a command that does not exist yet: says so and exits 2."""

    def main() -> None:
        def body():
            raise KneasError(f"'{command}' is not built yet in this version of kneas ({issue}); see the README for what works now")

        run_cli(body)

    return main
