"""Where the shared real datasets live: ``../shared/data`` beside the checkout (read in place, never copied).

Benchmarks, figure scripts, the evaluation suite's default folder and the tests all find the data here.
"""

from __future__ import annotations

from pathlib import Path

#: The checkout's root folder.
REPO_DIR = Path(__file__).resolve().parent.parent
#: The shared data folder (``../shared/data`` beside the checkout; its README says what each file is).
SHARED_DATA_DIR = REPO_DIR.parent / "shared" / "data"
