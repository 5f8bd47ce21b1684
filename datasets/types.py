"""The data model shared by every stage: laser scans, point clouds, trajectories and a recording.

Conventions (SPEC section 2): units and frames are in the names; times are integer nanoseconds
(``stamp_ns``); 2D poses are ``(x_m, y_m, theta_rad)`` rows of ``poses_xytheta`` arrays. Objects are frozen
dataclasses holding numpy arrays; nothing here knows about GPs, graphs or file formats.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from datasets.errors import DatasetError
from datasets.se2 import wrap_angle as wrap_angle_rad  # also imported from here by readers and tests

FloatArray = NDArray[np.float64]


def beam_angles_rad(angle_min_rad: float, angle_increment_rad: float, num_beams: int) -> NDArray[np.float32]:
    """(B,) float32 beam angles ``angle_min + i * angle_increment`` -- THE canonical construction.

    Every reader builds uniform beam angles with this function (parameters rounded to float32 as in a
    ``sensor_msgs/LaserScan``), so angles survive a round trip through a bag bit for bit.
    """
    a0 = np.float64(np.float32(angle_min_rad))
    inc = np.float64(np.float32(angle_increment_rad))
    return (a0 + np.arange(num_beams, dtype=np.float64) * inc).astype(np.float32)


@dataclass(frozen=True)
class LaserScan:
    """One planar laser scan in the laser frame.

    ``ranges_m`` (B,) and ``angles_rad`` (B,) describe the beams. A beam with ``range >= range_max_m``,
    ``+inf`` or ``NaN`` is a *no return* (free space only, SPEC section 2); ranges below ``range_min_m``
    (``-inf`` included) are invalid and dropped by consumers.
    """

    ranges_m: NDArray[np.float32]
    angles_rad: NDArray[np.float32]
    stamp_ns: int
    range_min_m: float
    range_max_m: float
    frame_id: str = "laser"

    @property
    def num_beams(self) -> int:
        return int(self.ranges_m.shape[0])

    def no_return_mask(self) -> NDArray[np.bool_]:
        """(B,) True for beams without a return (>= range_max, +inf or NaN).

        ``-inf`` ("too close", REP 117) is neither a return nor a no-return: it is dropped like a range
        below ``range_min_m``.
        """
        r = self.ranges_m
        with np.errstate(invalid="ignore"):
            return np.isnan(r) | (r >= self.range_max_m)

    def hit_mask(self) -> NDArray[np.bool_]:
        """(B,) True for beams with a valid return (range_min <= r < range_max)."""
        r = self.ranges_m
        with np.errstate(invalid="ignore"):
            return np.isfinite(r) & (r >= self.range_min_m) & (r < self.range_max_m)

    def points_xy_m(self) -> FloatArray:
        """(H, 2) end points of the valid returns in the laser frame."""
        m = self.hit_mask()
        r = self.ranges_m[m].astype(np.float64)
        a = self.angles_rad[m].astype(np.float64)
        return np.stack([r * np.cos(a), r * np.sin(a)], axis=1)


class ScanSequence(Sequence[LaserScan]):
    """Laser scans in time order with random access by index.

    Ranges and angles are held per scan (beam counts may differ between scans or sources). ``sources`` names
    the sensor each scan came from (a topic, or ``"laser"``); ``source_index`` (N,) points into it, so
    recordings of several platforms can carry per-source noise settings.
    """

    def __init__(
        self,
        ranges_m: Sequence[NDArray],
        angles_rad: Sequence[NDArray],
        stamps_ns: NDArray[np.int64] | Sequence[int],
        range_min_m: NDArray | Sequence[float] | float,
        range_max_m: NDArray | Sequence[float] | float,
        frame_ids: Sequence[str] | str = "laser",
        source_index: NDArray[np.int32] | None = None,
        sources: Sequence[str] = ("laser",),
    ) -> None:
        n = len(ranges_m)
        if len(angles_rad) != n or len(stamps_ns) != n:
            raise DatasetError(
                f"scan sequence: {n} range arrays, {len(angles_rad)} angle arrays, {len(stamps_ns)} stamps"
            )
        self._ranges = [np.asarray(r, dtype=np.float32) for r in ranges_m]
        self._angles = [np.asarray(a, dtype=np.float32) for a in angles_rad]
        for i, (r, a) in enumerate(zip(self._ranges, self._angles, strict=True)):
            if r.shape != a.shape or r.ndim != 1:
                raise DatasetError(f"scan {i}: {r.shape} ranges but {a.shape} angles")
        self.stamps_ns = np.asarray(stamps_ns, dtype=np.int64).reshape(n)
        self.range_min_m = np.broadcast_to(np.asarray(range_min_m, dtype=np.float64), (n,)).copy()
        self.range_max_m = np.broadcast_to(np.asarray(range_max_m, dtype=np.float64), (n,)).copy()
        self.frame_ids = [frame_ids] * n if isinstance(frame_ids, str) else list(frame_ids)
        self.source_index = (
            np.zeros(n, dtype=np.int32) if source_index is None else np.asarray(source_index, np.int32)
        )
        self.sources = list(sources)

    def __len__(self) -> int:
        return len(self._ranges)

    def __getitem__(self, index: int) -> LaserScan:  # type: ignore[override]
        if isinstance(index, slice):
            raise TypeError("use ScanSequence.subset(indices) for several scans")
        i = int(index)
        if i < 0:
            i += len(self)
        if not 0 <= i < len(self):
            raise IndexError(index)
        return LaserScan(
            ranges_m=self._ranges[i],
            angles_rad=self._angles[i],
            stamp_ns=int(self.stamps_ns[i]),
            range_min_m=float(self.range_min_m[i]),
            range_max_m=float(self.range_max_m[i]),
            frame_id=self.frame_ids[i],
        )

    def __iter__(self) -> Iterator[LaserScan]:
        for i in range(len(self)):
            yield self[i]

    @property
    def ranges_m(self) -> list[NDArray[np.float32]]:
        """Per-scan range arrays (read-only views by convention)."""
        return self._ranges

    @property
    def angles_rad(self) -> list[NDArray[np.float32]]:
        return self._angles

    def beam_counts(self) -> NDArray[np.int64]:
        return np.array([r.shape[0] for r in self._ranges], dtype=np.int64)

    def subset(self, indices: Sequence[int] | NDArray) -> ScanSequence:
        """A new sequence with the scans at ``indices`` (in that order)."""
        idx = [int(i) for i in indices]
        return ScanSequence(
            [self._ranges[i] for i in idx],
            [self._angles[i] for i in idx],
            self.stamps_ns[idx],
            self.range_min_m[idx],
            self.range_max_m[idx],
            [self.frame_ids[i] for i in idx],
            self.source_index[idx],
            self.sources,
        )

    def packed(self) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """(N, B) ranges and (N, B) angles when every scan has B beams; DatasetError otherwise."""
        counts = self.beam_counts()
        if len(counts) == 0 or np.any(counts != counts[0]):
            raise DatasetError("scans have different beam counts; cannot pack them into one array")
        return np.stack(self._ranges), np.stack(self._angles)


@dataclass(frozen=True)
class Trajectory:
    """Stamped 2D poses: wheel odometry, a SLAM estimate or a reference.

    ``stamps_ns`` (N,) int64, strictly increasing unless ``ordered=False`` was meaningful for the source;
    ``poses_xytheta`` (N, 3) in ``frame_id``. ``covariances_xytheta`` (N, 3, 3) world-frame covariances,
    order (x, y, theta), when known.
    """

    stamps_ns: NDArray[np.int64]
    poses_xytheta: FloatArray
    frame_id: str = "world"
    covariances_xytheta: FloatArray | None = None

    def __post_init__(self) -> None:
        stamps = np.asarray(self.stamps_ns, dtype=np.int64)
        poses = np.asarray(self.poses_xytheta, dtype=np.float64)
        if poses.ndim != 2 or poses.shape[1] != 3 or poses.shape[0] != stamps.shape[0]:
            raise DatasetError(f"trajectory: {stamps.shape[0]} stamps but poses of shape {poses.shape}")
        object.__setattr__(self, "stamps_ns", stamps)
        object.__setattr__(self, "poses_xytheta", poses)
        if self.covariances_xytheta is not None:
            cov = np.asarray(self.covariances_xytheta, dtype=np.float64)
            if cov.shape != (poses.shape[0], 3, 3):
                raise DatasetError(f"trajectory: covariances of shape {cov.shape} for {poses.shape[0]} poses")
            object.__setattr__(self, "covariances_xytheta", cov)

    def __len__(self) -> int:
        return int(self.stamps_ns.shape[0])

    def within_span(self, stamps_ns: NDArray[np.int64]) -> NDArray[np.bool_]:
        """(M,) whether each of ``stamps_ns`` lies within the trajectory's time span, give or take
        :data:`SPAN_SLACK_NS` or half the median period, whichever is longer (beyond, :meth:`interpolate`
        would only repeat an end pose)."""
        t = np.sort(self.stamps_ns)
        if t.shape[0] == 0:
            return np.zeros(np.shape(stamps_ns), dtype=bool)
        slack = SPAN_SLACK_NS
        if t.shape[0] > 1:
            slack = max(slack, int(np.median(np.diff(t))) // 2)
        q = np.asarray(stamps_ns, dtype=np.int64)
        return (q >= t[0] - slack) & (q <= t[-1] + slack)

    def interpolate(self, stamps_ns: NDArray[np.int64]) -> FloatArray:
        """(M, 3) poses at ``stamps_ns``: linear in x, y and in unwrapped theta; clamped at the ends."""
        if len(self) == 0:
            raise DatasetError("cannot interpolate an empty trajectory")
        t0 = self.stamps_ns[0]
        t = (self.stamps_ns - t0).astype(np.float64)  # relative ns: exact in float64 for ~104 days
        q = (np.asarray(stamps_ns, dtype=np.int64) - t0).astype(np.float64)
        theta = np.unwrap(self.poses_xytheta[:, 2])
        out = np.empty((q.shape[0], 3))
        out[:, 0] = np.interp(q, t, self.poses_xytheta[:, 0])
        out[:, 1] = np.interp(q, t, self.poses_xytheta[:, 1])
        out[:, 2] = wrap_angle_rad(np.interp(q, t, theta))
        return out


#: A stamp this close to a trajectory's first or last one still lies within its time span
#: (:meth:`Trajectory.within_span`; at least: half the median period where that is longer).
SPAN_SLACK_NS = 100_000_000


@dataclass(frozen=True)
class PointCloud:
    """One 3D point cloud in the sensor frame: ``points_xyz_m`` (P, 3), optional ``intensity`` (P,)."""

    points_xyz_m: NDArray[np.float32]
    stamp_ns: int
    frame_id: str = "lidar"
    intensity: NDArray[np.float32] | None = None


class CloudSequence(Sequence[PointCloud]):
    """3D clouds in time order, loaded lazily by index through ``load(i) -> PointCloud``."""

    def __init__(self, stamps_ns: NDArray[np.int64], load: Callable[[int], PointCloud]) -> None:
        self.stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
        self._load = load

    def __len__(self) -> int:
        return int(self.stamps_ns.shape[0])

    def __getitem__(self, index: int) -> PointCloud:  # type: ignore[override]
        i = int(index)
        if i < 0:
            i += len(self)
        if not 0 <= i < len(self):
            raise IndexError(index)
        return self._load(i)


@dataclass(frozen=True)
class Recording:
    """What a reader returns: everything a run needs from one input file.

    - ``scans``: planar scans (for 3D inputs, the height band of each cloud turned into a scan);
    - ``odometry``: wheel odometry in its own frame, as recorded (may be denser than the scans);
    - ``scan_poses``: the pose logged with each scan, (len(scans),) stamps matching ``scans`` (CARMEN's
      FLASER pose; raw odometry in a raw log, the corrected pose in a corrected log);
    - ``reference``: reference poses of the robot base at each scan (ground truth of simulated bags,
      corrected poses of ``*.gfs.log`` / ``*-corrected.log*``), same length as ``scans``, or None;
    - ``laser_in_base_xytheta`` (3,): the laser's mounting in the base frame (from tf when present);
    - ``clouds``: 3D clouds for 3D inputs;
    - ``meta``: free-form facts about the source (topics read, message counts, format details).
    """

    source: Path
    format: str
    scans: ScanSequence | None = None
    odometry: Trajectory | None = None
    scan_poses: Trajectory | None = None
    reference: Trajectory | None = None
    laser_in_base_xytheta: FloatArray = field(default_factory=lambda: np.zeros(3))
    clouds: CloudSequence | None = None
    meta: dict = field(default_factory=dict)
