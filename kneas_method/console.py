"""The one console every command and stage prints to, and the exit codes.

``say(text)`` prints one line, never wrapped (paths stay copyable and greppable).
Text with rich markup (``[yellow]...[/]``) is rendered on a terminal; when
output goes to a file or a pipe, rich prints no colour codes.
"""

from __future__ import annotations

from rich.console import Console

# soft_wrap: no line is broken at the console's width (80 columns when output goes to a file or a
# pipe), so every command's paths stay whole; tables still fit the width.
console = Console(stderr=False, highlight=False, soft_wrap=True)
err_console = Console(stderr=True, highlight=False, soft_wrap=True)

EXIT_USER_ERROR = 2
EXIT_INTERRUPTED = 130


def say(text: str, markup: bool = True) -> None:
    """One message line on the console, never wrapped."""
    console.print(text, soft_wrap=True, markup=markup)
