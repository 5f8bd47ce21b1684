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
    neighbour_ratio: float = 2.0,
    above_ratio: float = 2.0,
) -> RepeatedMaximum | None:
    """The no-return value of a log whose readings ``ranges_m`` (any shape, metres) hold one, else None.

    Readings are compared at 1 mm. A value is a no-return value when

    1. it occurs at least ``min_count`` times and in at least ``min_share`` of the readings (support);
    2. at least ``peak_ratio`` times as often as the median 1-mm bin within ``neighbourhood_m`` of it (a
       spike, not the dense part of the range distribution);
    3. at least ``neighbour_ratio`` times as often as every other reading within one quantum of it (the
       log's reading step: 1 cm in ``intel.clf``, 1 mm in ``orebro``), no-return values aside. Quantised
       readings leave most 1-mm bins empty, so test 2 alone is met by any value seen 10 times; a wall hit
       is spread over neighbouring steps (17.12, 17.13, 17.14 m seen 35, 51, 36 times in the first 300
       scans of ``intel.clf``), a code is not (51.15 m: 2,991 readings, 211 at 51.14 m, itself a code, and
       61 at 51.16 m in ``edmonton``);
    4. the readings above it that are not no-return values number at most 1/``above_ratio`` of its own
       count and at most ``tail_share`` of the readings that are not no-return values (it sits at the top
       of the range: a code outnumbers whatever real returns lie beyond it).

    No-return values are taken one at a time, the most frequent qualifying value first, and set aside
    before the next is looked for (a log may use two codes, e.g. 51.14 and 51.15 m, or 32.763 and
    32.767 m: each stands out only once the other is set aside). Only the values with at most
    ``tail_share`` of the other readings above them are looked at.
    """
    r = np.asarray(ranges_m, dtype=np.float64).ravel()
    r = r[np.isfinite(r) & (r > 0) & (r < _MAX_READING_M)]  # beyond: damage, and 1-mm bins overflow int64
    if r.size == 0:
        return None
    mm, counts = np.unique(np.round(r * 1000.0).astype(np.int64), return_counts=True)
    total = r.size
    need = max(min_count, min_share * total)
    cum_above = np.concatenate([np.cumsum(counts[::-1])[::-1][1:], [0]])  # readings above each value
    steps, step_counts = np.unique(np.diff(mm), return_counts=True)
    quantum = int(steps[np.argmax(step_counts)]) if steps.size else 1  # the most common reading step (mm)
    half = round(neighbourhood_m * 1000.0)
    is_code = np.zeros(len(mm), dtype=bool)
    peeled = 0
    while True:
        code_above = np.concatenate([np.cumsum((counts * is_code)[::-1])[::-1][1:], [0]])
        best = -1
        for i in range(len(mm) - 1, -1, -1):
            above = int(cum_above[i] - code_above[i])  # readings above that are not no-return values
            if above > tail_share * (total - peeled):
                break
            c = int(counts[i])
            if is_code[i] or c < need or above_ratio * above > c or (best >= 0 and c <= counts[best]):
                continue
            lo, hi = np.searchsorted(mm, [mm[i] - half, mm[i] + half + 1])
            # the background: the median count of the 1-mm bins around it, empty ones included (robust to
            # other codes beside it, 51.14 m next to 51.15 m)
            near = np.delete(counts[lo:hi], i - lo)
            padded = np.concatenate([near, np.zeros(max(2 * half - near.size, 0), dtype=near.dtype)])
            if c < peak_ratio * max(float(np.median(padded)), 1.0):
                continue
            a, b = np.searchsorted(mm, [mm[i] - quantum, mm[i] + quantum + 1])
            beside = np.delete(counts[a:b] * ~is_code[a:b], i - a)
            if beside.size and c < neighbour_ratio * int(beside.max()):
                continue
            best = i
        if best < 0:
            break
        is_code[best] = True
        peeled += int(counts[best])
    if not is_code.any():
        return None
    found = np.flatnonzero(is_code)
    values = tuple(float(mm[i]) / 1000.0 for i in found)
    return RepeatedMaximum(
        value_m=values[0],
        values_m=values,
        counts=tuple(int(counts[i]) for i in found),
        share=float(peeled) / total,
    )
