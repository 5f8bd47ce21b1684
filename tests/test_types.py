"""The shared data model: scans, sequences, trajectories, cloud-to-scan."""

from __future__ import annotations

import numpy as np
import pytest

from datasets.cloud import cloud_to_scan
from datasets.errors import DatasetError
from datasets.types import LaserScan, ScanSequence, Trajectory, beam_angles_rad, wrap_angle_rad


def test_beam_angles_are_float32_and_uniform() -> None:
    a = beam_angles_rad(-np.pi / 2, np.pi / 180, 180)
    assert a.dtype == np.float32 and a.shape == (180,)
    assert a[0] == np.float32(-np.pi / 2)
    np.testing.assert_allclose(np.diff(a.astype(np.float64)), np.pi / 180, atol=1e-6)


def test_scan_masks() -> None:
    scan = LaserScan(
        ranges_m=np.array([0.01, 1.0, 30.0, np.inf, np.nan, -np.inf], np.float32),
        angles_rad=beam_angles_rad(0, 0.1, 6),
        stamp_ns=5,
        range_min_m=0.05,
        range_max_m=30.0,
    )
    assert scan.hit_mask().tolist() == [False, True, False, False, False, False]
    assert scan.no_return_mask().tolist() == [False, False, True, True, True, False]
    np.testing.assert_allclose(scan.points_xy_m(), [[np.cos(0.1), np.sin(0.1)]], rtol=1e-6)


def test_sequence_random_access_and_subset() -> None:
    angles = beam_angles_rad(0, 0.5, 3)
    seq = ScanSequence(
        [np.full(3, i, np.float32) for i in range(4)], [angles] * 4, [10, 20, 30, 40], 0.0, 10.0
    )
    assert len(seq) == 4 and seq[2].stamp_ns == 30 and seq[-1].ranges_m[0] == 3
    sub = seq.subset([3, 1])
    assert sub.stamps_ns.tolist() == [40, 20]
    ranges, _ = seq.packed()
    assert ranges.shape == (4, 3)
    with pytest.raises(IndexError):
        seq[4]


def test_sequence_rejects_mismatched_arrays() -> None:
    with pytest.raises(DatasetError, match="scan 0"):
        ScanSequence([np.ones(3)], [np.ones(2)], [1], 0.0, 1.0)


def test_trajectory_interpolation_across_pi() -> None:
    traj = Trajectory(np.array([0, 10]), np.array([[0, 0, np.pi - 0.1], [1, 2, -np.pi + 0.1]]))
    mid = traj.interpolate(np.array([5]))[0]
    np.testing.assert_allclose(mid[:2], [0.5, 1.0])
    assert abs(wrap_angle_rad(mid[2] - np.pi)) < 1e-9


def test_interpolation_is_exact_at_epoch_stamps() -> None:
    t0 = 1_700_000_000_000_000_000  # 2023 in ns: float64 of the absolute stamp would quantise to 256 ns
    traj = Trajectory(np.array([t0, t0 + 1000]), np.array([[0.0, 0, 0], [1000.0, 0, 0]]))
    np.testing.assert_allclose(traj.interpolate(np.array([t0 + 1, t0 + 999]))[:, 0], [1.0, 999.0])


def test_cloud_to_scan_keeps_nearest_point_in_band() -> None:
    pts = np.array([[2.0, 0.0, 0.0], [3.0, 0.0, 0.0], [1.0, 0.0, 5.0], [0.0, 4.0, 0.1]])
    ranges, angles = cloud_to_scan(pts, (-0.5, 0.5), 360, 50.0)
    i0 = int(np.argmin(np.abs(angles)))
    i90 = int(np.argmin(np.abs(angles - np.pi / 2)))
    assert ranges[i0] == 2.0 and ranges[i90] == 4.0
    assert np.isinf(ranges).sum() == 358


def test_within_span_allows_the_slack_or_half_the_period() -> None:
    """Stamps beyond a trajectory's ends count as within it up to SPAN_SLACK_NS, or half the median period
    where that is longer; an unsorted trajectory is read by its sorted stamps."""
    from datasets.types import SPAN_SLACK_NS, Trajectory

    s = 10**9
    dense = Trajectory(np.array([3, 1, 2]) * s // 10, np.zeros((3, 3)))  # 0.1 s period, unsorted
    first, last = s // 10, 3 * s // 10
    q = np.array([0, first - SPAN_SLACK_NS - 1, last + SPAN_SLACK_NS, last + SPAN_SLACK_NS + 1])
    assert dense.within_span(q).tolist() == [True, False, True, False]
    sparse = Trajectory(np.array([0, 4, 8]) * s, np.zeros((3, 3)))  # 4 s period: 2 s of slack
    assert sparse.within_span(np.array([-2 * s, -2 * s - 1, 10 * s, 10 * s + 1])).tolist() == [
        True,
        False,
        True,
        False,
    ]
