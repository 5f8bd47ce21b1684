"""The progress protocol every long stage reports through (readers, SLAM, mapping, the pipeline), and the
timer of their stages (:class:`StageTimer`).

Library code receives a progress reporter and writes ``with progress.stage("odometry", total=n) as bar:
bar.advance()``; it never prints. :class:`Progress` is the silent reporter; the command line injects a
terminal one (:mod:`pipeline.progress`). :func:`stage` accepts None for "no reporter".
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Protocol


class StageBar(Protocol):
    """What a stage's ``with`` block receives: ``advance`` by a number of units of work."""

    def advance(self, amount: int = 1) -> None: ...


class ProgressLike(Protocol):
    """Anything with ``stage(name, total)`` returning a context manager of a :class:`StageBar`."""

    def stage(self, name: str, total: int | None = None): ...


class NullBar:
    """A bar that shows nothing."""

    def advance(self, amount: int = 1) -> None:
        pass


class Progress:
    """Silent progress (pipes, tests, library use)."""

    @contextmanager
    def stage(self, name: str, total: int | None = None) -> Iterator[StageBar]:
        yield NullBar()


@contextmanager
def stage(progress: ProgressLike | None, name: str, total: int | None) -> Iterator[StageBar]:
    """``progress.stage(name, total)``, or a silent bar without a progress reporter."""
    if progress is None:
        yield NullBar()
    else:
        with progress.stage(name, total=total) as bar:
            yield bar


class StageTimer:
    """Wall time per stage, in the order the stages ran: ``with timer("name"): ...`` adds the block's
    seconds to ``seconds["name"]``; :meth:`total` is the time since the timer was made."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self._t0 = time.perf_counter()

    @contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        t = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - t

    def total(self) -> float:
        return time.perf_counter() - self._t0
