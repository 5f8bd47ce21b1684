"""Writing bags: a :class:`~datasets.types.Recording`, or arbitrary messages, into a new ROS1 / ROS2 bag.

The output kind follows the path (:func:`bag_kind_of_path`):

=====================  ======================================================================================
path                   writes
=====================  ======================================================================================
``out.bag``            a ROS1 bag (v2.0, uncompressed chunks)
``out.mcap``           ONE ROS2 MCAP file (rosbag2 version 9 metadata embedded). ``rosbags`` writes a ROS2
                       bag as a folder ``out.mcap/out.mcap.mcap`` + ``metadata.yaml``; a user asking for
                       ``out.mcap`` expects a file, which ``ros2 bag info/play out.mcap`` (Iron and later),
                       Foxglove and :func:`~datasets.open_dataset` all read. So the folder is written in a
                       temporary place and only its ``.mcap`` file is kept.
``out.db3``            one ROS2 SQLite3 file, the same way
``out`` (no suffix)    a ROS2 bag folder (``metadata.yaml`` + ``out.mcap``)
=====================  ======================================================================================

Every output is written under a hidden temporary name beside the target (``.out.bag.partial-*``) and
renamed when complete, so a failed or interrupted write leaves nothing that looks complete; an existing
output is never overwritten.

A recording is written as (scan topic ``T`` = ``/scan``, or each source's name with several sources):

- ``T``: ``sensor_msgs/LaserScan``; ``angle_min`` / ``angle_increment`` are the float32 pair that reproduces
  the scan's angles bit for bit through :func:`~datasets.types.beam_angles_rad` (:func:`angle_parameters`);
- ``/odom``: ``nav_msgs/Odometry`` (child frame ``base_link``; the (x, y, yaw) covariance if known);
  ``meta["odometry_by_source"]`` goes to ``<ns>/odom``;
- ``/ground_truth/pose`` (or ``<ns>/ground_truth/pose`` per source): ``geometry_msgs/PoseStamped``;
- ``T_pose`` (e.g. ``/scan_pose``): ``geometry_msgs/PoseStamped``, the recording's ``scan_poses`` -- the pose
  logged with each scan (CARMEN's FLASER pose), which is not the odometry stream;
- ``/tf_static``: ``base_link`` -> laser frame, from ``laser_in_base_xytheta``.
"""

from __future__ import annotations

import os
import shutil
import sqlite3
import tempfile
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from rosbags import rosbag1, rosbag2
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin
from rosbags.serde import SerdeError

from datasets.errors import DatasetError, UnknownFormatError, first_line, shown, shown_name, shown_names
from datasets.progress import stage
from datasets.ros.mcap_stream import streaming_storage, write_streamed
from datasets.ros.reader import SCAN_POSE_SUFFIX, namespace_of
from datasets.ros.typestores import BagKind, header_msg, pose_msg, standard_typestore, time_msg
from datasets.types import Recording, Trajectory

ANGLE_SEARCH_ULPS = 64  # float32 neighbours of the angle_increment estimate tried on each side
SENTINEL_BASE = 0x7FA5C3E1  # bit pattern (a float32 NaN) that marks where an array's elements go in a message
MARK_BYTES = 8  # the least length of such a mark
# ROS2 QoS of a latched topic (/tf_static): reliable, transient local, keep last 1; default durations.
LATCHED_QOS = Qos(
    QosHistory.KEEP_LAST,
    1,
    QosReliability.RELIABLE,
    QosDurability.TRANSIENT_LOCAL,
    QosTime(0, 0),
    QosTime(0, 0),
    QosLiveliness.AUTOMATIC,
    QosTime(0, 0),
    False,
)


def bag_kind_of_path(path: Path) -> tuple[BagKind, str]:
    """``(kind, layout)`` of an output path: ``("ros1", "bag")``, ``("ros2", "mcap" | "db3" | "folder")``."""
    suffix = Path(path).suffix.lower()
    if suffix == ".bag":
        return "ros1", "bag"
    if suffix in (".mcap", ".db3"):
        return "ros2", suffix[1:]
    if suffix == "":
        return "ros2", "folder"
    raise UnknownFormatError(
        f"{path}: unknown bag format '{suffix}' "
        "(write a ROS1 .bag, a ROS2 .mcap / .db3, or a folder without suffix)"
    )


def check_output_path(path: Path) -> tuple[BagKind, str]:
    """Refuse an existing output, a missing parent folder or one that cannot be written into (one line);
    returns :func:`bag_kind_of_path`."""
    path = Path(path)
    kind = bag_kind_of_path(path)
    if path.exists() or path.is_symlink():
        raise DatasetError(f"{path}: exists already; not overwriting it (remove it or choose another name)")
    if not path.parent.is_dir():
        raise DatasetError(f"{path}: the folder {path.parent} does not exist")
    try:  # a real probe: permissions, read-only file systems and ACLs all count
        with tempfile.TemporaryFile(dir=path.parent, prefix=".gpom-write-probe-"):
            pass
    except OSError as exc:
        raise DatasetError(f"{path}: cannot write into {path.parent} ({exc.strerror or exc})") from None
    return kind


@dataclass(frozen=True)
class StreamedArray:
    """A 1-D numeric array of a message given in consecutive pieces, so that a big message's arrays need not
    exist whole (e.g. a map layer flipped band by band): ``size`` elements of ``dtype``; ``pieces()``
    yields 1-D contiguous arrays of that dtype whose concatenation is the array."""

    dtype: np.dtype
    size: int
    pieces: Callable[[], Iterator[NDArray]]

    @classmethod
    def of(cls, values: NDArray) -> StreamedArray:
        """An array that exists already, flattened (C order) as one piece."""
        flat = np.ascontiguousarray(values).reshape(-1)
        return cls(flat.dtype, flat.size, lambda: iter([flat]))

    def whole(self) -> NDArray:
        """The array in one piece."""
        out = np.empty(self.size, self.dtype)
        at = 0
        for piece in self.pieces():
            out[at : at + piece.size] = piece
            at += piece.size
        return out


class BagWriter:
    """Writes messages into an open bag; get one from :func:`open_bag_writer`.

    Messages are objects of ``writer.types[msgtype]`` (e.g. ``writer.types["nav_msgs/msg/OccupancyGrid"]``);
    :meth:`header` and :meth:`time` build the parts that differ between ROS1 and ROS2.
    """

    def __init__(self, kind: BagKind, raw: Any, path: Path) -> None:
        self.kind = kind
        self.path = path
        self.typestore = standard_typestore(kind)
        self.types = self.typestore.types
        self.counts: dict[str, int] = {}
        self._raw = raw
        self._conns: dict[tuple[str, str], Any] = {}

    def header(self, stamp_ns: int, frame_id: str, seq: int = 0) -> object:
        """A ``std_msgs/Header`` of this bag's ROS version."""
        return header_msg(self.typestore, self.kind, stamp_ns, frame_id, seq)

    def time(self, stamp_ns: int) -> object:
        return time_msg(self.typestore, stamp_ns)

    def write(self, topic: str, msgtype: str, stamp_ns: int, msg: object, latching: bool = False) -> None:
        """Append ``msg`` of ``msgtype`` (e.g. ``sensor_msgs/msg/LaserScan``) on ``topic`` at ``stamp_ns``.

        ``latching`` marks the topic latched (ROS1 ``latching=1``, ROS2 transient-local QoS), for
        ``/tf_static`` and maps. It is taken from the first message of a topic.
        """
        self._write_bytes(topic, msgtype, stamp_ns, self._serialise(topic, msgtype, msg), latching)

    def write_built(
        self, topic: str, msgtype: str, stamp_ns: int, build: Callable[[], object], latching: bool = False
    ) -> None:
        """:meth:`write` of the message ``build()`` returns, dropped once serialised: a big message's arrays
        (a building's map layers) and the bag's copies of its bytes are not held at the same time."""
        self._write_bytes(topic, msgtype, stamp_ns, self._serialise(topic, msgtype, build()), latching)

    def write_arrays_streamed(
        self,
        topic: str,
        msgtype: str,
        stamp_ns: int,
        build: Callable[[Sequence[NDArray]], object],
        arrays: Sequence[StreamedArray],
        latching: bool = False,
    ) -> None:
        """:meth:`write` of ``build(data)``, the message whose big array fields are ``arrays`` (in the order
        they are serialised), without holding it whole where the bag allows.

        An MCAP bag gets the message piece by piece (:mod:`datasets.ros.mcap_stream`): ``build`` is called
        with short stand-ins for the arrays to find their places in the serialised message
        (:meth:`_array_layout`), and the pieces go between. Any other bag, or a message whose layout moves
        with the arrays' lengths (an 8-byte field after an array of 4-byte elements), gets ``build`` of the
        whole arrays."""
        layout = None
        if self.kind == "ros2" and streaming_storage(self._raw) is not None:
            layout = self._array_layout(topic, msgtype, build, arrays)
        if layout is None:
            self.write_built(topic, msgtype, stamp_ns, lambda: build([a.whole() for a in arrays]), latching)
            return

        def pieces() -> Iterator[bytes | NDArray]:
            for between, array in zip(layout, arrays, strict=False):
                yield between
                yield int(array.size).to_bytes(4, "little")
                for piece in array.pieces():
                    yield np.ascontiguousarray(piece, array.dtype).reshape(-1)
            yield layout[-1]

        size = sum(len(b) for b in layout) + sum(4 + a.size * np.dtype(a.dtype).itemsize for a in arrays)
        conn = self._connection(topic, msgtype, latching)
        write_streamed(self._raw, conn, int(stamp_ns), pieces(), size)
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def _array_layout(
        self,
        topic: str,
        msgtype: str,
        build: Callable[[Sequence[NDArray]], object],
        arrays: Sequence[StreamedArray],
    ) -> list[bytes] | None:
        """The serialised message's bytes between the arrays (len(arrays) + 1 parts: before the first
        array's length field, between one array's last element and the next one's length field, after the
        last), or None when the stand-ins cannot be found or the layout depends on the arrays' lengths.

        Each array's stand-in is a distinct pattern of at least 8 bytes (a NaN's bits for float32); the
        message is serialised with each stand-in and again with one element more, which must shift what
        follows by exactly one element (no alignment padding that depends on the length)."""
        marks = []
        for i, a in enumerate(arrays):
            dtype = np.dtype(a.dtype)
            pattern = ((SENTINEL_BASE + i) % 2**32).to_bytes(4, "little") * (2 + dtype.itemsize // 4)
            count = max(1, MARK_BYTES // dtype.itemsize)
            marks.append(np.frombuffer(pattern[: count * dtype.itemsize], dtype))
        once = bytes(self._serialise(topic, msgtype, build([m.copy() for m in marks])))
        longer = bytes(self._serialise(topic, msgtype, build([np.concatenate([m, m[:1]]) for m in marks])))
        parts: list[bytes] = []
        at = 0
        expected = b""
        for m in marks:
            mark = m.tobytes()
            found = once.find(mark, at)
            length = m.size.to_bytes(4, "little")
            if found < at + 4 or once.count(mark) != 1 or once[found - 4 : found] != length:
                return None
            parts.append(once[at : found - 4])
            expected += parts[-1] + (m.size + 1).to_bytes(4, "little") + mark + m[:1].tobytes()
            at = found + len(mark)
        parts.append(once[at:])
        if expected + parts[-1] != longer:
            return None
        return parts

    def _serialise(self, topic: str, msgtype: str, msg: object) -> bytes | memoryview:
        if msgtype not in self.types:
            raise DatasetError(
                f"{self.path}: unknown message type {shown_name(msgtype)} for topic {shown_name(topic)}"
            )
        try:
            if self.kind == "ros1":
                return self.typestore.serialize_ros1(msg, msgtype)
            return self.typestore.serialize_cdr(msg, msgtype)
        except (SerdeError, TypeError, ValueError, AttributeError, KeyError) as exc:
            raise DatasetError(
                f"{self.path}: a {shown_name(msgtype)} message for {shown_name(topic)} cannot be serialised "
                f"({first_line(exc)})"
            ) from None

    def _write_bytes(
        self, topic: str, msgtype: str, stamp_ns: int, data: bytes | memoryview, latching: bool
    ) -> None:
        self._raw.write(self._connection(topic, msgtype, latching), int(stamp_ns), data)
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def _connection(self, topic: str, msgtype: str, latching: bool) -> Any:
        """The bag's connection of ``topic`` with ``msgtype``, added on first use."""
        key = (topic, msgtype)
        conn = self._conns.get(key)
        if conn is None:
            if self.kind == "ros1":
                conn = self._raw.add_connection(
                    topic, msgtype, typestore=self.typestore, latching=1 if latching else None
                )
            else:
                qos = [LATCHED_QOS] if latching else []
                conn = self._raw.add_connection(
                    topic, msgtype, typestore=self.typestore, offered_qos_profiles=qos
                )
            self._conns[key] = conn
        return conn


@contextmanager
def open_bag_writer(path: str | Path, compress: bool = False) -> Iterator[BagWriter]:
    """A :class:`BagWriter` on a new bag at ``path`` (kind from the suffix, see the module docstring).

    ``compress``: compress the bag's chunks the way every reader of its format decompresses by itself, for
    big payloads such as float map layers: an MCAP file or folder gets zstd chunks (MCAP's own chunk
    compression, not rosbag2's file or message compression, so ``metadata.yaml`` declares none), a ROS1 bag
    lz4 chunks; a SQLite3 bag has no chunks and stays uncompressed. The bag appears at ``path`` only when
    the ``with`` block ends without an exception.
    """
    path = Path(path)
    kind, layout = check_output_path(path)
    tmpdir = Path(tempfile.mkdtemp(prefix=f".{path.name}.partial-", dir=path.parent))
    try:
        if kind == "ros1":
            inner = tmpdir / path.name
            raw: Any = rosbag1.Writer(inner)
            if compress:
                raw.set_compression(rosbag1.Writer.CompressionFormat.LZ4)
            produced = inner
        else:
            stem = path.name if layout == "folder" else path.stem
            inner = tmpdir / stem
            plugin = StoragePlugin.SQLITE3 if layout == "db3" else StoragePlugin.MCAP
            raw = rosbag2.Writer(inner, version=rosbag2.Writer.VERSION_LATEST, storage_plugin=plugin)
            if compress and plugin == StoragePlugin.MCAP:
                raw.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
            produced = inner if layout == "folder" else inner / f"{stem}.{layout}"
        with raw:
            writer = BagWriter(kind, raw, path)
            yield writer
        if path.exists():
            raise DatasetError(f"{path}: appeared while writing; not overwriting it")
        os.replace(produced, path)
    except (rosbag1.WriterError, rosbag2.WriterError, OSError, sqlite3.Error) as exc:
        # sqlite3.Error: a .db3 bag's storage ("database or disk is full"; over a file-size limit "disk I/O
        # error")
        raise DatasetError(f"{path}: cannot write the bag ({first_line(exc)})") from None
    finally:
        shutil.rmtree(tmpdir, ignore_errors=True)


def write_messages(
    path: str | Path,
    messages: Iterable[tuple[str, str, int, object]],
    progress: Any = None,
    total: int | None = None,
) -> dict[str, int]:
    """Write ``(topic, msgtype, stamp_ns, message)`` tuples into a new bag; returns messages per topic.

    Build messages with the classes of ``standard_typestore(kind).types`` (kind from
    :func:`bag_kind_of_path`), or use :func:`open_bag_writer` for its ``header`` / ``time`` helpers.
    """
    with open_bag_writer(path) as writer:
        if progress is None:
            for topic, msgtype, stamp_ns, msg in messages:
                writer.write(topic, msgtype, stamp_ns, msg)
        else:
            with progress.stage("write bag", total=total) as bar:
                for topic, msgtype, stamp_ns, msg in messages:
                    writer.write(topic, msgtype, stamp_ns, msg)
                    bar.advance()
        return dict(writer.counts)


# -- LaserScan angles -----------------------------------------------------------------------------------


def angle_parameters(angles_rad: NDArray) -> tuple[float, float]:
    """float32 ``(angle_min, angle_increment)`` giving ``angles_rad`` exactly through ``beam_angles_rad``.

    ``angle_min`` is ``angles[0]`` (exact by construction); the increment is the float32 estimate
    ``(a[-1] - a[0]) / (n - 1)`` or the nearest of its float32 neighbours (up to
    :data:`ANGLE_SEARCH_ULPS` on each side) that reproduces every angle. DatasetError if none does
    (non-uniform angles cannot be a ``sensor_msgs/LaserScan``).
    """
    a = np.asarray(angles_rad, dtype=np.float32)
    n = a.size
    if n == 0:
        raise DatasetError("a scan without beams cannot be written")
    a0 = np.float32(a[0])
    if n == 1:
        return float(a0), 0.0
    est = np.float32((float(a[-1]) - float(a[0])) / (n - 1))
    cands = [est]
    up = down = est
    for _ in range(ANGLE_SEARCH_ULPS):
        up, down = np.nextafter(up, np.float32(np.inf)), np.nextafter(down, np.float32(-np.inf))
        cands += [up, down]
    idx = np.arange(n, dtype=np.float64)
    base = np.float64(a0)
    for start in range(0, len(cands), 16):
        block = np.asarray(cands[start : start + 16], dtype=np.float32).astype(np.float64)
        grid = (base + idx[None, :] * block[:, None]).astype(np.float32)
        ok = np.flatnonzero((grid == a[None, :]).all(axis=1))
        if ok.size:
            return float(a0), float(np.float32(block[ok[0]]))
    raise DatasetError(
        f"beam angles are not angle_min + i * angle_increment for any float32 increment near "
        f"{float(est):.9g} (within {ANGLE_SEARCH_ULPS} ulps); a sensor_msgs/LaserScan cannot hold them"
    )


# -- recordings -----------------------------------------------------------------------------------------


def _source_topics(recording: Recording, scan_topic: str) -> list[str]:
    scans = recording.scans
    if scans is None:
        return []
    if len(scans.sources) <= 1:
        return [scan_topic]
    topics = [s if s.startswith("/") else f"/{s}/scan" for s in scans.sources]
    if len(set(topics)) != len(topics):
        raise DatasetError(
            f"{recording.source}: scan sources {shown(scans.sources)} do not map to distinct topics"
        )
    return topics


def _pose_stamped(w: BagWriter, stamp_ns: int, frame: str, pose: NDArray, seq: int) -> object:
    return w.types["geometry_msgs/msg/PoseStamped"](
        header=w.header(stamp_ns, frame, seq), pose=pose_msg(w.typestore, *pose)
    )


def _odometry_msg(w: BagWriter, traj: Trajectory, i: int, child: str) -> object:
    cov = np.zeros((6, 6))
    if traj.covariances_xytheta is not None:
        cov[np.ix_([0, 1, 5], [0, 1, 5])] = traj.covariances_xytheta[i]
    t = w.types
    pose = t["geometry_msgs/msg/PoseWithCovariance"](
        pose=pose_msg(w.typestore, *traj.poses_xytheta[i]), covariance=cov.reshape(36)
    )
    zero = t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
    twist = t["geometry_msgs/msg/TwistWithCovariance"](
        twist=t["geometry_msgs/msg/Twist"](linear=zero, angular=zero), covariance=np.zeros(36)
    )
    return t["nav_msgs/msg/Odometry"](
        header=w.header(int(traj.stamps_ns[i]), traj.frame_id, i),
        child_frame_id=child,
        pose=pose,
        twist=twist,
    )


def _transform_stamped(w: BagWriter, stamp_ns: int, parent: str, child: str, xytheta: NDArray) -> object:
    t = w.types
    x, y, yaw = (float(v) for v in xytheta)
    tf = t["geometry_msgs/msg/Transform"](
        translation=t["geometry_msgs/msg/Vector3"](x=x, y=y, z=0.0),
        rotation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=np.sin(0.5 * yaw), w=np.cos(0.5 * yaw)),
    )
    return t["geometry_msgs/msg/TransformStamped"](
        header=w.header(stamp_ns, parent), child_frame_id=child, transform=tf
    )


def write_recording(
    recording: Recording,
    path: str | Path,
    progress: Any = None,
    scan_topic: str = "/scan",
    odom_topic: str = "/odom",
    reference_topic: str = "/ground_truth/pose",
    base_frame: str = "base_link",
) -> dict[str, int]:
    """Write ``recording`` into a new bag at ``path`` (layout in the module docstring); messages per topic.

    The scan angles are checked first (:func:`angle_parameters`), so a recording that cannot be written
    fails before anything is created.
    """
    path = Path(path)
    check_output_path(path)
    scans = recording.scans
    topics = _source_topics(recording, scan_topic)
    angle_params: list[tuple[float, float]] = []
    if scans is not None:
        by_array: dict[int, tuple[float, float]] = {}
        for i, angles in enumerate(scans.angles_rad):
            key = id(angles)
            if key not in by_array:
                try:
                    by_array[key] = angle_parameters(angles)
                except DatasetError as exc:
                    raise DatasetError(f"{recording.source}: scan {i}: {exc}") from None
            angle_params.append(by_array[key])
    if scans is None and recording.odometry is None and recording.reference is None:
        raise DatasetError(f"{recording.source}: nothing to write (no scans, odometry or reference poses)")

    multi = len(topics) > 1
    odom_by_source: dict[str, Trajectory] = recording.meta.get("odometry_by_source") or {}
    mounts: dict = recording.meta.get("laser_in_base_by_source") or {}
    total = (len(scans) if scans is not None else 0) * (
        1 + (recording.reference is not None) + (recording.scan_poses is not None)
    )
    total += len(recording.odometry) if recording.odometry is not None else 0
    total += sum(len(t) for t in odom_by_source.values())

    with open_bag_writer(path) as w, stage(progress, "write bag", total) as bar:
        if scans is not None:
            stamp0 = int(scans.stamps_ns[0])
            tfs = []
            for k in range(len(topics)):
                first = int(np.argmax(scans.source_index == k))
                mount = mounts.get(scans.sources[k]) if multi else None
                mount = recording.laser_in_base_xytheta if mount is None else mount
                tfs.append(
                    _transform_stamped(w, stamp0, base_frame, scans.frame_ids[first].strip("/"), mount)
                )
            w.write(
                "/tf_static",
                "tf2_msgs/msg/TFMessage",
                stamp0,
                w.types["tf2_msgs/msg/TFMessage"](transforms=tfs),
                latching=True,
            )
            laser = w.types["sensor_msgs/msg/LaserScan"]
            empty = np.zeros(0, dtype=np.float32)
            for i in range(len(scans)):
                stamp = int(scans.stamps_ns[i])
                ranges = scans.ranges_m[i]
                a_min, a_inc = angle_params[i]
                msg = laser(
                    header=w.header(stamp, scans.frame_ids[i], i),
                    angle_min=a_min,
                    angle_max=float(scans.angles_rad[i][-1]),
                    angle_increment=a_inc,
                    time_increment=0.0,
                    scan_time=0.0,
                    range_min=float(scans.range_min_m[i]),
                    range_max=float(scans.range_max_m[i]),
                    ranges=np.ascontiguousarray(ranges, dtype=np.float32),
                    intensities=empty,
                )
                w.write(topics[scans.source_index[i]], "sensor_msgs/msg/LaserScan", stamp, msg)
                bar.advance()
            for traj, suffix_topics in (
                (
                    recording.reference,
                    [reference_topic]
                    if not multi
                    else [f"{namespace_of(t)}/ground_truth/pose" for t in topics],
                ),
                (recording.scan_poses, [t + SCAN_POSE_SUFFIX for t in topics]),
            ):
                if traj is None:
                    continue
                if multi and traj is recording.reference and len(set(suffix_topics)) != len(suffix_topics):
                    raise DatasetError(
                        f"{recording.source}: scan topics {shown_names(topics)} share a namespace; "
                        "per-source reference topics would collide"
                    )
                if len(traj) != len(scans):
                    raise DatasetError(
                        f"{recording.source}: {len(traj)} per-scan poses for {len(scans)} scans"
                    )
                for i in range(len(scans)):
                    stamp = int(traj.stamps_ns[i])
                    topic = suffix_topics[scans.source_index[i]]
                    w.write(
                        topic,
                        "geometry_msgs/msg/PoseStamped",
                        stamp,
                        _pose_stamped(w, stamp, traj.frame_id, traj.poses_xytheta[i], i),
                    )
                    bar.advance()
        elif recording.reference is not None:
            traj = recording.reference
            for i in range(len(traj)):
                stamp = int(traj.stamps_ns[i])
                w.write(
                    reference_topic,
                    "geometry_msgs/msg/PoseStamped",
                    stamp,
                    _pose_stamped(w, stamp, traj.frame_id, traj.poses_xytheta[i], i),
                )
        odoms = [(odom_topic, recording.odometry)] if recording.odometry is not None else []
        for source, traj in odom_by_source.items():
            odoms.append(
                (f"{namespace_of(source if source.startswith('/') else '/' + source + '/scan')}/odom", traj)
            )
        for topic, traj in odoms:
            for i in range(len(traj)):
                w.write(
                    topic,
                    "nav_msgs/msg/Odometry",
                    int(traj.stamps_ns[i]),
                    _odometry_msg(w, traj, i, base_frame),
                )
                bar.advance()
        return dict(w.counts)
