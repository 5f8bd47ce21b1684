"""Exception hierarchy for known errors.

Every error a user can cause (bad file, bad topic, bad configuration value) is raised as a subclass of
:class:`GpomError`. The command line prints ``str(error)`` on one line and exits with status 1; anything
else is a bug and keeps its traceback. Library code never prints or exits.

A message quotes what it found in a file only through :func:`shown`, so that it stays one printable line of
bounded length whatever the file holds (control or non-UTF-8 bytes, megabyte fields, 5000-digit numbers).
"""

from __future__ import annotations

import math
import reprlib
from collections.abc import Iterable


class GpomError(Exception):
    """Base class of every known error of the project (the CLI turns it into one line, exit 1)."""


class DatasetError(GpomError):
    """A recording cannot be read or written: missing, unreadable, corrupt or inconsistent input."""


class UnknownFormatError(DatasetError):
    """The format of a path cannot be guessed or is not supported."""


class TopicError(DatasetError):
    """A requested topic is missing, or auto-detection found zero or several candidates."""


class ConfigError(GpomError):
    """A configuration file or value is invalid."""


#: The longest a value read from a file is shown in an error message (characters, ``...`` included).
SHOWN_LIMIT = 60

#: Integers of more bits than this are shown by their number of digits: ``repr`` of an integer of more
#: than 4300 decimal digits raises ValueError (``sys.get_int_max_str_digits``), and such a value is no use
#: in a message anyway.
_SHOWN_INT_BITS = 256


class _BoundedRepr(reprlib.Repr):
    """``reprlib`` bounded by depth and width (a YAML alias bomb is never expanded), safe on huge ints."""

    def __init__(self) -> None:
        super().__init__()
        self.maxlevel, self.maxstring, self.maxother = 3, 4 * SHOWN_LIMIT, 4 * SHOWN_LIMIT

    def repr_int(self, x: int, level: int) -> str:
        if x.bit_length() <= _SHOWN_INT_BITS:
            return repr(x)
        bits = x.bit_length()
        digits = int((bits - 1) * math.log10(2)) + 1  # the true count, or one less
        about = "about " if bits > 1 << 20 else ""  # (10**digits of a million digits takes a while)
        if not about and abs(x) >= 10**digits:
            digits += 1
        return f"<{'a negative' if x < 0 else 'an'} integer of {about}{digits} digits>"

    def repr_bytes(self, x: bytes, level: int) -> str:
        return repr(x[: self.maxstring]) + ("..." if len(x) > self.maxstring else "")


_REPR = _BoundedRepr()


def _escaped(text: str) -> str:
    """``text`` with every non-printable character (control, separator, format) written as an escape."""
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else c.encode("unicode_escape").decode("ascii") for c in text)


def shown(value: object, limit: int = SHOWN_LIMIT, *, bare: bool = False) -> str:
    """``value`` (from a file, or a library's message about one) as it may appear in an error message: one
    printable line of at most ``limit`` characters, whatever the value holds.

    By default its ``repr`` (``'text'``, ``b'\\xff'``, ``[1, 2]``; bytes that are UTF-8 as the text they
    encode), bounded for containers and huge integers. ``bare=True`` shows a ``str`` (or UTF-8 ``bytes``) as
    its text, unquoted, for a name or a library's message. Either way every non-printable character
    (newline, tab, NUL, ESC, bidi controls) becomes an escape such as ``\\x1b``, and a longer result is cut
    to end in ``...``. The one function every reader quotes file contents through.
    """
    if isinstance(value, bytes | bytearray | memoryview):
        raw = bytes(value[: 4 * limit + 4])
        try:
            value = raw.decode("utf-8")
        except UnicodeDecodeError as exc:
            if exc.start < len(raw) - 3 or len(raw) == len(value):  # not UTF-8 (not just cut mid-character)
                text = _REPR.repr(raw)
                return _cut(_escaped(text), limit)
            value = raw[: exc.start].decode("utf-8")
    if isinstance(value, str):
        head = value[: 4 * limit + 4]
        text = head if bare else repr(head)
        if len(head) < len(value):
            text += "..."
    else:
        try:
            text = _REPR.repr(value)
        except Exception:  # a container whose element's repr fails
            text = f"<{type(value).__name__}>"
    return _cut(_escaped(text), limit)


def _cut(text: str, limit: int) -> str:
    """``text`` cut to ``limit`` characters, ending in ``...`` when cut."""
    return text if len(text) <= limit else text[: max(limit - 3, 0)] + "..."


def first_line(exc: BaseException, limit: int = 200) -> str:
    """The first line of ``exc``'s message through :func:`shown` (for a library's error about a file): its
    type name when empty; what a bare MemoryError means."""
    if isinstance(exc, MemoryError):
        return "a size field asks for more memory than there is (MemoryError)"
    try:
        text = str(exc).strip()
    except Exception:  # e.g. ValueError(10**5000): its str fails
        text = ""
    lines = text.splitlines()
    return shown(lines[0].strip() if lines else type(exc).__name__, limit, bare=True)


#: The longest a name read from a file (topic, message type, frame) is shown in a message.
NAME_LIMIT = 120


def shown_name(name: object) -> str:
    """A name read from a file (a topic, message type or frame id) for a message: :func:`shown`, unquoted."""
    return shown(name, NAME_LIMIT, bare=True)


def shown_names(names: Iterable[object], most: int = 12) -> str:
    """``a, b, c`` of :func:`shown_name`; beyond ``most`` names, ``... and N more``."""
    names = list(names)
    text = ", ".join(shown_name(n) for n in names[:most])
    return text + (f" and {len(names) - most} more" if len(names) > most else "")
