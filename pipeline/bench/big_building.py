"""The big-building part of ``bench``: ``run`` end to end on the fr-clinic hospital log (4,820 s of data,
maps of about 15 M cells each), so that a map whose cost follows its bounding box shows as a regression.

Reported: the wall time and real-time factor of the run, its stage timings (wall, and CPU user / system), the
cells of a map and, per map (before and after loop closure), the cells the GP solved and those beyond every
training input's reach (:mod:`mapping.reach`, answered with the prior) with the rate of each. Compare the
real-time factor with ``pipeline_intel_realtime_factor`` of the same ``bench``
(``big_building_realtime_ratio_to_intel``): machines differ, ratios of runs made one after the other do not.
Timings depend on the machine's load.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from datasets.paths import SHARED_DATA_DIR
from pipeline.bench.pipeline import timed_run
from pipeline.progress import Progress

FR_CLINIC = SHARED_DATA_DIR / "fr-clinic" / "fr-clinic_robotlaser.clf.bz2"


def render_rates(stats: dict[str, float]) -> dict[str, float | None]:
    """Cells per second of the solved cells and of those answered with the prior, from one map's
    :attr:`mapping.gpmap.GPOccupancyMap.last_query_stats`."""

    def rate(cells: float, seconds: float) -> float | None:
        return cells / seconds if seconds > 0 else None

    return {
        "cells_solved": int(stats["solved"]),
        "cells_prior": int(stats["prior"]),
        "solved_cells_per_s": rate(stats["solved"], stats["solved_s"]),
        "prior_cells_per_s": rate(stats["prior"], stats["prior_s"]),
    }


def bench_big_building(progress: Progress | None = None, path: str | Path = FR_CLINIC) -> dict[str, Any]:
    """Run the full pipeline once on ``path`` (default fr-clinic) and report its figures."""
    summary, wall, _ = timed_run(path, progress)
    h, w = summary["map"]["shape_hw"]
    return {
        "big_building_input": str(path),
        "big_building_wall_s": wall,
        "big_building_realtime_factor": summary["data_duration_s"] / wall,
        "big_building_stages_s": summary["timings_s"],
        "big_building_stages_cpu_s": summary["cpu_s"],
        "big_building_map_cells": h * w,
        "big_building_render": {
            name: render_rates(stats) for name, stats in summary["map"].get("render", {}).items()
        },
    }
