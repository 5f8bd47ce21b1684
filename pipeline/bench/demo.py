"""The first-run part of ``bench``: ``run.py demo`` with numba's cache empty (a new user's first run) and
again with it filled.

Both runs are separate interpreters whose numba cache is a fresh temporary folder (``NUMBA_CACHE_DIR``), so
the checkout's own cache is neither used nor touched: the first run compiles every core it calls, the second
loads them. ``demo_cold_wall_s`` / ``demo_warm_wall_s`` are the processes' wall times and
``demo_cold_stages_s`` / ``demo_warm_stages_s`` the runs' own stage timings. ``make env`` fills the
checkout's cache (``pipeline/warmup.py``) so that a user's first ``make demo`` runs like the warm one.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from datasets.paths import REPO_DIR
from pipeline.progress import Progress


def isolated_cache_env(cache_dir: Path) -> dict[str, str]:
    """This process's environment with numba's cache in ``cache_dir`` (and the checkout importable)."""
    env = dict(os.environ)
    env["NUMBA_CACHE_DIR"] = str(cache_dir)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(REPO_DIR), env.get("PYTHONPATH", "")) if p)
    return env


def _demo(out_dir: Path, env: dict[str, str]) -> tuple[float, dict[str, Any]]:
    """Wall time (s) of one ``run.py -q demo --json`` process and the run's stage timings."""
    t0 = time.perf_counter()
    proc = subprocess.run(
        [
            sys.executable,
            str(REPO_DIR / "run.py"),
            "-q",
            "demo",
            "--out",
            str(out_dir),
            "--overwrite",
            "--json",
        ],
        env=env,
        capture_output=True,
        text=True,
        check=False,
    )
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        tail = (proc.stderr.strip().splitlines() or ["no message"])[-1]
        raise RuntimeError(f"demo benchmark failed (exit {proc.returncode}): {tail}")
    summary = json.loads(proc.stdout)
    return wall, summary.get("timings_s", {})


def bench_demo(progress: Progress | None = None) -> dict[str, Any]:
    """Cold and warm ``run.py demo`` (see the module docstring)."""
    progress = progress or Progress()
    with (
        tempfile.TemporaryDirectory(prefix="gpom-bench-demo-") as tmp,
        progress.stage("bench demo", 2) as bar,
    ):
        env = isolated_cache_env(Path(tmp) / "numba-cache")
        cold_s, cold_stages = _demo(Path(tmp) / "demo", env)
        bar.advance()
        warm_s, warm_stages = _demo(Path(tmp) / "demo", env)
        bar.advance()
    return {
        "demo_cold_wall_s": cold_s,
        "demo_warm_wall_s": warm_s,
        "demo_cold_over_warm": cold_s / warm_s,
        "demo_cold_stages_s": cold_stages,
        "demo_warm_stages_s": warm_stages,
    }
