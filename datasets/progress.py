"""The progress protocol every long stage reports through (readers, SLAM, mapping, the pipeline), and the
timer of their stages (:class:`StageTimer`).

Library code receives a progress reporter and writes ``with progress.stage("odometry", total=n) as bar:
bar.advance()``; it never prints. :class:`Progress` is the silent reporter; the command line injects a
terminal one (:mod:`pipeline.progress`). :func:`stage` accepts None for "no reporter".
"""

from __future__ import annotations

import os
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
    seconds to ``seconds["name"]``; :meth:`total` is the time since the timer was made.

    ``cpu_seconds["name"]`` holds the process's CPU seconds in the block, ``(user, system)``, every thread
    counted (:func:`os.times`). System time is mostly the kernel handing the process fresh memory: a stage
    whose system time nears its user time spends its wall time on memory, not on arithmetic."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self.cpu_seconds: dict[str, tuple[float, float]] = {}
        self._t0 = time.perf_counter()
        self._cpu0 = os.times()

    @contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        t = time.perf_counter()
        cpu = os.times()
        try:
            yield
        finally:
            self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - t
            now = os.times()
            user, system = self.cpu_seconds.get(name, (0.0, 0.0))
            self.cpu_seconds[name] = (user + now.user - cpu.user, system + now.system - cpu.system)

    def total(self) -> float:
        return time.perf_counter() - self._t0

    def total_cpu(self) -> tuple[float, float]:
        """The process's ``(user, system)`` CPU seconds since the timer was made."""
        now = os.times()
        return now.user - self._cpu0.user, now.system - self._cpu0.system

    def cpu_summary(self) -> dict[str, dict[str, float]]:
        """``{stage: {"user": s, "system": s}}`` per stage and for the ``total``, as ``summary.json``
        stores them."""
        rows = {**self.cpu_seconds, "total": self.total_cpu()}
        return {name: {"user": user, "system": system} for name, (user, system) in rows.items()}
