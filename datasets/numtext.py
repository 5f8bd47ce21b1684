"""Fast, exact parsing of many decimal numbers from text (batched numpy, no Python loop per number).

Log formats hold millions of plain decimals (``1.07``, ``-0.002458``, ``976052857.337530``). Both parsers
here take one ``bytes`` blob of tokens separated by single spaces, read every token of the plain form
``[+-]digits[.digits]`` with vectorised digit arithmetic, and hand the rare other tokens (exponents,
``nan``, very long mantissas) to Python one by one:

- :func:`parse_floats` gives the float64 that ``float(token)`` gives (the mantissa and ``10**k`` are exact
  in float64 for up to 15 digits, so one IEEE division rounds correctly);
- :func:`parse_stamps_ns` gives integer nanoseconds of decimal seconds, exactly (no float on the way).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from datasets.errors import shown
from datasets.stamps import StampRangeError, decimal_to_ns

_CHUNK_BYTES = 1 << 18
_POW10 = 10 ** np.arange(19, dtype=np.int64)
_SPACE, _DOT, _MINUS, _PLUS, _ZERO, _NINE = (ord(c) for c in " .-+09")


class NumberParseError(ValueError):
    """A token is not a number of the expected kind; ``index`` is its position among the tokens."""

    def __init__(self, index: int, token: str, message: str) -> None:
        super().__init__(message)
        self.index = index
        self.token = token


def _chunks(blob: bytes) -> list[bytes]:
    """``blob`` cut at spaces into pieces of about ``_CHUNK_BYTES`` (bounds the temporary arrays)."""
    out = []
    start = 0
    while len(blob) - start > _CHUNK_BYTES:
        cut = blob.find(b" ", start + _CHUNK_BYTES)
        if cut < 0:
            break
        out.append(blob[start:cut])
        start = cut + 1
    out.append(blob[start:])
    return out


def _cumulative(mask: NDArray[np.bool_]) -> NDArray[np.int32]:
    """(len+1,) int32: ``out[i]`` = number of True in ``mask[:i]``."""
    out = np.empty(mask.shape[0] + 1, dtype=np.int32)
    out[0] = 0
    np.cumsum(mask, dtype=np.int32, out=out[1:])
    return out


def _decompose(chunk: bytes) -> tuple[NDArray, NDArray, NDArray, NDArray, NDArray, NDArray]:
    """Per token: (negative, mantissa int64, fraction digits, digit count, plain-form flag, starts).

    A token is plain when it reads ``[+-]d+[.d*]`` or ``[+-][d*].d+`` with 1..18 digits.
    """
    buf = np.frombuffer(chunk, dtype=np.uint8)
    space = buf == _SPACE
    sep = np.flatnonzero(space)
    starts = np.empty(sep.shape[0] + 1, dtype=np.int64)
    starts[0] = 0
    starts[1:] = sep + 1
    ends = np.empty_like(starts)
    ends[:-1] = sep
    ends[-1] = buf.shape[0]
    is_digit = (buf >= _ZERO) & (buf <= _NINE)
    is_dot = buf == _DOT
    cum_digit = _cumulative(is_digit)
    cum_dot = _cumulative(is_dot)
    cum_other = _cumulative(~(is_digit | is_dot | space))
    n_digits = cum_digit[ends] - cum_digit[starts]
    n_dots = cum_dot[ends] - cum_dot[starts]
    n_other = cum_other[ends] - cum_other[starts]
    nonempty = ends > starts
    first = buf[np.minimum(starts, buf.shape[0] - 1)] if buf.shape[0] else np.zeros(1, np.uint8)
    signed = nonempty & ((first == _MINUS) | (first == _PLUS))
    plain = nonempty & (n_digits >= 1) & (n_digits <= 18) & (n_dots <= 1) & (n_other == signed)

    # mantissa: each digit times 10 ** (digits after it in its token), summed per token (exact in int64)
    digit_pos = np.flatnonzero(is_digit)
    after = np.repeat(cum_digit[ends], n_digits) - np.arange(1, digit_pos.shape[0] + 1, dtype=np.int32)
    contrib = (buf[digit_pos] - _ZERO).astype(np.int64) * _POW10[np.minimum(after, 18)]
    mantissa = np.zeros(starts.shape[0], dtype=np.int64)
    has = n_digits > 0
    if digit_pos.shape[0]:
        mantissa[has] = np.add.reduceat(contrib, cum_digit[starts[has]])
    # fraction digits: digits after the token's first dot
    frac = np.zeros(starts.shape[0], dtype=np.int64)
    dotted = np.flatnonzero(n_dots > 0)
    first_dot = np.flatnonzero(is_dot)[cum_dot[starts[dotted]]]
    frac[dotted] = cum_digit[ends[dotted]] - cum_digit[first_dot + 1]
    return nonempty & (first == _MINUS), mantissa, frac, n_digits, plain, starts


def _tokens(chunk: bytes, starts: NDArray, index: NDArray) -> list[bytes]:
    ends = np.concatenate([starts[1:] - 1, [len(chunk)]])
    return [chunk[starts[i] : ends[i]] for i in index.tolist()]


def parse_floats(blob: bytes) -> NDArray[np.float64]:
    """(T,) float64 of the T space-separated tokens of ``blob``; NumberParseError at the first bad token.

    ``nan`` and ``inf`` tokens parse (to NaN / inf) as with ``float``; callers reject them if they must.
    """
    parts = []
    offset = 0
    for chunk in _chunks(blob):
        negative, mantissa, frac, n_digits, plain, starts = _decompose(chunk)
        exact = plain & (n_digits <= 15)
        values = mantissa.astype(np.float64) / 10.0 ** frac.astype(np.float64)
        values[negative] *= -1.0
        slow = np.flatnonzero(~exact)
        for i, tok in zip(slow.tolist(), _tokens(chunk, starts, slow), strict=True):
            try:
                values[i] = float(tok)
            except ValueError:
                text = tok.decode("ascii", "replace")
                raise NumberParseError(offset + i, text, f"{shown(text)} is not a number") from None
        parts.append(values)
        offset += values.shape[0]
    return np.concatenate(parts)


def parse_stamps_ns(blob: bytes) -> NDArray[np.int64]:
    """(T,) int64 nanoseconds of the T space-separated decimal-seconds tokens of ``blob``, exactly.

    NumberParseError at the first token that is not a finite decimal number.
    """
    parts = []
    offset = 0
    for chunk in _chunks(blob):
        negative, mantissa, frac, _, plain, starts = _decompose(chunk)
        fast = plain & (frac <= 9)
        scale = _POW10[np.clip(frac, 0, 18)]
        whole = mantissa // scale
        fast &= whole < 9_000_000_000  # whole * 1e9 stays inside int64
        stamps = whole * 1_000_000_000 + (mantissa % scale) * _POW10[np.clip(9 - frac, 0, 18)]
        stamps[negative] *= -1
        slow = np.flatnonzero(~fast)
        for i, tok in zip(slow.tolist(), _tokens(chunk, starts, slow), strict=True):
            text = tok.decode("ascii", "replace")
            try:
                stamps[i] = decimal_to_ns(tok)
            except StampRangeError as exc:
                raise NumberParseError(offset + i, text, str(exc)) from None
            except (ValueError, OverflowError):
                raise NumberParseError(
                    offset + i, text, f"{shown(text)} is not a finite decimal number of seconds"
                ) from None
        parts.append(stamps)
        offset += stamps.shape[0]
    return np.concatenate(parts)
