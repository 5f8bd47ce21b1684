"""``bench``: the performance figures of SPEC section 7, measured as benchmarks (never as timed tests).

Each stage contributes one part, a function ``(progress) -> dict`` in its own module (mapping, SLAM, the full
pipeline, scale); their keys are merged into one object with the keys of SPEC section 3 first.
"""

from __future__ import annotations

import importlib
import resource
import sys
from pathlib import Path
from typing import Any

from pipeline.progress import Progress

SPEC_KEYS = (
    "gpfol_queries_per_s",
    "gppol_queries_per_s",
    "grid_cells_per_s",
    "odometry_scans_per_s",
    "slam_intel_wall_s",
    "pipeline_intel_wall_s",
    "pipeline_intel_realtime_factor",
    "peak_rss_mib",
)

# (module, function) of each part, run in this order.
PARTS: tuple[tuple[str, str], ...] = (
    ("pipeline.bench_mapping", "bench_mapping"),
    ("pipeline.bench_slam", "bench_slam"),
    ("pipeline.bench_pipeline", "bench_pipeline"),
    ("pipeline.bench_scale", "bench_scale"),
)


def peak_rss_mib() -> float:
    """Peak resident memory of this process (MiB).

    On Linux the high-water mark of its own memory (``VmHWM``): ``getrusage``'s max RSS of a process started
    by ``fork`` + ``exec`` begins at its parent's resident size (measured: a child of a 640 MB parent reports
    637 MB, its ``VmHWM`` 14 MB), so it cannot measure a child alone."""
    status = Path("/proc/self/status")
    if status.is_file():
        for line in status.read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return kib / 1024.0 if sys.platform != "darwin" else kib / 2**20


def run_bench(progress: Progress | None = None) -> dict[str, Any]:
    """Run every benchmark part; returns the SPEC keys plus extras."""
    progress = progress or Progress()
    result: dict[str, Any] = dict.fromkeys(SPEC_KEYS)
    for module_name, func_name in PARTS:
        result.update(getattr(importlib.import_module(module_name), func_name)(progress))
    result["peak_rss_mib"] = peak_rss_mib()
    return result
