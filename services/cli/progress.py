"""Progress of a long command on stderr: a bar on a terminal, plain lines otherwise.

:func:`progress_bar` is a context manager yielding the callable a stage takes as ``progress``
(the fraction done, 0..1). On a terminal it draws a rich progress bar; when stderr is a file or a
pipe (a log, CI) it writes one plain line each time another tenth is done
(``merging: 40 %``), so a log shows the run moving without a bar's control characters.
"""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Callable, Iterator

__all__ = ["progress_bar"]


@contextlib.contextmanager
def progress_bar(label: str, step: float = 0.1) -> Iterator[Callable[[float], None]]:
    """Report the fraction done of ``label``'s work: a bar on a terminal, else a line each ``step``."""
    from rich.console import Console

    console = Console(stderr=True)
    if console.is_terminal:
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

        with Progress(TextColumn(f"[bold]{label}[/bold]"), BarColumn(), TextColumn("{task.percentage:>3.0f}%"),
                      TimeElapsedColumn(), console=console) as bar:  # fmt: skip
            task = bar.add_task(label, total=1.0)
            yield lambda f: bar.update(task, completed=min(max(float(f), 0.0), 1.0))
        return
    shown = [-1]

    def line(f: float) -> None:
        tenth = int(min(max(float(f), 0.0), 1.0) / step + 1e-9)
        if tenth > shown[0]:
            shown[0] = tenth
            print(f"{label}: {min(100, round(tenth * step * 100))} %", file=sys.stderr, flush=True)

    yield line
