"""The property every fuzz case checks: a reader returns a valid recording or raises a known error whose
message is one printable line of bounded length; and the odd YAML scalars the harness feeds to YAML files."""

from __future__ import annotations

import base64
from collections.abc import Callable
from pathlib import Path

import numpy as np
from hypothesis import strategies as st

from datasets.errors import GpomError
from datasets.types import Recording
from datasets.validate import validate_recording

CORPUS = Path(__file__).parent / "corpus"

#: The longest message a known error may have: a path, a few values and names, each of them cut by
#: :func:`datasets.errors.shown` (60 / 120 / 200 characters), at most a dozen names in a list.
MAX_MESSAGE = 2000


def check_message(err: GpomError) -> str:
    """``str(err)``, asserted to be one non-empty printable line (no newline, tab, NUL, ESC, bidi control:
    ``str.isprintable``) of at most :data:`MAX_MESSAGE` characters."""
    message = str(err)
    assert message.strip(), f"a known error with an empty message: {err!r}"
    assert message.isprintable(), f"a known error that is not one printable line: {message!r}"
    assert len(message) <= MAX_MESSAGE, f"a known error of {len(message)} characters: {message[:300]!r}..."
    return message


def reads_cleanly(read: Callable[[], object]) -> object | None:
    """Call ``read``; a :class:`GpomError` (:func:`check_message`) is a clean failure and gives None.

    Any other exception propagates: that is the defect the harness looks for. A returned
    :class:`Recording` must pass :func:`validate_recording` and have a finite, usable shape.
    """
    try:
        out = read()
    except GpomError as err:
        check_message(err)
        return None
    if isinstance(out, Recording):
        validate_recording(out)
        if out.scans is not None:
            for r in out.scans.ranges_m[:50]:
                assert r.dtype == np.float32 and r.ndim == 1
    return out


# -- odd YAML scalars --------------------------------------------------------------------------------------

_BIG = "9" * 5000  # beyond Python's 4300-digit limit of int(str)

#: Plain and tagged YAML scalars that PyYAML / ruamel resolve to dates, timestamps, bytes, sets, huge
#: numbers, or refuse with a ValueError: each is valid in block and in flow context (no bare , ] }).
_FIXED_SCALARS = [
    # implicit dates and timestamps, valid and impossible
    "2001-02-28", "2001-02-29", "2001-13-45", "0000-01-01", "9999-12-31", "2001-12-14t21:59:43.10-05:00",
    "2001-12-14 21:59:43.10 +99", "2001-12-14 21:59:43.1234567890123", "2002-12-14",
    # explicit timestamps
    "!!timestamp 2001-02-28", "!!timestamp 2001-02-29", "!!timestamp 2001-13-45", "!!timestamp x",
    "!!timestamp 2001-12-14 21:59:43 +99",
    # numbers YAML 1.1 reads, or cannot
    _BIG, f"-{_BIG}", f"0x{'f' * 5000}", f"0o{'7' * 5000}", f"0b{'1' * 20000}", f"1:{_BIG}", "190:20:30",
    "-1:0:0", "1_000", "0x_1f", "!!int 1.5", "!!int abc", f"!!int {_BIG}", "!!int 0x", "!!float abc",
    f"!!float 1:{_BIG}", "!!float 1e99999", "!!float .", ".inf", "-.inf", ".nan", "1e400", "-0",
    # bytes, sets and other collections by tag
    "!!binary aGVsbG8=", "!!binary //79", "!!binary @@@", "!!binary ''", "!!set {a: null, b: null}",
    "!!set {}", "!!omap [a: 1]", "!!pairs [a: 1]", "!!seq []", "!!map {}",
    # booleans, nulls, merge and value keys, strings by tag
    "yes", "no", "on", "off", "y", "~", "null", "!!null x", "!!bool maybe", "!!str 5", "<<", "=",
    # tags the safe loaders refuse
    "!unknown x", "!!python/name:os.system", "!!python/object/apply:os.system [ls]",
    # escapes: ESC, NUL, NEL, line separator, an astral character, a lone surrogate
    '"\\e[2J\\0\\x85\\u2028\\U0001f600"', '"\\ud800"', '"a\\nb\\tc"',
]  # fmt: skip


def _date(year: int, month: int, day: int) -> str:
    return f"{year:04d}-{month:02d}-{day:02d}"


def _binary(data: bytes) -> str:
    return "!!binary " + base64.b64encode(data).decode("ascii")


#: Any of the odd YAML scalars, or a generated date (any year, month and day) or ``!!binary`` of any bytes.
YAML_ODD_SCALARS = st.one_of(
    st.sampled_from(_FIXED_SCALARS),
    st.builds(_date, st.integers(0, 9999), st.integers(0, 99), st.integers(0, 99)),
    st.binary(max_size=24).map(_binary),
)
