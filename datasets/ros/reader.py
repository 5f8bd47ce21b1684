"""``read_ros1`` / ``read_ros2``: a ROS bag to a :class:`~datasets.types.Recording`.

What is read (stamps are header stamps in integer ns):

- scans: ``sensor_msgs/LaserScan`` (ranges float32 as recorded; angles from
  :func:`~datasets.types.beam_angles_rad`, the canonical construction) or ``sensor_msgs/PointCloud2``
  (a lazy :class:`~datasets.types.CloudSequence` plus one planar scan per cloud from
  :func:`~datasets.cloud.cloud_to_scan`);
- ``odometry``: ``nav_msgs/Odometry`` (x, y, yaw; the (x, y, yaw) block of the pose covariance when it is
  not all zero);
- ``reference``: a ground-truth topic (name contains ``ground_truth``; ``PoseStamped``,
  ``PoseWithCovarianceStamped`` or ``Odometry``) interpolated at the scan stamps;
- ``scan_poses``: the topic ``<scan topic>_pose`` (``PoseStamped``, written by
  :func:`~datasets.ros.writer.write_recording` for a recording's scan poses), at the scan stamps;
- ``laser_in_base_xytheta``: the tf chain (``/tf_static``, then the first ``/tf`` value of each edge) from
  the odometry's child frame (else ``base_link``) to the scan's frame, when present.

Topic choice (:class:`~datasets.config.InputConfig`): an explicit topic must exist with a fitting type;
``None`` auto-detects exactly one candidate (preferring the scan topic's namespace for odometry and ground
truth). ``scan_topic="all"`` reads every LaserScan topic (several platforms, ``ScanSequence.sources`` = the
topic names); then the reference of ``/ns/scan`` comes from ``/ns/...ground_truth...`` or else the single
global ground-truth topic, and per-namespace odometry goes to ``meta["odometry_by_source"]``.
``scan_topic="none"`` reads a bag without scans (e.g. odometry only); by default a bag without a scan topic
is a :class:`~datasets.errors.TopicError` that lists its topics. ``odom_topic="none"`` reads it without
odometry.

Bad input (SPEC section 8) raises one line naming the file: negative ranges, empty scans and header stamps
going backwards within a topic name the topic and the message; so do non-finite beam angles or range limits,
LaserScan fields that disagree (a zero increment, ``angle_min + (n - 1) * angle_increment`` not at
``angle_max`` within :data:`ANGLE_MAX_TOLERANCE_INCREMENTS` increments, a fan wider than a full turn),
non-finite poses or covariances, PointCloud2 layouts that do not fit their data, and tf rotations that are
not unit quaternions (those within :data:`QUATERNION_NORM_TOLERANCE` of unit are normalised).
``inf`` and ``NaN`` ranges are accepted: REP 117 uses them for "no return" (and ``-inf`` for "too close");
a reading at or beyond the message's ``range_max`` is none either. ``meta["no_return"]`` says so (``rule``,
``range_m``: the largest declared ``range_max``), as the CARMEN reader's does.
A topic whose header stamps are all equal (a driver that never sets them: stamp 0) is stamped with the bag's
receive times instead (when those differ), and listed in ``meta["bag_time_topics"]``. Odometry that no
scan lies within (its stamps wholly before or after the scans', or all zero) is an error naming both time
spans; ``meta["scans_outside_odometry"]`` counts, per odometry topic, the scans
outside its span (:meth:`~datasets.types.Trajectory.within_span`).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from datasets.cloud import cloud_to_scan
from datasets.config import InputConfig
from datasets.errors import DatasetError, TopicError, shown, shown_name, shown_names
from datasets.ros.bag import Bag, open_bag
from datasets.ros.typestores import BagKind, stamp_ns_of, yaw_of_quaternion
from datasets.types import (
    CloudSequence,
    PointCloud,
    Recording,
    ScanSequence,
    Trajectory,
    beam_angles_rad,
)

SCAN_TYPE = "sensor_msgs/msg/LaserScan"
CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"
ODOM_TYPE = "nav_msgs/msg/Odometry"
POSE_STAMPED_TYPE = "geometry_msgs/msg/PoseStamped"
POSE_COV_TYPE = "geometry_msgs/msg/PoseWithCovarianceStamped"
REFERENCE_TYPES = (POSE_STAMPED_TYPE, POSE_COV_TYPE, ODOM_TYPE)
TF_TYPE = "tf2_msgs/msg/TFMessage"
SCAN_POSE_SUFFIX = "_pose"  # scan poses of scan topic T are on T + "_pose"

ALL_TOPICS = "all"
NO_SCANS = "none"
NO_ODOMETRY = "none"  # odom_topic "none": read the bag without odometry

#: A tf rotation whose quaternion norm is within this of 1 is normalised; any other is refused.
QUATERNION_NORM_TOLERANCE = 1e-2

#: A LaserScan's ``angle_min + (n - 1) * angle_increment`` may miss its ``angle_max`` by this many increments
#: (drivers differ by one step: n beams over ``angle_max - angle_min`` in n or n - 1 steps) ...
ANGLE_MAX_TOLERANCE_INCREMENTS = 1.5
#: ... plus this many radians (float32 rounding of the three fields).
ANGLE_MAX_TOLERANCE_RAD = 1e-4

# sensor_msgs/PointField datatypes
_POINT_FIELD_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


def read_ros1(path: Path, cfg: InputConfig) -> Recording:
    """Read a ROS1 ``.bag`` (damaged indexes and outdated embedded definitions are handled)."""
    return read_bag(Path(path), cfg, "ros1")


def read_ros2(path: Path, cfg: InputConfig) -> Recording:
    """Read a ROS2 bag: a folder with ``metadata.yaml``, a ``.mcap`` or a ``.db3`` file."""
    return read_bag(Path(path), cfg, "ros2")


def read_bag(path: Path, cfg: InputConfig, kind: BagKind) -> Recording:
    """Read the bag at ``path`` of ``kind`` (see the module docstring)."""
    with open_bag(path, kind) as bag:
        return _BagReading(bag, cfg).recording()


def namespace_of(topic: str) -> str:
    """``/ns/scan`` -> ``/ns``; ``/scan`` -> ``""``."""
    return topic.rsplit("/", 1)[0] if "/" in topic else ""


def _in_namespace(topic: str, ns: str) -> bool:
    return bool(ns) and topic.startswith(ns + "/")


class _BagReading:
    """One reading of one bag: topic choices, then the streams."""

    def __init__(self, bag: Bag, cfg: InputConfig) -> None:
        self.bag = bag
        self.cfg = cfg
        self.path = bag.path
        self.clamped: dict[str, int] = {}  # pose topic -> scans outside its time span (end pose used)
        self.outside_odometry: dict[str, int] = {}  # odometry topic -> scans outside its time span
        self.bag_time_topics: list[str] = []  # topics whose equal header stamps gave way to the bag's times

    # -- topic choice ---------------------------------------------------------------------------------

    def _of_types(self, types: Sequence[str]) -> list[str]:
        return sorted(t.name for t in self.bag.topics.values() if t.msgtype in types)

    def _require(self, topic: str, types: Sequence[str], what: str) -> str:
        info = self.bag.topics.get(topic)
        if info is None:
            raise TopicError(
                f"{self.path}: no {what} topic {shown_name(topic)}; topics: {self.bag.describe_topics()}"
            )
        if info.msgtype not in types:
            raise TopicError(
                f"{self.path}: {what} topic {shown_name(topic)} is {shown_name(info.msgtype)}, "
                f"not {' or '.join(types)}"
            )
        return topic

    def scan_topics(self) -> list[str]:
        want = self.cfg.scan_topic
        if want == NO_SCANS:
            return []
        if want == ALL_TOPICS:
            found = self._of_types([SCAN_TYPE])
            if not found:
                raise TopicError(
                    f"{self.path}: no sensor_msgs/LaserScan topic; topics: {self.bag.describe_topics()}"
                )
            return found
        if want is not None:
            return [self._require(want, (SCAN_TYPE, CLOUD_TYPE), "scan")]
        found = self._of_types([SCAN_TYPE]) or self._of_types([CLOUD_TYPE])
        if len(found) == 1:
            return found
        if not found:
            raise TopicError(
                f"{self.path}: no sensor_msgs/LaserScan or PointCloud2 topic; topics: "
                f"{self.bag.describe_topics()} (scan topic 'none' reads the bag without scans)"
            )
        raise TopicError(
            f"{self.path}: several scan topics ({shown_names(found)}); choose one with --scan-topic "
            "(or 'all' for every LaserScan topic)"
        )

    def _pick(self, candidates: list[str], ns: str, what: str, option: str) -> str | None:
        """Exactly one of ``candidates`` (those in namespace ``ns`` first), None if there is none."""
        if len(candidates) > 1 and ns:
            local = [t for t in candidates if _in_namespace(t, ns)]
            if local:
                candidates = local
        if len(candidates) > 1:
            raise TopicError(
                f"{self.path}: several {what} topics ({shown_names(candidates)}); choose one with {option}"
            )
        return candidates[0] if candidates else None

    def odom_topic(self, ns: str) -> str | None:
        if self.cfg.odom_topic == NO_ODOMETRY:
            return None
        if self.cfg.odom_topic is not None:
            return self._require(self.cfg.odom_topic, (ODOM_TYPE,), "odometry")
        cands = [t for t in self._of_types([ODOM_TYPE]) if "ground_truth" not in t]
        return self._pick(cands, ns, "odometry", "--odom-topic")

    def reference_candidates(self) -> list[str]:
        return [t for t in self._of_types(REFERENCE_TYPES) if "ground_truth" in t]

    def reference_topic(self, ns: str) -> str | None:
        if self.cfg.reference_topic is not None:
            return self._require(self.cfg.reference_topic, REFERENCE_TYPES, "reference")
        return self._pick(self.reference_candidates(), ns, "ground-truth", "input.reference_topic")

    # -- the recording --------------------------------------------------------------------------------

    def recording(self) -> Recording:
        topics = self.scan_topics()
        meta: dict = {
            "bag_kind": self.bag.kind,
            "topics": {t.name: {"type": t.msgtype, "count": t.count} for t in self.bag.topics.values()},
            "scan_topics": topics,
            "notes": self.bag.notes,
        }
        clouds = None
        if not topics:
            scans = None
        elif self.bag.topics[topics[0]].msgtype == CLOUD_TYPE:
            scans, clouds = self._read_clouds(topics[0])
        else:
            scans = self._read_scans(topics)
        if scans is not None:
            meta["no_return"] = self._no_return(scans, clouds is not None)
        multi = len(topics) > 1
        namespaces = [namespace_of(t) for t in topics]

        # odometry
        odometry = None
        if multi and self.cfg.odom_topic is None:
            by_source = {}
            for topic, ns in zip(topics, namespaces, strict=True):
                local = [
                    t for t in self._of_types([ODOM_TYPE]) if _in_namespace(t, ns) and "ground_truth" not in t
                ]
                if len(local) > 1:
                    raise TopicError(
                        f"{self.path}: several odometry topics in {shown_name(ns)} ({shown_names(local)})"
                    )
                if local:
                    by_source[topic] = self._read_poses(local[0])
                    self._check_odometry_span(by_source[topic], local[0], scans, topics.index(topic))
                    meta.setdefault("odom_topics", {})[topic] = local[0]
            glob = [
                t
                for t in self._of_types([ODOM_TYPE])
                if "ground_truth" not in t and not any(_in_namespace(t, ns) for ns in namespaces)
            ]
            odom_topic = self._pick(glob, "", "odometry", "--odom-topic")
            meta["odometry_by_source"] = by_source
        else:
            odom_topic = self.odom_topic(namespaces[0] if namespaces else "")
        if odom_topic is not None:
            odometry = self._read_poses(odom_topic)
            self._check_odometry_span(odometry, odom_topic, scans, None)
        meta["odom_topic"] = odom_topic
        meta["scans_outside_odometry"] = self.outside_odometry

        # reference and scan poses, at the scan stamps
        reference = scan_poses = None
        if scans is not None:
            reference = self._per_scan_reference(scans, topics, namespaces, meta)
            scan_poses = self._per_scan_topic(scans, topics, [t + SCAN_POSE_SUFFIX for t in topics], meta)

        # laser mounting from tf
        laser_in_base = np.zeros(3)
        if scans is not None:
            base = self._base_frame(odom_topic)
            mounts = self._laser_in_base(
                base, [scans.frame_ids[int(np.argmax(scans.source_index == i))] for i in range(len(topics))]
            )
            meta["laser_in_base_by_source"] = dict(zip(topics, mounts, strict=True))
            if mounts[0] is not None:
                laser_in_base = mounts[0]
            meta["base_frame"] = base
        meta["scans_outside_pose_topics"] = self.clamped
        meta["bag_time_topics"] = self.bag_time_topics
        return Recording(
            source=self.path,
            format=self.bag.kind,
            scans=scans,
            odometry=odometry,
            scan_poses=scan_poses,
            reference=reference,
            laser_in_base_xytheta=laser_in_base,
            clouds=clouds,
            meta=meta,
        )

    def _no_return(self, scans: ScanSequence, from_clouds: bool) -> dict:
        """``meta["no_return"]``: how no-return readings are recognised (as the CARMEN reader says it)."""
        if from_clouds:
            rule = "input.cloud_range_max_m (a cloud's bearings without a point are +inf: no return)"
        else:
            rule = "the LaserScan's declared range_max (REP 117: +inf is no return)"
        return {"rule": rule, "range_m": float(np.max(scans.range_max_m))}

    # -- streams --------------------------------------------------------------------------------------

    def _usable_stamps(self, topic: str, header_ns: list[int], bag_ns: list[int]) -> list[int]:
        """``header_ns``, or the bag's receive times ``bag_ns`` (when they differ) if a driver stamped every
        one of a topic's messages alike (unset headers, stamp 0): then the header gives no time at all, and
        odometry interpolated at one instant would hand every scan the same pose. The topic goes to
        ``meta["bag_time_topics"]``."""
        if len(header_ns) < 2 or min(header_ns) != max(header_ns) or min(bag_ns) == max(bag_ns):
            return header_ns
        for i in range(1, len(bag_ns)):
            self._check_order(topic, i, bag_ns[i], bag_ns[i - 1])
        self.bag_time_topics.append(topic)
        return bag_ns

    def _check_order(self, topic: str, i: int, stamp: int, previous: int | None) -> None:
        if previous is not None and stamp < previous:
            raise DatasetError(
                f"{self.path}: topic {shown_name(topic)}: header stamp goes backwards at message {i} "
                f"({stamp} ns after {previous} ns)"
            )

    def _read_scans(self, topics: list[str]) -> ScanSequence:
        ranges: list[NDArray] = []
        angles: list[NDArray] = []
        stamps: list[int] = []
        rmin: list[float] = []
        rmax: list[float] = []
        frames: list[str] = []
        source: list[int] = []
        angle_cache: dict[tuple[float, float, int], NDArray] = {}
        fans_checked: set[tuple[float, float, float, int]] = set()  # (min, max, increment, beams)
        for k, topic in enumerate(topics):
            where = f"{self.path}: topic {shown_name(topic)}"
            previous = None
            topic_stamps: list[int] = []
            bag_times: list[int] = []
            for i, (_, t, msg) in enumerate(self.bag.messages([topic])):
                stamp = stamp_ns_of(msg.header.stamp)
                self._check_order(topic, i, stamp, previous)
                previous = stamp
                r = np.array(msg.ranges, dtype=np.float32)
                if r.size == 0:
                    raise DatasetError(f"{where}: message {i} (stamp {stamp} ns) is an empty scan")
                negative = np.flatnonzero(np.isfinite(r) & (r < 0))
                if negative.size:
                    j = int(negative[0])
                    raise DatasetError(
                        f"{where}: message {i} (stamp {stamp} ns) has {negative.size} "
                        f"negative ranges (beam {j}: {r[j]} m)"
                    )
                key = (float(msg.angle_min), float(msg.angle_increment), int(r.size))
                if key not in angle_cache:
                    with np.errstate(invalid="ignore", over="ignore"):  # checked right below
                        beams = beam_angles_rad(*key)
                    if not np.isfinite(beams).all():
                        raise DatasetError(
                            f"{where}: message {i} (stamp {stamp} ns) has non-finite beam "
                            f"angles (angle_min {key[0]!r}, angle_increment {key[1]!r}, {key[2]} beams)"
                        )
                    angle_cache[key] = beams
                fan = (key[0], float(msg.angle_max), key[1], key[2])
                if fan not in fans_checked:
                    problem = _beam_fan_problem(*fan)
                    if problem:
                        raise DatasetError(f"{where}: message {i} (stamp {stamp} ns) {problem}")
                    fans_checked.add(fan)
                limits = (float(msg.range_min), float(msg.range_max))
                if not (np.isfinite(limits).all() and 0.0 <= limits[0] < limits[1]):
                    raise DatasetError(
                        f"{where}: message {i} (stamp {stamp} ns) has range limits "
                        f"[{limits[0]!r}, {limits[1]!r}] m (need finite, 0 <= range_min < range_max)"
                    )
                ranges.append(r)
                angles.append(angle_cache[key])
                topic_stamps.append(stamp)
                bag_times.append(int(t))
                rmin.append(float(msg.range_min))
                rmax.append(float(msg.range_max))
                frames.append(msg.header.frame_id)
                source.append(k)
            stamps += self._usable_stamps(topic, topic_stamps, bag_times)
        if not ranges:
            raise DatasetError(f"{self.path}: scan topic {shown_names(topics)} holds no messages")
        order = np.argsort(np.asarray(stamps, dtype=np.int64), kind="stable")
        return ScanSequence(
            [ranges[i] for i in order],
            [angles[i] for i in order],
            np.asarray(stamps, dtype=np.int64)[order],
            np.asarray(rmin)[order],
            np.asarray(rmax)[order],
            [frames[i] for i in order],
            np.asarray(source, dtype=np.int32)[order],
            topics,
        )

    def _read_clouds(self, topic: str) -> tuple[ScanSequence, CloudSequence]:
        cfg = self.cfg
        ranges, angles, stamps, frames, bag_times = [], [], [], [], []
        where = f"{self.path}: topic {shown_name(topic)}"
        previous = None
        for i, (_, t, msg) in enumerate(self.bag.messages([topic])):
            stamp = stamp_ns_of(msg.header.stamp)
            self._check_order(topic, i, stamp, previous)
            previous = stamp
            points, _ = cloud_points(msg, f"{where}: message {i}")
            r, a = cloud_to_scan(points, cfg.cloud_height_band_m, cfg.cloud_scan_beams, cfg.cloud_range_max_m)
            ranges.append(r)
            angles.append(a)
            stamps.append(stamp)
            frames.append(msg.header.frame_id)
            bag_times.append(t)
        if not ranges:
            raise DatasetError(f"{self.path}: scan topic {shown_name(topic)} holds no messages")
        stamps = self._usable_stamps(topic, stamps, [int(t) for t in bag_times])
        scans = ScanSequence(ranges, angles, stamps, 0.0, cfg.cloud_range_max_m, frames, sources=[topic])
        loader = _CloudLoader(self.path, self.bag.kind, topic, bag_times)
        return scans, CloudSequence(np.asarray(stamps, dtype=np.int64), loader)

    def _read_poses(self, topic: str) -> Trajectory:
        """A trajectory from an Odometry / PoseStamped / PoseWithCovarianceStamped topic."""
        msgtype = self.bag.topics[topic].msgtype
        where = f"{self.path}: topic {shown_name(topic)}"
        stamps, poses, covs, bag_times = [], [], [], []
        frame = "world"
        previous = None
        for i, (_, t, msg) in enumerate(self.bag.messages([topic])):
            stamp = stamp_ns_of(msg.header.stamp)
            self._check_order(topic, i, stamp, previous)
            previous = stamp
            bag_times.append(int(t))
            frame = msg.header.frame_id
            pose = msg.pose if msgtype == POSE_STAMPED_TYPE else msg.pose.pose
            q = pose.orientation
            xytheta = (float(pose.position.x), float(pose.position.y), yaw_of_quaternion(q.x, q.y, q.z, q.w))
            if not np.isfinite(xytheta).all():
                raise DatasetError(
                    f"{where}: message {i} (stamp {stamp} ns) has a non-finite pose "
                    f"(x {xytheta[0]!r}, y {xytheta[1]!r}, yaw {xytheta[2]!r})"
                )
            stamps.append(stamp)
            poses.append(xytheta)
            if msgtype != POSE_STAMPED_TYPE:
                c = np.asarray(msg.pose.covariance, dtype=np.float64).reshape(6, 6)
                c = c[np.ix_([0, 1, 5], [0, 1, 5])]
                if not np.isfinite(c).all():
                    raise DatasetError(
                        f"{where}: message {i} (stamp {stamp} ns) has a non-finite pose covariance"
                    )
                covs.append(c)
        cov = np.asarray(covs) if covs and np.any(np.asarray(covs)) else None
        stamps = self._usable_stamps(topic, stamps, bag_times)
        return Trajectory(
            np.asarray(stamps, dtype=np.int64), np.asarray(poses, dtype=np.float64).reshape(-1, 3), frame, cov
        )

    def _at_scans(self, traj: Trajectory, stamps: NDArray[np.int64], topic: str) -> NDArray:
        """Poses of ``traj`` at ``stamps``; scans outside its time span get the end pose (counted in meta)."""
        if len(traj) == 0:
            raise DatasetError(f"{self.path}: pose topic {shown_name(topic)} holds no messages")
        outside = int(np.count_nonzero((stamps < traj.stamps_ns[0]) | (stamps > traj.stamps_ns[-1])))
        self.clamped[topic] = outside
        return traj.interpolate(stamps)

    def _check_odometry_span(
        self, odometry: Trajectory, topic: str, scans: ScanSequence | None, source: int | None
    ) -> None:
        """Count the scans (of ``source``, else all) outside the odometry's time span
        (:meth:`~datasets.types.Trajectory.within_span`, as SLAM reads it); refuse odometry no scan lies in.

        Wheel poses are interpolated at the scan stamps downstream; outside the span that would be the end
        pose, so odometry wholly before or after the scans (or with broken header stamps) would silently hand
        every scan the same pose.
        """
        if scans is None or len(scans) == 0 or len(odometry) == 0:
            return
        stamps = scans.stamps_ns if source is None else scans.stamps_ns[scans.source_index == source]
        if stamps.size == 0:
            return
        inside = odometry.within_span(stamps)
        self.outside_odometry[topic] = int(stamps.size - np.count_nonzero(inside))
        if inside.any():
            return
        raise DatasetError(
            f"{self.path}: odometry topic {shown_name(topic)} spans {_span_s(np.sort(odometry.stamps_ns))} "
            "but the scans span "
            f"{_span_s(stamps)}: no scan lies within the odometry's time span; fix the header stamps, or "
            f"pass --odom-topic {NO_ODOMETRY} to read the scans without odometry"
        )

    def _per_scan_reference(
        self, scans: ScanSequence, topics: list[str], namespaces: list[str], meta: dict
    ) -> Trajectory | None:
        if len(topics) == 1 or self.cfg.reference_topic is not None:
            topic = self.reference_topic(namespaces[0])
            meta["reference_topic"] = topic
            if topic is None:
                return None
            traj = self._read_poses(topic)
            return Trajectory(scans.stamps_ns, self._at_scans(traj, scans.stamps_ns, topic), traj.frame_id)
        cands = self.reference_candidates()
        chosen = []
        for ns in namespaces:
            local = [t for t in cands if _in_namespace(t, ns)]
            glob = [t for t in cands if not any(_in_namespace(t, n) for n in namespaces)]
            pick = local or glob
            if len(pick) > 1:
                raise TopicError(
                    f"{self.path}: several ground-truth topics for namespace {shown(ns)} "
                    f"({shown_names(pick)}); choose one with input.reference_topic"
                )
            chosen.append(pick[0] if pick else None)
        meta["reference_topics"] = dict(zip(topics, chosen, strict=True))
        return self._per_scan_topic(scans, topics, chosen, None)

    def _per_scan_topic(
        self, scans: ScanSequence, topics: list[str], pose_topics: list[str | None], meta: dict | None
    ) -> Trajectory | None:
        """Poses at every scan stamp from one pose topic per source; None unless every source has one."""
        present = [t if t is not None and t in self.bag.topics else None for t in pose_topics]
        if any(t is None for t in present):
            return None
        poses = np.empty((len(scans), 3))
        frame = "world"
        for k, topic in enumerate(present):
            traj = self._read_poses(topic)
            frame = traj.frame_id
            sel = scans.source_index == k
            poses[sel] = self._at_scans(traj, scans.stamps_ns[sel], topic)
        if meta is not None:
            meta["scan_pose_topics"] = present
        return Trajectory(scans.stamps_ns, poses, frame)

    # -- tf -------------------------------------------------------------------------------------------

    def _base_frame(self, odom_topic: str | None) -> str:
        if odom_topic is not None:
            for _, _, msg in self.bag.messages([odom_topic]):
                if msg.child_frame_id:
                    return msg.child_frame_id.strip("/")
                break
        return "base_link"

    def _laser_in_base(self, base: str, laser_frames: list[str]) -> list[NDArray | None]:
        """(3,) x, y, yaw of each laser frame in ``base`` through tf, or None without a chain.

        A transform that :func:`_transform_matrix` refuses (a zero, NaN or non-unit rotation) is an error only
        when the chain to a laser needs it; on ``/tf`` a later valid value of the same edge is used instead.
        """
        edges: dict[tuple[str, str], NDArray] = {}
        refused: dict[tuple[str, str], str] = {}  # edge -> the error, raised if a chain needs the edge
        for name in ("/tf_static", "/tf"):
            if name not in self.bag.topics or self.bag.topics[name].msgtype != TF_TYPE:
                continue
            static = name == "/tf_static"
            for i, (_, _, msg) in enumerate(self.bag.messages([name])):
                for tr in msg.transforms:
                    key = (tr.header.frame_id.strip("/"), tr.child_frame_id.strip("/"))
                    if key in edges and not static:
                        continue
                    where = (
                        f"{self.path}: topic {name}: message {i}: transform "
                        f"{shown_name(key[0])} -> {shown_name(key[1])}"
                    )
                    try:
                        edges[key] = _transform_matrix(tr.transform, where)
                        refused.pop(key, None)
                    except DatasetError as exc:
                        edges.pop(key, None)
                        if static or key not in refused:
                            refused[key] = str(exc)
        out: list[NDArray | None] = []
        for laser in laser_frames:
            m = _chain(edges, base, laser.strip("/"))
            if m is None:
                for key, error in refused.items():
                    if _chain({**edges, key: np.eye(4)}, base, laser.strip("/")) is not None:
                        raise DatasetError(error)
            out.append(None if m is None else np.array([m[0, 3], m[1, 3], np.arctan2(m[1, 0], m[0, 0])]))
        return out


def _span_s(stamps_ns: NDArray[np.int64]) -> str:
    """``[first, last] s`` of sorted stamps (seconds, 3 decimals) and the length, for an error message."""
    a, b = int(stamps_ns[0]), int(stamps_ns[-1])
    return f"[{a / 1e9:.3f}, {b / 1e9:.3f}] s ({(b - a) / 1e9:.3f} s)"


def _beam_fan_problem(angle_min: float, angle_max: float, angle_increment: float, beams: int) -> str | None:
    """What is wrong with a LaserScan's beam fan (a phrase for an error message), or None when it is sound.

    ``angle_min`` and ``angle_increment`` (already known to give finite angles) build the beams; they must
    agree with ``angle_max``: ``angle_min + (beams - 1) * angle_increment`` within
    :data:`ANGLE_MAX_TOLERANCE_INCREMENTS` increments plus :data:`ANGLE_MAX_TOLERANCE_RAD` of it (so a zero,
    vanishing or wrongly signed increment, or ranges of another length than the fan, are refused), and the
    fan may be at most one increment wider than a full turn. Reversed scans (``angle_min > angle_max``, a
    negative increment) are sound. One beam has no fan: only its ``angle_min`` counts.
    """
    if beams < 2:
        return None
    fields = (
        f"(angle_min {angle_min!r}, angle_max {angle_max!r}, angle_increment {angle_increment!r}, "
        f"{beams} beams)"
    )
    if not np.isfinite(angle_max):
        return f"has a non-finite angle_max {fields}"
    inc = float(np.float32(angle_increment))
    if inc == 0.0:
        return f"has a zero angle_increment {fields}"
    a0, a1 = float(np.float32(angle_min)), float(np.float32(angle_max))
    end = a0 + (beams - 1) * inc
    if abs(end - a1) > ANGLE_MAX_TOLERANCE_INCREMENTS * abs(inc) + ANGLE_MAX_TOLERANCE_RAD:
        return (
            f"has beam angles that do not end at angle_max: angle_min + {beams - 1} * angle_increment = "
            f"{end:.6g} rad, angle_max {a1:.6g} rad {fields}"
        )
    if abs(end - a0) > 2.0 * np.pi + abs(inc) + ANGLE_MAX_TOLERANCE_RAD:
        return f"has a beam fan of {abs(end - a0):.6g} rad, more than a full turn {fields}"
    return None


def _transform_matrix(tf: object, where: str) -> NDArray:
    """4x4 homogeneous matrix of a ``geometry_msgs/Transform``.

    The rotation is normalised when its norm is within :data:`QUATERNION_NORM_TOLERANCE` of 1 (float32
    rounding, sloppy publishers); a zero, non-finite or far from unit quaternion, or a non-finite
    translation, is a :class:`~datasets.errors.DatasetError` (``where`` names the file, topic and frames).
    """
    t, q = tf.translation, tf.rotation  # type: ignore[attr-defined]
    quat = np.array([q.x, q.y, q.z, q.w], dtype=np.float64)
    trans = np.array([t.x, t.y, t.z], dtype=np.float64)
    with np.errstate(over="ignore"):
        norm = float(np.linalg.norm(quat)) if np.isfinite(quat).all() else float("nan")
    if not abs(norm - 1.0) <= QUATERNION_NORM_TOLERANCE:
        raise DatasetError(
            f"{where}: rotation quaternion (x, y, z, w) = {quat.tolist()} is not a unit quaternion "
            f"(norm {norm:.6g})"
        )
    if not np.isfinite(trans).all():
        raise DatasetError(f"{where}: translation {trans.tolist()} is not finite")
    x, y, z, w = quat / norm
    m = np.eye(4)
    m[:3, :3] = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    m[:3, 3] = trans
    return m


def _rigid_inverse(m: NDArray) -> NDArray:
    """Inverse of a 4x4 rigid transform (rotation transposed; never singular)."""
    inv = np.eye(4)
    inv[:3, :3] = m[:3, :3].T
    inv[:3, 3] = -m[:3, :3].T @ m[:3, 3]
    return inv


def _chain(edges: dict[tuple[str, str], NDArray], start: str, goal: str) -> NDArray | None:
    """Pose of ``goal`` in ``start`` through the tf tree (edges used in either direction), breadth first."""
    if start == goal:
        return np.eye(4)
    neighbours: dict[str, list[tuple[str, NDArray]]] = {}
    for (parent, child), m in edges.items():
        neighbours.setdefault(parent, []).append((child, m))
        neighbours.setdefault(child, []).append((parent, _rigid_inverse(m)))
    frontier = [(start, np.eye(4))]
    seen = {start}
    while frontier:
        nxt = []
        for frame, pose in frontier:
            for other, m in neighbours.get(frame, []):
                if other in seen:
                    continue
                if other == goal:
                    return pose @ m
                seen.add(other)
                nxt.append((other, pose @ m))
        frontier = nxt
    return None


def cloud_points(msg: object, where: str) -> tuple[NDArray[np.float32], NDArray[np.float32] | None]:
    """(P, 3) finite x, y, z of a ``sensor_msgs/PointCloud2`` and (P,) intensity if it has one.

    The fields' offsets, datatypes and the endianness come from the message; rows may be padded
    (``row_step > width * point_step``). Vectorised through a numpy structured dtype.
    """
    fields = {f.name: f for f in msg.fields}  # type: ignore[attr-defined]
    missing = [n for n in ("x", "y", "z") if n not in fields]
    if missing:
        raise DatasetError(f"{where}: point cloud without field(s) {shown_names(missing)}")
    endian = ">" if msg.is_bigendian else "<"  # type: ignore[attr-defined]
    names = ["x", "y", "z"] + (["intensity"] if "intensity" in fields else [])
    formats, offsets = [], []
    step = int(msg.point_step)  # type: ignore[attr-defined]
    width, height, row_step = int(msg.width), int(msg.height), int(msg.row_step)  # type: ignore[attr-defined]
    for n in names:
        f = fields[n]
        if f.datatype not in _POINT_FIELD_TYPES:
            raise DatasetError(f"{where}: field {n} has unknown datatype {f.datatype}")
        formats.append(endian + _POINT_FIELD_TYPES[f.datatype])
        offsets.append(int(f.offset))
        end = offsets[-1] + np.dtype(formats[-1]).itemsize
        if end > step:
            raise DatasetError(
                f"{where}: field {n} (offset {offsets[-1]}, {end - offsets[-1]} bytes) does not fit in "
                f"point_step {step}"
            )
    data = np.asarray(msg.data, dtype=np.uint8)  # type: ignore[attr-defined]
    if step * width > row_step or data.size < row_step * height:
        raise DatasetError(
            f"{where}: point cloud data of {data.size} bytes does not hold {height} rows of {width} points "
            f"(point_step {step}, row_step {row_step})"
        )
    if width == 0 or height == 0:  # no points (and point_step is then bounded by nothing: no dtype from it)
        return np.zeros((0, 3), np.float32), (np.zeros(0, np.float32) if "intensity" in names else None)
    # here point_step <= row_step <= the data's size: the dtype's size comes from the data, not a field alone
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": step})
    rows = data[: row_step * height].reshape(height, row_step)[:, : step * width]
    arr = np.ascontiguousarray(rows).view(dtype).reshape(-1)
    pts = np.stack([arr["x"], arr["y"], arr["z"]], axis=1).astype(np.float32)
    keep = np.isfinite(pts).all(axis=1)
    intensity = arr["intensity"].astype(np.float32)[keep] if "intensity" in names else None
    return pts[keep], intensity


class _CloudLoader:
    """Loads cloud ``i`` from the bag on demand (the bag is reopened; clouds are never all in memory)."""

    def __init__(self, path: Path, kind: BagKind, topic: str, bag_times_ns: list[int]) -> None:
        self.path, self.kind, self.topic = path, kind, topic
        self.bag_times = np.asarray(bag_times_ns, dtype=np.int64)

    def __call__(self, i: int) -> PointCloud:
        t = int(self.bag_times[i])
        ordinal = i - int(np.searchsorted(self.bag_times, t, side="left"))
        with open_bag(self.path, self.kind) as bag:
            for k, (_, _, msg) in enumerate(bag.messages([self.topic], start=t, stop=t + 1)):
                if k == ordinal:
                    pts, intensity = cloud_points(
                        msg, f"{self.path}: topic {shown_name(self.topic)}: cloud {i}"
                    )
                    return PointCloud(pts, stamp_ns_of(msg.header.stamp), msg.header.frame_id, intensity)
        raise DatasetError(f"{self.path}: topic {shown_name(self.topic)}: cloud {i} is gone from the bag")
