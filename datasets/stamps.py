"""Timestamps as exact integer nanoseconds: decimal text in and out, and strictly increasing repairs.

Log formats write times as decimal seconds (``976052857.337530``). Parsing them through a float64 loses
the last digits (a float64 near 1e9 s resolves ~0.1 us), so they are parsed from their text straight to
integer nanoseconds and written back the same way.
"""

from __future__ import annotations

from bisect import bisect_left
from collections.abc import Sequence
from decimal import ROUND_HALF_EVEN, Decimal, localcontext

import numpy as np
from numpy.typing import NDArray

from datasets.errors import shown

NS_PER_S = 1_000_000_000


def decimal_to_ns(text: bytes | str) -> int:
    """Integer nanoseconds of a decimal number of seconds (``b"12.5"`` -> 12_500_000_000), exactly.

    Digits beyond the ninth decimal are rounded half to even. Accepts a sign and an exponent
    (``8.97771e-67``). Raises ValueError for anything that is not a finite decimal number, and
    StampRangeError (a ValueError) for a number of nanoseconds that does not fit an int64 (``1e30``).
    """
    s = text.decode("ascii", "replace") if isinstance(text, bytes) else text
    whole, dot, frac = s.partition(".")
    if s.isascii() and whole.isdigit() and (not dot or (frac.isdigit() and len(frac) <= 9)):
        if len(whole) <= 9:  # the common case: no range check needed
            return int(whole) * NS_PER_S + (int(frac.ljust(9, "0")) if dot else 0)
        digits = whole.lstrip("0")  # int() refuses more than 4300 digits, leading zeros included
        if len(digits) > _MAX_WHOLE_DIGITS:
            raise StampRangeError(s)
        return _checked(s, int(digits or "0") * NS_PER_S + (int(frac.ljust(9, "0")) if dot else 0))
    try:
        value = Decimal(s)
        if not value.is_finite():
            raise ValueError(f"{shown(s, 40)} is not a finite number")
        if value and value.adjusted() > _MAX_WHOLE_DIGITS:  # > 1e11 s: int64 ns end near 9.2e9 s
            raise StampRangeError(s)
        with localcontext() as ctx:
            ctx.prec = 40
            ns = int(value.scaleb(9).quantize(Decimal(1), rounding=ROUND_HALF_EVEN))
    except ArithmeticError:  # decimal.InvalidOperation, decimal.Overflow: not a usable decimal
        raise ValueError(f"{shown(s, 40)} is not a decimal number") from None
    return _checked(s, ns)


_MAX_WHOLE_DIGITS = 11
_INT64_MAX = (1 << 63) - 1
_INT64_MIN = -(1 << 63)


class StampRangeError(ValueError):
    """A finite decimal number of seconds whose nanoseconds do not fit an int64 (beyond +-292 years)."""

    def __init__(self, text: str) -> None:
        super().__init__(
            f"{shown(text, 40)} is out of range for a timestamp (int64 nanoseconds, +-292 years)"
        )


def stamp_field_ns(text: str) -> int:
    """:func:`decimal_to_ns` of one text field of a file; a ValueError whose message says what is wrong
    with the field ("is out of range ..." / "is not a decimal number"), for the reader to prefix with the
    file, the line and the field."""
    try:
        return decimal_to_ns(text)
    except StampRangeError:
        raise ValueError("is out of range (int64 nanoseconds, +-292 years)") from None
    except (ValueError, OverflowError):
        raise ValueError("is not a decimal number") from None


def _checked(text: str, ns: int) -> int:
    """``ns`` if it fits an int64, else StampRangeError."""
    if not _INT64_MIN <= ns <= _INT64_MAX:
        raise StampRangeError(text)
    return ns


class StampParseError(ValueError):
    """A timestamp text is not a finite decimal number; ``index`` is its position in the input."""

    def __init__(self, index: int, message: str) -> None:
        super().__init__(message)
        self.index = index


def decimals_to_ns(texts: Sequence[bytes | str]) -> NDArray[np.int64]:
    """(N,) int64 nanoseconds of decimal second strings; StampParseError gives the first bad index."""
    out = np.empty(len(texts), dtype=np.int64)
    for i, t in enumerate(texts):
        try:
            out[i] = decimal_to_ns(t)
        except ValueError as exc:
            raise StampParseError(i, str(exc)) from None
        except OverflowError:
            raise StampParseError(i, f"{shown(t, 40)} is out of range for a timestamp") from None
    return out


def ns_to_decimal(stamp_ns: int) -> str:
    """Decimal seconds with nine decimals, exactly (``12_500_000_000`` -> ``"12.500000000"``)."""
    sign = "-" if stamp_ns < 0 else ""
    whole, frac = divmod(abs(int(stamp_ns)), NS_PER_S)
    return f"{sign}{whole}.{frac:09d}"


def longest_increasing_mask(values: NDArray) -> NDArray[np.bool_]:
    """(N,) True on one longest strictly increasing subsequence of ``values`` (patience sorting, N log N)."""
    vals = np.asarray(values).tolist()
    n = len(vals)
    keep = np.zeros(n, dtype=bool)
    if n == 0:
        return keep
    tails: list = []  # smallest tail value of an increasing run of each length
    tail_index: list[int] = []
    previous = [-1] * n
    for i, v in enumerate(vals):
        k = bisect_left(tails, v)
        if k == len(tails):
            tails.append(v)
            tail_index.append(i)
        else:
            tails[k] = v
            tail_index[k] = i
        previous[i] = tail_index[k - 1] if k > 0 else -1
    i = tail_index[-1]
    while i >= 0:
        keep[i] = True
        i = previous[i]
    return keep


def monotone_stamps_ns(stamps_ns: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
    """Strictly increasing stamps for records whose order (not their stamps) is the truth.

    Keeps the stamps of one longest strictly increasing subsequence and re-stamps every other record by
    linear interpolation, in record index, between its kept neighbours (extrapolating with the median
    step at the ends). Returns ``(stamps_ns (N,) int64, restamped (N,) bool)``; untouched input when it is
    already strictly increasing.
    """
    s = np.asarray(stamps_ns, dtype=np.int64)
    n = s.shape[0]
    if n < 2 or np.all(s[1:] > s[:-1]):  # not np.diff: it overflows int64 for stamps far apart
        return s.copy(), np.zeros(n, dtype=bool)
    keep = longest_increasing_mask(s)
    # stamps far apart (a damaged or synthetic log) overflow int64 arithmetic: use Python ints there
    wide = int(s.max()) - int(s.min()) >= 1 << 60
    work = s.astype(object) if wide else s
    idx = np.arange(n, dtype=np.int64)
    kept_idx = idx[keep]
    kept = work[keep]
    step = int(np.median(np.diff(kept.astype(np.float64)))) if kept.shape[0] > 1 else 1
    step = max(step, 1)
    # nearest kept neighbour before / after each record (as positions into kept_idx)
    after = np.searchsorted(kept_idx, idx, side="left")
    before = after - 1
    out = work.copy()
    lost = ~keep
    inner = lost & (before >= 0) & (after < kept.shape[0])
    b, a = before[inner], after[inner]
    i0, i1 = kept_idx[b], kept_idx[a]
    pos = idx.astype(object) if wide else idx  # record positions in the arithmetic's type
    out[inner] = kept[b] + (kept[a] - kept[b]) * (pos[inner] - i0) // (i1 - i0)
    head = lost & (before < 0)
    out[head] = kept[0] - (kept_idx[0] - pos[head]) * step
    tail = lost & (after >= kept.shape[0])
    out[tail] = kept[-1] + (pos[tail] - kept_idx[-1]) * step
    # guarantee strict increase even where kept neighbours are closer than one ns per record
    out = pos + np.maximum.accumulate(out - pos)
    if wide:  # re-stamped ends may leave int64: clip (the result may then not increase there)
        out = np.array([min(max(int(v), _INT64_MIN), _INT64_MAX) for v in out], dtype=np.int64)
    return out, out != s
