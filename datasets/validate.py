"""Validation at the reader boundary: what every reader returns is checked once, here.

SLAM and mapping assume finite input: finite angles, range limits, poses, covariances and mountings, stamps in
time order, sizes that fit. A reader that lets a non-finite or impossible value through (a damaged file, a NaN
in ``/odom``, ``angle_increment: nan``) would otherwise crash a later stage with a library exception far from
its cause; :func:`validate_recording` turns it into one :class:`~datasets.errors.DatasetError` naming the file
and the field. Ranges are the exception: out-of-limits values are legal readings there (REP 117).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from datasets.errors import DatasetError
from datasets.types import Recording, Trajectory

#: Largest believable |stamp| (ns), 2200-01-01 in Unix time: int64 nanoseconds end in 2262 and anything past
#: 2200 is damage. Negative stamps are legal (corrected logs carry synthetic, even negative, stamps).
MAX_STAMP_NS = 7_258_118_400 * 10**9
#: Largest believable coordinate of a pose or a mounting (m): 10,000 km.
MAX_COORDINATE_M = 1e7


def _first_bad(mask: NDArray[np.bool_]) -> int:
    return int(np.flatnonzero(mask)[0])


def _check_stamps(where: str, stamps_ns: NDArray[np.int64]) -> None:
    if stamps_ns.size == 0:
        return
    bad = np.abs(stamps_ns) > MAX_STAMP_NS
    if bad.any():
        i = _first_bad(bad)
        raise DatasetError(f"{where}: stamp {i} is {int(stamps_ns[i])} ns, beyond the year 2200")
    back = np.diff(stamps_ns) < 0
    if back.any():
        i = _first_bad(back) + 1
        t, t_prev = int(stamps_ns[i]), int(stamps_ns[i - 1])
        raise DatasetError(f"{where}: stamps not in time order (stamp {i}, {t} ns, is before {t_prev} ns)")


def _check_trajectory(where: str, traj: Trajectory | None) -> None:
    if traj is None:
        return
    poses = traj.poses_xytheta
    bad = ~np.isfinite(poses).all(axis=1) | (np.abs(poses[:, :2]) > MAX_COORDINATE_M).any(axis=1)
    if bad.any():
        i = _first_bad(bad)
        raise DatasetError(
            f"{where}: pose {i} is not finite or beyond {MAX_COORDINATE_M:g} m: {poses[i].tolist()}"
        )
    _check_stamps(where, traj.stamps_ns)
    if traj.covariances_xytheta is not None:
        cov = traj.covariances_xytheta
        bad = ~np.isfinite(cov).all(axis=(1, 2))
        if bad.any():
            raise DatasetError(f"{where}: covariance {_first_bad(bad)} is not finite")


def validate_recording(rec: Recording) -> Recording:
    """``rec`` unchanged if every value SLAM and mapping rely on is finite and ordered; else DatasetError.

    Checked: scan angles finite; range limits finite with 0 <= min < max; stamps in time order with
    |stamp| <= :data:`MAX_STAMP_NS`; odometry, scan poses, reference poses, covariances and the laser's
    mounting finite. Ranges are not checked: any value outside [min, max] (NaN, +-inf,
    negative) is an invalid reading or a no-return by REP 117, and the scan's masks say which.
    """
    src = str(rec.source)
    mount = np.asarray(rec.laser_in_base_xytheta, dtype=np.float64)
    if mount.shape != (3,) or not np.isfinite(mount).all() or (np.abs(mount[:2]) > MAX_COORDINATE_M).any():
        raise DatasetError(f"{src}: the laser's mounting (x, y, theta) is not finite: {mount.tolist()}")
    scans = rec.scans
    if scans is not None and len(scans) > 0:
        angles = np.concatenate(scans.angles_rad)
        if not np.isfinite(angles).all():
            i = _scan_of_beam(scans, _first_bad(~np.isfinite(angles)))
            raise DatasetError(f"{src}: scan {i} has non-finite beam angles (angle_min / angle_increment)")
        lo, hi = scans.range_min_m, scans.range_max_m
        bad = ~np.isfinite(lo) | ~np.isfinite(hi) | (lo < 0) | (hi <= lo)
        if bad.any():
            i = _first_bad(bad)
            raise DatasetError(
                f"{src}: scan {i} has range limits [{lo[i]!r}, {hi[i]!r}] m (need finite, 0 <= min < max)"
            )
        _check_stamps(f"{src}: scans", scans.stamps_ns)
    for name in ("odometry", "scan_poses", "reference"):
        _check_trajectory(f"{src}: {name}", getattr(rec, name))
    if rec.clouds is not None:
        _check_stamps(f"{src}: clouds", rec.clouds.stamps_ns)
    return rec


def _scan_of_beam(scans, beam: int) -> int:
    """Index of the scan holding packed beam ``beam``."""
    return int(np.searchsorted(np.cumsum(scans.beam_counts()), beam, side="right"))
