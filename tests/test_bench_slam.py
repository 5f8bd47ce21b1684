"""The SLAM part of ``bench`` on a short real log: every per-log figure is there and consistent (the
figures themselves are measured by ``bench``, never asserted as timings)."""

from __future__ import annotations

import pytest

from pipeline.bench.slam import LOGS, bench_slam
from tests.conftest import data_file


def test_bench_slam_reports_each_log_and_the_loop_search_share() -> None:
    out = bench_slam(logs=(("seattle", data_file("radish-corrected/seattle-corrected.log.gz")),))
    assert out["odometry_scans_per_s"] == out["slam_seattle_odometry_scans_per_s"] > 0
    assert out["slam_seattle_scans"] == 241
    # the wheels SLAM runs on are those run would use: the ODOM records' raw motion, not the corrected poses
    assert "re-anchored" in out["slam_seattle_wheel_odometry"]
    assert out["slam_seattle_keyframes"] > 0 and out["slam_seattle_loop_closures"] >= 0
    wall, duration = out["slam_seattle_wall_s"], out["slam_seattle_data_duration_s"]
    assert wall > 0 and duration > 0
    assert out["slam_seattle_realtime_factor"] == pytest.approx(duration / wall)
    total, loop = out["slam_seattle_total_s"], out["slam_seattle_loop_search_s"]
    assert 0 < total <= wall and 0 <= loop <= total
    assert out["slam_seattle_loop_search_share"] == pytest.approx(loop / total)
    breakdown = out["slam_seattle_breakdown_s"]
    assert {"odometry_s", "graph_incremental_s", "graph_batch_s", "marginals_s"} <= set(breakdown)
    assert "loop_search_s" not in breakdown and "total_s" not in breakdown


def test_bench_slam_runs_intel_and_fr079_by_default() -> None:
    assert [name for name, _ in LOGS] == ["intel", "fr079"]
    for _, path in LOGS:
        assert path.is_file(), path
