"""The SLAM part of ``bench`` (SPEC section 7): odometry scans per second and the SLAM wall time on intel.clf.

One full run of the SLAM stage on ``intel.clf`` (13,631 scans, 2,691 s of data) with the default
configuration: ``slam_intel_wall_s`` is its wall time (reading the log excluded),
``odometry_scans_per_s`` the scans registered per second by its odometry sub-stage, and
``slam_intel_breakdown_s`` the time of each sub-stage. Timings depend on the machine's load.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from datasets.registry import open_dataset
from pipeline.config import load_config
from pipeline.progress import Progress
from slam.system import run_slam

INTEL = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "intel" / "intel.clf.bz2"


def bench_slam(progress: Progress | None = None, path: str | Path = INTEL) -> dict[str, Any]:
    """Run SLAM once on ``path`` (default intel.clf) and report its speed."""
    progress = progress or Progress()
    config = load_config()
    rec = open_dataset(path, config.input)
    wheel = rec.scan_poses if rec.scan_poses is not None else rec.odometry
    t0 = time.perf_counter()
    result = run_slam(rec.scans, wheel, rec.laser_in_base_xytheta, config.slam, progress)
    wall = time.perf_counter() - t0
    stamps = rec.scans.stamps_ns
    duration_s = float(stamps[-1] - stamps[0]) / 1e9
    timings = result.timings_s
    return {
        "odometry_scans_per_s": len(rec.scans) / timings["odometry_s"],
        "slam_intel_wall_s": wall,
        "slam_intel_realtime_factor": duration_s / wall,
        "slam_intel_scans": len(rec.scans),
        "slam_intel_keyframes": len(result.keyframe_scans),
        "slam_intel_loop_closures": len(result.loop_closures),
        "slam_intel_breakdown_s": {k: v for k, v in timings.items() if k != "total_s"},
    }
