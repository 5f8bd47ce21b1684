"""``bench``: the performance figures of SPEC section 7, measured as benchmarks (never as timed tests).

Each stage contributes one part, a function ``(progress) -> dict`` in its own module, so that parts land
independently. Keys of SPEC section 3 that no landed part measures yet are reported as ``None``.
"""

from __future__ import annotations

import importlib
import resource
import sys
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
    """Peak resident memory of this process (MiB)."""
    kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return kib / 1024.0 if sys.platform != "darwin" else kib / 2**20


def run_bench(progress: Progress | None = None) -> dict[str, Any]:
    """Run every landed benchmark part; returns the SPEC keys (None where not measured) plus extras."""
    progress = progress or Progress()
    result: dict[str, Any] = dict.fromkeys(SPEC_KEYS)
    for module_name, func_name in PARTS:
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as exc:
            if exc.name == module_name:
                continue
            raise
        result.update(getattr(module, func_name)(progress))
    result["peak_rss_mib"] = peak_rss_mib()
    return result
