"""The documentation a user reads: the version follows the changelog."""

from __future__ import annotations

import re
import tomllib

from tests.conftest import REPO

CHANGELOG = REPO / "CHANGELOG.md"


def test_version_follows_the_changelog() -> None:
    from pipeline.commands import version_line

    with open(REPO / "pyproject.toml", "rb") as f:
        version = tomllib.load(f)["project"]["version"]
    headings = re.findall(r"^## \[([^\]]+)\](?: - (\d{4}-\d{2}-\d{2}))?", CHANGELOG.read_text(), flags=re.M)
    released = [(v, date) for v, date in headings if v.lower() != "unreleased"]
    assert released, "CHANGELOG.md has no released version"
    newest, date = released[0]
    assert date, f"the newest release {newest} has no date"
    assert newest == version, f"CHANGELOG's newest release {newest}, pyproject {version}"
    assert version_line() == f"gpom {version}"
    assert headings[0][0].lower() in ("unreleased", version.lower())  # newest first
