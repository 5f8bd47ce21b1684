"""Shared fixtures: paths to the real datasets in ../shared/data (read in place, never copied)."""

from __future__ import annotations

from pathlib import Path

import pytest

import pipeline  # noqa: F401  (first: sets the vector width numba compiles for, pipeline.simd)
from datasets.paths import REPO_DIR, SHARED_DATA_DIR

REPO = REPO_DIR
DATA = SHARED_DATA_DIR.resolve()


def data_file(relative: str) -> Path:
    """Path of a file of the shared real datasets; the test fails (not skips) when it is missing."""
    path = DATA / relative
    if not path.exists():
        pytest.fail(f"real dataset missing: {path} (the shared data folder must sit beside the checkout)")
    return path


@pytest.fixture(scope="session")
def data_dir() -> Path:
    if not DATA.is_dir():
        pytest.fail(f"shared data folder missing: {DATA}")
    return DATA
