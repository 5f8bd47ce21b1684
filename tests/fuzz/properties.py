"""The property every fuzz case checks: a reader returns a valid recording or raises a known error."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from datasets.errors import GpomError
from datasets.types import Recording
from datasets.validate import validate_recording

CORPUS = Path(__file__).parent / "corpus"


def reads_cleanly(read: Callable[[], object]) -> object | None:
    """Call ``read``; a :class:`GpomError` (whose message is one line) is a clean failure and gives None.

    Any other exception propagates: that is the defect the harness looks for. A returned
    :class:`Recording` must pass :func:`validate_recording` and have a finite, usable shape.
    """
    try:
        out = read()
    except GpomError as err:
        assert str(err).strip(), "a known error with an empty message"
        assert "\n" not in str(err).strip(), f"a known error of several lines: {err!r}"
        return None
    if isinstance(out, Recording):
        validate_recording(out)
        if out.scans is not None:
            for r in out.scans.ranges_m[:50]:
                assert r.dtype == np.float32 and r.ndim == 1
    return out
