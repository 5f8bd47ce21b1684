"""The SLAM part of ``bench`` (SPEC section 7): the SLAM stage on ``intel.clf`` and ``fr079.clf``.

One full run of the SLAM stage per log with the default configuration (reading the log excluded). For each
log NAME:

- ``slam_NAME_wall_s``: its wall time; ``slam_NAME_data_duration_s``: the time the log spans (first to last
  scan); ``slam_NAME_realtime_factor``: data duration / wall time;
- ``slam_NAME_loop_search_s``: the loop-closure search (``SlamResult.timings_s["loop_search_s"]``) and
  ``slam_NAME_loop_search_share`` its share of ``slam_NAME_total_s``, the SLAM stage's own total
  (``timings_s["total_s"]``, the sum of its sub-stages; the wall time when absent);
- ``slam_NAME_breakdown_s``: every other entry of ``timings_s`` (sub-stage wall times, s; the
  ``odometry_*_s`` entries are parts of ``odometry_s``);
- ``slam_NAME_odometry_scans_per_s``, ``slam_NAME_scans``, ``slam_NAME_keyframes``,
  ``slam_NAME_loop_closures``; ``slam_NAME_wheel_odometry``: where SLAM's wheel odometry came from (the
  choice of :func:`slam.system.wheel_odometry`, as in ``run``: a corrected log's poses are never handed
  over).

``odometry_scans_per_s`` (a SPEC key) is intel's. Timings depend on the machine's load.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from datasets.paths import SHARED_DATA_DIR
from datasets.registry import open_dataset
from pipeline.config import load_config
from pipeline.progress import Progress
from slam.system import run_slam_recording

DATA = SHARED_DATA_DIR
INTEL = DATA / "intel" / "intel.clf.bz2"
FR079 = DATA / "fr079" / "fr079.clf.bz2"
LOGS: tuple[tuple[str, Path], ...] = (("intel", INTEL), ("fr079", FR079))


def bench_slam(
    progress: Progress | None = None, logs: tuple[tuple[str, str | Path], ...] = LOGS
) -> dict[str, Any]:
    """Run SLAM once on each ``(name, path)`` of ``logs`` and report ``slam_NAME_*`` figures (module doc);
    ``odometry_scans_per_s`` is the first log's."""
    progress = progress or Progress()
    out: dict[str, Any] = {}
    for name, path in logs:
        figures = bench_slam_log(path, progress)
        if "odometry_scans_per_s" not in out:
            out["odometry_scans_per_s"] = figures["odometry_scans_per_s"]
        out.update({f"slam_{name}_{key}": value for key, value in figures.items()})
    return out


def bench_slam_log(path: str | Path, progress: Progress | None = None) -> dict[str, Any]:
    """One SLAM run on the log at ``path``: wall time, data duration, real-time factor, loop-search time
    and share, the other sub-stage times, odometry rate and counts (keys without the ``slam_NAME_``
    prefix)."""
    config = load_config()
    rec = open_dataset(path, config.input)
    t0 = time.perf_counter()
    result = run_slam_recording(rec, config.slam, progress)
    wall_s = time.perf_counter() - t0
    stamps = rec.scans.stamps_ns
    duration_s = float(stamps[-1] - stamps[0]) / 1e9
    timings = dict(result.timings_s)
    total_s = timings.get("total_s") or wall_s
    loop_s = timings.get("loop_search_s")
    odometry_s = timings.get("odometry_s")
    return {
        "wall_s": wall_s,
        "data_duration_s": duration_s,
        "realtime_factor": duration_s / wall_s,
        "total_s": total_s,
        "loop_search_s": loop_s,
        "loop_search_share": loop_s / total_s if loop_s is not None and total_s > 0 else None,
        "breakdown_s": {k: v for k, v in timings.items() if k not in ("total_s", "loop_search_s")},
        "odometry_scans_per_s": len(rec.scans) / odometry_s if odometry_s else None,
        "scans": len(rec.scans),
        "keyframes": len(result.keyframe_scans),
        "loop_closures": len(result.loop_closures),
        "wheel_odometry": result.wheel_odometry,
    }
