"""Progress reporting injected into long stages: a rich progress bar on a terminal, silence in a pipe.

The protocol and the silent :class:`Progress` live in :mod:`datasets.progress` (every layer reports through
them); this module adds the terminal's bars and chooses between the two.
"""

from __future__ import annotations

import sys
from collections.abc import Iterator
from contextlib import contextmanager

from datasets.progress import Progress, StageBar


class _RichBar:
    def __init__(self, progress, task_id) -> None:
        self._progress = progress
        self._task = task_id

    def advance(self, amount: int = 1) -> None:
        self._progress.advance(self._task, amount)


class RichProgress(Progress):
    """One rich progress bar per stage, on stderr."""

    @contextmanager
    def stage(self, name: str, total: int | None = None) -> Iterator[StageBar]:
        from rich.console import Console
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            TextColumn,
            TimeElapsedColumn,
            TimeRemainingColumn,
        )
        from rich.progress import Progress as RichProgressBar

        columns = [
            TextColumn("[bold]{task.description:<14}"),
            BarColumn(),
            MofNCompleteColumn(),
            TimeElapsedColumn(),
            TimeRemainingColumn(),
        ]
        with RichProgressBar(*columns, console=Console(stderr=True), transient=False) as bar:
            task = bar.add_task(name, total=total)
            yield _RichBar(bar, task)
            if total is not None:
                bar.update(task, completed=total)


def progress_for_terminal(quiet: bool = False) -> Progress:
    """A rich progress reporter when stderr is a terminal (and not ``quiet``), else a silent one."""
    if not quiet and sys.stderr.isatty():
        return RichProgress()
    return Progress()
