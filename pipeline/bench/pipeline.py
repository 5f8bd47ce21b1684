"""The full-pipeline part of ``bench`` (SPEC section 7): ``run`` on ``intel.clf`` end to end.

One run of the whole pipeline (read, SLAM, training, maps before and after loop closure, every export) with
the default configuration into a temporary folder: ``pipeline_intel_wall_s`` is its wall time and
``pipeline_intel_realtime_factor`` the log's duration divided by it; ``pipeline_intel_mapper`` names the
mapper, ``pipeline_intel_stages_s`` the run's own stage timings. Timings depend on the machine's load.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Any

from datasets.paths import SHARED_DATA_DIR
from pipeline.config import Config, load_config
from pipeline.progress import Progress
from pipeline.run import run_pipeline

INTEL = SHARED_DATA_DIR / "intel" / "intel.clf.bz2"


def timed_run(path: str | Path, progress: Progress | None = None) -> tuple[dict[str, Any], float, Config]:
    """One ``run`` of the default configuration on ``path`` into a temporary folder: its summary, its wall
    time (s) and the configuration."""
    config = load_config()
    with tempfile.TemporaryDirectory(prefix="gpom-bench-") as tmp:
        t0 = time.perf_counter()
        summary = run_pipeline(Path(path), Path(tmp) / "run", config, progress=progress)
        wall = time.perf_counter() - t0
    return summary, wall, config


def bench_pipeline(progress: Progress | None = None, path: str | Path = INTEL) -> dict[str, Any]:
    """Run the full pipeline once on ``path`` (default intel.clf) and report its wall time."""
    summary, wall, config = timed_run(path, progress)
    return {
        "pipeline_intel_wall_s": wall,
        "pipeline_intel_realtime_factor": summary["data_duration_s"] / wall,
        "pipeline_intel_mapper": config.mapping.mapper,
        "pipeline_intel_stages_s": summary["timings_s"],
        "pipeline_intel_stages_cpu_s": summary["cpu_s"],
        "pipeline_intel_map_cells": summary["map"]["shape_hw"][0] * summary["map"]["shape_hw"][1],
    }
