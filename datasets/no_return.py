"""No-return readings of lasers that log them as a fixed number instead of ``inf``.

Many CARMEN logs write a beam that saw nothing as one fixed reading (81.83 m in ``intel.clf``, 81.91 m in
``fr079.clf``, 51.15 m in some of the Radish logs of a 50 m laser, 32.767 m in ``orebro``). Taken as a
return, that value puts a phantom wall at the laser's reach and frees the space in front of every real wall
the beam crossed. Such a value stands out in the log's histogram of readings: it recurs far more often than
the readings around it, at the top of the range. :func:`repeated_maximum_m` finds it; readers then treat
readings at or beyond it as no returns (SPEC section 2), as they do with a sensor's declared maximum.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

_MAX_READING_M = 1e9  # readings at or beyond this are not compared (no laser reaches 1e6 km)


@dataclass(frozen=True)
class RepeatedMaximum:
    """A log's no-return reading: the smallest of the repeated top values (``value_m``; readings at or
    beyond it are no returns), every such value with its count, and the share of readings they hold."""

    value_m: float
    values_m: tuple[float, ...]
    counts: tuple[int, ...]
    share: float


def repeated_maximum_m(
    ranges_m: NDArray,
    min_count: int = 20,
    min_share: float = 2e-4,
    peak_ratio: float = 10.0,
    tail_share: float = 0.01,
    neighbourhood_m: float = 1.0,
) -> RepeatedMaximum | None:
    """The no-return value of a log whose readings ``ranges_m`` (any shape, metres) hold one, else None.

    Readings are compared at 1 mm. Walking down from the largest reading, a value is a no-return value when
    (1) it occurs at least ``min_count`` times and in at least ``min_share`` of the readings, (2) at least
    ``peak_ratio`` times as often as the median 1-mm bin within ``neighbourhood_m`` of it (a spike, not the
    dense part of the range distribution) and (3) at most ``tail_share`` of the readings that are not
    no-return values already lie above it (it sits at the top of the range). Values found this way are
    peeled off and the walk goes on (a log may use two codes, e.g. 51.14 and 51.15 m); the walk stops at the
    first value that is not a no-return value and has more than ``tail_share`` of the readings above it.
    """
    r = np.asarray(ranges_m, dtype=np.float64).ravel()
    r = r[np.isfinite(r) & (r > 0) & (r < _MAX_READING_M)]  # beyond: damage, and 1-mm bins overflow int64
    if r.size == 0:
        return None
    mm, counts = np.unique(np.round(r * 1000.0).astype(np.int64), return_counts=True)
    total = r.size
    need = max(min_count, min_share * total)
    cum_above = np.concatenate([np.cumsum(counts[::-1])[::-1][1:], [0]])  # readings above each value
    found: list[int] = []
    peeled = 0
    half = round(neighbourhood_m * 1000.0)
    for i in range(len(mm) - 1, -1, -1):
        above = cum_above[i] - peeled
        if above > tail_share * (total - peeled):
            break
        c = counts[i]
        if c < need:
            continue
        lo, hi = np.searchsorted(mm, [mm[i] - half, mm[i] + half + 1])
        # the background: the median count of the 1-mm bins around it, empty ones included (robust to other
        # codes beside it, 51.14 m next to 51.15 m)
        near = np.delete(counts[lo:hi], i - lo)
        bins = 2 * half
        padded = np.concatenate([near, np.zeros(max(bins - near.size, 0), dtype=near.dtype)])
        background = max(float(np.median(padded)), 1.0)
        if c >= peak_ratio * background:
            found.append(i)
            peeled += c
    if not found:
        return None
    values = tuple(float(mm[i]) / 1000.0 for i in sorted(found))
    return RepeatedMaximum(
        value_m=values[0],
        values_m=values,
        counts=tuple(int(counts[i]) for i in sorted(found)),
        share=float(peeled) / total,
    )
