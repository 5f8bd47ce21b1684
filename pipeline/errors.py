"""Known errors raised by the pipeline (run folders, inputs, stored parameters), and the translation of
library exceptions into them at the boundary of each stage."""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from datasets.errors import GpomError


class PipelineError(GpomError):
    """A run cannot proceed: existing output folder, inconsistent run folder, missing inputs."""


#: Exceptions of the libraries under the stages that bad input can provoke: GTSAM (RuntimeError, e.g.
#: IndeterminateSystemException), numpy linear algebra, allocation (numpy's ArrayMemoryError is a
#: MemoryError), floating point traps, and the operating system's I/O errors (read-only folders, a full disk).
LIBRARY_ERRORS: tuple[type[BaseException], ...] = (
    RuntimeError,
    np.linalg.LinAlgError,
    MemoryError,
    FloatingPointError,
    OSError,
)


def reworded(exc: GpomError, message: str) -> GpomError:
    """A known error of ``exc``'s class saying ``message`` (a PipelineError when that class takes other
    arguments)."""
    try:
        return type(exc)(message)
    except TypeError:  # a subclass with another constructor
        return PipelineError(message)


@contextmanager
def stage_boundary(stage: str, subject: str | Path, name_known_errors: bool = True) -> Iterator[None]:
    """Turn a library exception raised in ``stage`` of the work on ``subject`` into one PipelineError line.

    A known error (:class:`GpomError`) without ``subject`` in its message gets it as a prefix (unless
    ``name_known_errors`` is False), so that every message names the file it is about. ``GPOM_TRACEBACK=1``
    in the environment keeps the original exception (for bug reports).
    """
    name = str(subject)
    try:
        yield
    except GpomError as exc:
        if not name_known_errors or name in str(exc):
            raise
        raise reworded(exc, f"{name}: {exc}") from exc
    except LIBRARY_ERRORS as exc:
        if os.environ.get("GPOM_TRACEBACK"):
            raise
        detail = " ".join(str(exc).split()) or "no message"
        if isinstance(exc, OSError) and exc.strerror:
            detail = f"{exc.strerror}" + (f": {exc.filename}" if exc.filename else "")
            if exc.filename2:  # a copy or rename: where it went is often what failed (a full disk)
                detail += f" -> {exc.filename2}"
        raise PipelineError(
            f"{name}: {stage} failed: {type(exc).__name__}: {detail[:300]} (GPOM_TRACEBACK=1 shows where)"
        ) from None
