"""``datasets.errors.shown``: how every reader quotes what it found in a file in an error message."""

from __future__ import annotations

import pytest

from datasets.errors import SHOWN_LIMIT, first_line, shown, shown_name, shown_names


@pytest.mark.parametrize(
    ("value", "expected"),
    [
        ("bz2", "'bz2'"),
        (b"bz2", "'bz2'"),
        (b"\nz\x00", r"'\nz\x00'"),
        (b"\xff\xfe\x1b", r"b'\xff\xfe\x1b'"),
        ("gp\x1b[2J\npol", r"'gp\x1b[2J\npol'"),
        ("\u202eevil", r"'\u202eevil'"),
        ("café", "'café'"),
        (7, "7"),
        (None, "None"),
        ({}, "{}"),
        pytest.param(10**5000, "<an integer of 5001 digits>", id="int-5001-digits"),
        pytest.param(-(16**6000), "<a negative integer of 7225 digits>", id="int-minus-7225-digits"),
        pytest.param([1, 10**5000], "[1, <an integer of 5001 digits>]", id="list-of-huge-int"),
    ],
)
def test_shown_is_a_bounded_escaped_repr(value: object, expected: str) -> None:
    assert shown(value) == expected


@pytest.mark.parametrize(
    ("value", "expected"),
    [("base_link", "base_link"), ("a\nb", r"a\nb"), (b"/scan\x00", r"/scan\x00"), (b"\xff", r"b'\xff'")],
)
def test_shown_bare_is_the_text_escaped(value: object, expected: str) -> None:
    assert shown(value, bare=True) == expected


@pytest.mark.parametrize(
    "value",
    ["x" * 10_000, b"\x01" * 10_000, "é" * 10_000, b"\xc3\xa9" * 10_000, [[["deep"] * 100] * 100] * 100],
)
@pytest.mark.parametrize("bare", [False, True])
def test_shown_is_one_printable_line_within_the_limit(value: object, bare: bool) -> None:
    text = shown(value, bare=bare)
    assert text.isprintable() and len(text) <= SHOWN_LIMIT and text.endswith("..."), text
    assert len(shown(value, 20, bare=bare)) <= 20


def test_a_repr_that_fails_shows_the_type() -> None:
    class Broken:
        def __repr__(self) -> str:
            raise RuntimeError("no")

    assert shown(Broken()).startswith("<Broken")
    assert shown([Broken()]).startswith("[<Broken")


def test_first_line_of_library_messages() -> None:
    assert first_line(ValueError("bad\x00 value\nsecond line")) == r"bad\x00 value"
    assert first_line(ValueError()) == "ValueError"
    assert first_line(ValueError(10**5000)) == "ValueError"  # its str() fails
    assert "MemoryError" in first_line(MemoryError())
    assert len(first_line(OSError("x" * 10_000))) == 200


def test_names() -> None:
    assert shown_name("/scan") == "/scan"
    assert shown_name("/a\tb") == r"/a\tb"
    assert shown_names(["/a", "/b\n"]) == r"/a, /b\n"
    assert shown_names([f"/t{i}" for i in range(20)], most=3) == "/t0, /t1, /t2 and 17 more"
