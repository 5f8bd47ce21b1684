"""Bad ROS1 / ROS2 input: every defect a user's file can trigger is one DatasetError line.

Each test writes a small valid bag with rosbags' own writers in ``tmp_path``, damages it in one precise way
and checks the error. The bag builders here are shared with the fuzzing harness
(``tests/fuzz/test_fuzz_ros.py``).
"""

from __future__ import annotations

import re
import sqlite3
import struct
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags import rosbag1, rosbag2
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin

from datasets import open_dataset
from datasets.errors import DatasetError
from datasets.ros.typestores import BagKind, header_msg, pose_msg, standard_typestore
from tests.conftest import REPO

T0 = 1_600_000_000_000_000_000
STEP_NS = 100_000_000
SCAN_BEAMS = 11

Message = tuple[str, str, int, Any]  # topic, msgtype, bag time (ns), message object (or raw bytes)


# -- building small valid bags -----------------------------------------------------------------------------


def _vector3(types: Any, x: float = 0.0, y: float = 0.0, z: float = 0.0) -> Any:
    return types["geometry_msgs/msg/Vector3"](x=x, y=y, z=z)


def tf_static_msg(kind: BagKind, quat: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)) -> Message:
    """``/tf_static``: base_link -> laser, 0.1 m ahead, rotated by ``quat`` (x, y, z, w)."""
    st = standard_typestore(kind)
    t = st.types
    rot = t["geometry_msgs/msg/Quaternion"](x=quat[0], y=quat[1], z=quat[2], w=quat[3])
    tr = t["geometry_msgs/msg/TransformStamped"](
        header=header_msg(st, kind, T0, "base_link"),
        child_frame_id="laser",
        transform=t["geometry_msgs/msg/Transform"](translation=_vector3(t, 0.1), rotation=rot),
    )
    return "/tf_static", "tf2_msgs/msg/TFMessage", T0, t["tf2_msgs/msg/TFMessage"](transforms=[tr])


def scan_msg(
    kind: BagKind,
    stamp_ns: int,
    angle_min: float = -0.5,
    angle_increment: float = 0.1,
    range_min: float = 0.0,
    range_max: float = 10.0,
    ranges: np.ndarray | None = None,
) -> Message:
    """``/scan``: a sensor_msgs/LaserScan of :data:`SCAN_BEAMS` beams."""
    st = standard_typestore(kind)
    r = np.linspace(1.0, 2.0, SCAN_BEAMS).astype(np.float32) if ranges is None else ranges
    msg = st.types["sensor_msgs/msg/LaserScan"](
        header=header_msg(st, kind, stamp_ns, "laser"),
        angle_min=angle_min,
        angle_max=float(np.clip(angle_min + angle_increment * (len(r) - 1), -3e38, 3e38)),
        angle_increment=angle_increment,
        time_increment=0.0,
        scan_time=0.0,
        range_min=range_min,
        range_max=range_max,
        ranges=r,
        intensities=np.zeros(0, np.float32),
    )
    return "/scan", "sensor_msgs/msg/LaserScan", stamp_ns, msg


def odom_msg(kind: BagKind, stamp_ns: int, x: float = 0.0, y: float = 0.0, yaw: float = 0.0) -> Message:
    """``/odom``: a nav_msgs/Odometry (child frame base_link, zero covariance)."""
    st = standard_typestore(kind)
    t = st.types
    cov = np.zeros(36)
    twist = t["geometry_msgs/msg/Twist"](linear=_vector3(t), angular=_vector3(t))
    msg = t["nav_msgs/msg/Odometry"](
        header=header_msg(st, kind, stamp_ns, "odom"),
        child_frame_id="base_link",
        pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose_msg(st, x, y, yaw), covariance=cov),
        twist=t["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=cov),
    )
    return "/odom", "nav_msgs/msg/Odometry", stamp_ns, msg


def cloud_msg(
    kind: BagKind,
    stamp_ns: int,
    points: np.ndarray | None = None,
    point_step: int | None = None,
    width: int | None = None,
    height: int = 1,
    row_step: int | None = None,
    data: bytes | None = None,
) -> Message:
    """``/points``: a sensor_msgs/PointCloud2 of float32 x, y, z; any layout field can be overridden."""
    st = standard_typestore(kind)
    t = st.types
    pts = (
        np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 0.1], [-3.0, 0.0, -0.1]], np.float32)
        if points is None
        else points
    )
    raw = pts.astype("<f4").tobytes() if data is None else data
    pf = t["sensor_msgs/msg/PointField"]
    fields = [pf(name=n, offset=4 * k, datatype=7, count=1) for k, n in enumerate("xyz")]
    w = len(pts) if width is None else width
    step = 12 if point_step is None else point_step
    msg = t["sensor_msgs/msg/PointCloud2"](
        header=header_msg(st, kind, stamp_ns, "lidar"),
        height=height,
        width=w,
        fields=fields,
        is_bigendian=False,
        point_step=step,
        row_step=step * w if row_step is None else row_step,
        data=np.frombuffer(raw, np.uint8),
        is_dense=False,
    )
    return "/points", "sensor_msgs/msg/PointCloud2", stamp_ns, msg


def standard_messages(kind: BagKind, n: int = 3, clouds: bool = False) -> list[Message]:
    """A valid recording: ``/tf_static``, then ``n`` scans (or clouds) and ``n`` odometry messages."""
    out = [tf_static_msg(kind)]
    for i in range(n):
        t = T0 + i * STEP_NS
        out.append(cloud_msg(kind, t) if clouds else scan_msg(kind, t))
        out.append(odom_msg(kind, t + 1, x=0.1 * i))
    return out


def serialize(kind: BagKind, msgtype: str, msg: Any) -> bytes:
    """ROS1 or CDR bytes of ``msg`` (raw bytes pass through unchanged)."""
    if isinstance(msg, bytes | bytearray | memoryview):
        return bytes(msg)
    st = standard_typestore(kind)
    return bytes(st.serialize_ros1(msg, msgtype) if kind == "ros1" else st.serialize_cdr(msg, msgtype))


def write_ros1(path: Path, messages: list[Message], compression: str | None = None) -> Path:
    """A ROS1 bag at ``path`` (``compression``: None, ``"bz2"`` or ``"lz4"`` chunks)."""
    st = standard_typestore("ros1")
    writer = rosbag1.Writer(path)
    if compression:
        writer.set_compression(getattr(rosbag1.Writer.CompressionFormat, compression.upper()))
    conns: dict[str, Any] = {}
    with writer:
        for topic, msgtype, stamp, msg in messages:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=st)
            writer.write(conns[topic], stamp, serialize("ros1", msgtype, msg))
    return path


def write_ros2(
    folder: Path, messages: list[Message], storage: str = "mcap", compression: str | None = None
) -> Path:
    """A ROS2 bag folder at ``folder`` (``storage``: ``"mcap"`` or ``"sqlite3"``; ``compression``: None or
    rosbags' zstd compression mode ``"file"``, ``"message"`` or, for MCAP, ``"storage"`` (zstd chunks))."""
    st = standard_typestore("ros2")
    plugin = StoragePlugin.SQLITE3 if storage == "sqlite3" else StoragePlugin.MCAP
    writer = rosbag2.Writer(folder, version=rosbag2.Writer.VERSION_LATEST, storage_plugin=plugin)
    if compression:
        mode = getattr(CompressionMode, compression.upper())
        writer.set_compression(mode, CompressionFormat.ZSTD)
    conns: dict[str, Any] = {}
    with writer:
        for topic, msgtype, stamp, msg in messages:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=st)
            writer.write(conns[topic], stamp, serialize("ros2", msgtype, msg))
    return folder


def storage_file(folder: Path) -> Path:
    """The single ``.mcap`` / ``.db3`` file of a ROS2 bag folder (readable on its own), or its ``.zstd``
    file when the bag is compressed by file."""
    (found,) = [p for p in folder.iterdir() if p.suffix in (".mcap", ".db3", ".zstd")]
    return found


def declare_compression(folder: Path, mode: str, fmt: str = "zstd") -> Path:
    """Rewrite the ``compression_mode`` / ``compression_format`` of the folder's metadata.yaml (the data
    stays as written): ``mode`` ``FILE``, ``MESSAGE`` or ``""`` (none)."""
    meta = folder / "metadata.yaml"
    text = meta.read_text()
    text, n_fmt = re.subn(r"(?m)^(\s*compression_format:).*$", rf"\1 '{fmt}'", text)
    text, n_mode = re.subn(r"(?m)^(\s*compression_mode:).*$", rf"\1 '{mode}'", text)
    assert n_fmt == n_mode == 1, text
    meta.write_text(text)
    return folder


def write_bag(layout: str, where: Path, messages: Callable[[BagKind], list[Message]]) -> Path:
    """A bag of ``layout`` (``bag``, ``bag-bz2``, ``bag-lz4``, ``folder``, ``folder-db3``, ``mcap``, ``db3``)
    in the folder ``where``, holding ``messages(kind)``; returns the path to give to ``open_dataset``."""
    if layout.startswith("bag"):
        compression = layout.split("-")[1] if "-" in layout else None
        return write_ros1(where / "b.bag", messages("ros1"), compression)
    storage = "sqlite3" if "db3" in layout else "mcap"
    folder = write_ros2(where / "b2", messages("ros2"), storage)
    return folder if layout.startswith("folder") else storage_file(folder)


# -- ROS1 record surgery -----------------------------------------------------------------------------------

ROS1_MAGIC = b"#ROSBAG V2.0\n"


def ros1_records(data: bytes, start: int = len(ROS1_MAGIC), end: int | None = None) -> list[dict[str, Any]]:
    """The records of a ROS1 bag from ``start`` (the top level by default; a chunk's data for its inner
    records): ``pos``, ``fields`` (name -> (value pos, value bytes)), ``data_pos``, ``data_len``."""
    pos, out = start, []
    end = len(data) if end is None else end
    while pos + 4 <= end:
        (hlen,) = struct.unpack_from("<I", data, pos)
        fields, fpos = {}, pos + 4
        while fpos < pos + 4 + hlen:
            (flen,) = struct.unpack_from("<I", data, fpos)
            name, _, value = data[fpos + 4 : fpos + 4 + flen].partition(b"=")
            fields[name.decode("latin-1")] = (fpos + 4 + len(name) + 1, value)
            fpos += 4 + flen
        dpos = pos + 4 + hlen
        (dlen,) = struct.unpack_from("<I", data, dpos)
        out.append({"pos": pos, "fields": fields, "data_pos": dpos + 4, "data_len": dlen})
        pos = dpos + 4 + dlen
    return out


def _op(record: dict[str, Any]) -> int:
    return record["fields"]["op"][1][0]


def _conn_ids(records: list[dict[str, Any]]) -> dict[str, int]:
    """topic -> connection id, from the connection records of the index section."""
    return {
        r["fields"]["topic"][1].decode(): struct.unpack("<I", r["fields"]["conn"][1])[0]
        for r in records
        if _op(r) == 7
    }


def _expect_error(path: Path, *parts: str) -> str:
    with pytest.raises(DatasetError) as err:
        open_dataset(path)
    message = str(err.value)
    assert "\n" not in message and message.startswith(f"{path}: "), message
    for part in parts:
        assert part in message, message
    return message


# -- ROS1 --------------------------------------------------------------------------------------------------


def test_ros1_damaged_index_never_decodes_another_topic(tmp_path: Path) -> None:
    """Index records of /scan and /odom swapped: /scan's index points at Odometry records."""
    path = write_ros1(tmp_path / "swap.bag", standard_messages("ros1"))
    data = bytearray(path.read_bytes())
    records = ros1_records(bytes(data))
    ids = _conn_ids(records)
    index = {struct.unpack("<I", r["fields"]["conn"][1])[0]: r for r in records if _op(r) == 4}
    scan_at = index[ids["/scan"]]["fields"]["conn"][0]
    odom_at = index[ids["/odom"]]["fields"]["conn"][0]
    data[scan_at : scan_at + 4] = struct.pack("<I", ids["/odom"])
    data[odom_at : odom_at + 4] = struct.pack("<I", ids["/scan"])
    path.write_bytes(data)
    _expect_error(path, "corrupt bag index", "topic /odom", "under /scan")


def test_ros1_corrupt_connection_record_reports_the_real_error(tmp_path: Path) -> None:
    """A connection record whose field length overruns it: the scanner's error, not a BufferError."""
    path = write_ros1(tmp_path / "conn.bag", standard_messages("ros1"))
    data = bytearray(path.read_bytes())
    conn = next(r for r in ros1_records(bytes(data)) if _op(r) == 7)
    data[conn["data_pos"] : conn["data_pos"] + 4] = struct.pack("<I", 0x7FFFFFFF)
    path.write_bytes(data)
    _expect_error(path, "corrupt ROS1 bag", f"index connection at byte {conn['pos']}", "overruns")


def test_ros1_huge_record_length_with_little_memory(tmp_path: Path) -> None:
    """A chunk header length of 4 GiB, read with the address space limited to 2 GiB: no MemoryError, as no
    reader allocates what the damaged length asks for (rosbags' strict reader would; it is not given the
    file)."""
    resource = pytest.importorskip("resource")
    path = write_ros1(tmp_path / "huge.bag", standard_messages("ros1"))
    data = bytearray(path.read_bytes())
    chunk = next(r for r in ros1_records(bytes(data)) if _op(r) == 5)
    data[chunk["pos"] : chunk["pos"] + 4] = struct.pack("<I", 0xFFFFFFF0)
    path.write_bytes(data)
    limit = 2 << 30
    script = (
        "import resource, sys\n"
        f"resource.setrlimit(resource.RLIMIT_AS, ({limit}, {limit}))\n"
        "from datasets import open_dataset\n"
        "from datasets.errors import DatasetError\n"
        "try:\n"
        "    open_dataset(sys.argv[1])\n"
        "except DatasetError as err:\n"
        "    print('DatasetError:', err)\n"
    )
    assert resource.RLIMIT_AS is not None
    done = subprocess.run(
        [sys.executable, "-c", script, str(path)], cwd=REPO, capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.startswith(f"DatasetError: {path}: corrupt ROS1 bag (record at byte {chunk['pos']}")
    overrun = f"strict reader: record at byte {chunk['pos']}: its header of 4294967280 bytes runs past"
    assert overrun in done.stdout


@pytest.mark.parametrize("compression", ["bz2", "lz4"])
def test_ros1_chunk_decompressing_beyond_its_declared_size(tmp_path: Path, compression: str) -> None:
    """A compressed chunk whose header declares fewer bytes than it holds is refused, never inflated."""
    path = write_ros1(tmp_path / "c.bag", standard_messages("ros1"), compression)
    data = bytearray(path.read_bytes())
    chunk = next(r for r in ros1_records(bytes(data)) if _op(r) == 5)
    at = chunk["fields"]["size"][0]
    data[at : at + 4] = struct.pack("<I", 16)
    # the strict reader too must fail: break the first index data record's count
    idx = next(r for r in ros1_records(bytes(data)) if _op(r) == 4)
    at = idx["fields"]["count"][0]
    data[at : at + 4] = struct.pack("<I", 0x7FFFFFFF)
    path.write_bytes(data)
    _expect_error(path, "corrupt ROS1 bag", "decompresses to more than the 16 bytes")


@pytest.mark.parametrize(
    ("value", "shown"),
    [(b"\nz\x00", r"'\nz\x00'"), (b"\xff\xfe\x1b", r"b'\xff\xfe\x1b'"), (b"zst", "'zst'")],
    ids=["newline-nul", "not-utf8", "unknown"],
)
def test_ros1_chunk_compression_field_is_quoted_escaped(tmp_path: Path, value: bytes, shown: str) -> None:
    """A chunk's ``compression`` field holding control bytes: the message quoted them raw (two lines, a NUL);
    it now shows them escaped, from both the chunk scanner and rosbags' strict reader."""
    path = write_ros1(tmp_path / "c.bag", standard_messages("ros1"), "bz2")
    data = bytearray(path.read_bytes())
    chunk = next(r for r in ros1_records(bytes(data)) if _op(r) == 5)
    at, old = chunk["fields"]["compression"]
    assert old == b"bz2" and len(value) == len(old)
    data[at : at + len(value)] = value
    path.write_bytes(data)
    message = _expect_error(path, "corrupt ROS1 bag", f"unsupported compression {shown}")
    assert message.isprintable(), message


# -- MCAP and ROS 2 ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("length", [1 << 40, 1 << 63])
def test_mcap_huge_record_length(tmp_path: Path, length: int) -> None:
    """The MCAP header record's u64 length set to 2^40 (MemoryError) or 2^63 (OverflowError)."""
    path = storage_file(write_ros2(tmp_path / "m", standard_messages("ros2")))
    data = bytearray(path.read_bytes())
    assert data[:8] == b"\x89MCAP0\r\n" and data[8] == 0x01  # magic, then the header record
    data[9:17] = struct.pack("<Q", length)
    path.write_bytes(data)
    _expect_error(path, "corrupt or unreadable ROS2 bag")


@pytest.mark.parametrize(
    ("old", "new", "expected"),
    [
        ("name: /scan", "name: {}", "a topic name is {}, not a string"),
        ("nanoseconds: 200000001", "nanoseconds: abc", "corrupt or unreadable ROS2 bag"),
        ("message_count: 3", "message_count: [1]", "has message count [1]"),
        ("type: sensor_msgs/msg/LaserScan", "type: 7", "has message type 7"),
        (
            "type_description_hash: \n        RIHS01_64c1",
            'type_description_hash: "\\n0"\n      x: RIHS01_64c1',
            "topic /scan has type hash '\\n0'",
        ),
    ],
    ids=["name-dict", "nanoseconds-abc", "count-list", "type-int", "hash-newline"],
)
def test_metadata_yaml_with_wrong_types(tmp_path: Path, old: str, new: str, expected: str) -> None:
    folder = write_ros2(tmp_path / "y", standard_messages("ros2"))
    meta = folder / "metadata.yaml"
    text = meta.read_text()
    assert old in text
    meta.write_text(text.replace(old, new, 1))
    _expect_error(folder, expected)


def test_db3_with_a_null_topic_name(tmp_path: Path) -> None:
    path = storage_file(write_ros2(tmp_path / "n", standard_messages("ros2"), "sqlite3"))
    db = sqlite3.connect(path)
    db.execute("PRAGMA writable_schema = ON")
    db.execute(
        "UPDATE sqlite_master SET sql = replace(sql, 'name TEXT NOT NULL', 'name TEXT') WHERE name = 'topics'"
    )
    db.commit()
    db.close()
    db = sqlite3.connect(path)
    db.execute("UPDATE topics SET name = NULL WHERE name = '/odom'")
    db.commit()
    db.close()
    _expect_error(path, "a topic name is None, not a string")


def test_db3_with_a_corrupt_page(tmp_path: Path) -> None:
    """The messages table's b-tree page damaged: SQLite's CorruptError while reading becomes one line."""
    path = storage_file(write_ros2(tmp_path / "p", standard_messages("ros2"), "sqlite3"))
    db = sqlite3.connect(path)
    (root,) = db.execute("SELECT rootpage FROM sqlite_master WHERE name = 'messages'").fetchone()
    (page,) = db.execute("PRAGMA page_size").fetchone()
    db.close()
    data = bytearray(path.read_bytes())
    start = (root - 1) * page
    data[start + 4 : start + 8] = struct.pack("<I", 0xFFFFFFF0)  # cell count and cell content offset
    path.write_bytes(data)
    _expect_error(path, "corrupt bag, reading messages failed (database disk image is malformed)")


# -- ROS 2 compression: what metadata.yaml declares against what the files hold ---------------------------


@pytest.mark.parametrize(
    ("storage", "mode"),
    [("mcap", "file"), ("mcap", "message"), ("mcap", "storage"), ("sqlite3", "file"), ("sqlite3", "message")],
)
def test_ros2_zstd_compressed_bags_read(tmp_path: Path, storage: str, mode: str) -> None:
    """Bags compressed by rosbags' writer (per file, per message, MCAP zstd chunks) read completely."""
    folder = write_ros2(tmp_path / "z", standard_messages("ros2"), storage, compression=mode)
    rec = open_dataset(folder)
    assert rec.scans is not None and len(rec.scans) == 3 and len(rec.odometry) == 3


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
@pytest.mark.parametrize("mode", ["FILE", "MESSAGE"])
def test_ros2_declared_zstd_but_stored_plain(tmp_path: Path, storage: str, mode: str) -> None:
    """metadata.yaml says zstd, the storage file is not: was backports.zstd.ZstdError from rosbags
    (``reader.open()`` for FILE, the message loop for MESSAGE)."""
    folder = declare_compression(write_ros2(tmp_path / "z", standard_messages("ros2"), storage), mode)
    hint = (
        "declare a zstd compression_mode message that" if mode == "MESSAGE" else "declare a zstd compression"
    )
    _expect_error(folder, "corrupt ROS2 bag: zstd-compressed data does not decompress", hint)


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
@pytest.mark.parametrize(("written", "declared"), [("file", "MESSAGE"), ("message", "FILE"), ("message", "")])
def test_ros2_compression_mode_other_than_written(
    tmp_path: Path, storage: str, written: str, declared: str
) -> None:
    """Compressed one way, declared another (or not at all): one DatasetError line, whichever layer fails."""
    folder = write_ros2(tmp_path / "z", standard_messages("ros2"), storage, compression=written)
    _expect_error(declare_compression(folder, declared))


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_ros2_truncated_zstd_file(tmp_path: Path, storage: str) -> None:
    """A file-compressed bag whose .zstd file is cut in half."""
    folder = write_ros2(tmp_path / "z", standard_messages("ros2"), storage, compression="file")
    data = storage_file(folder)
    data.write_bytes(data.read_bytes()[: data.stat().st_size // 2])
    _expect_error(folder)


def test_mcap_damaged_zstd_chunk(tmp_path: Path) -> None:
    """A single .mcap file with zstd chunks, one byte of a chunk's compressed data flipped."""
    path = storage_file(write_ros2(tmp_path / "z", standard_messages("ros2"), "mcap", compression="storage"))
    data = bytearray(path.read_bytes())
    pos = 8
    while data[pos] != 0x06:  # the first chunk record
        pos += 9 + struct.unpack_from("<Q", data, pos + 1)[0]
    (length,) = struct.unpack_from("<Q", data, pos + 1)
    compressed_end = pos + 9 + length
    data[compressed_end - 20] ^= 0xFF
    path.write_bytes(data)
    _expect_error(path)


# -- non-finite and impossible values ----------------------------------------------------------------------


def _with(kind: BagKind, replace: dict[int, Message], n: int = 3) -> list[Message]:
    msgs = standard_messages(kind, n)
    for i, m in replace.items():
        msgs[i] = m
    return msgs


@pytest.mark.parametrize("layout", ["bag", "mcap"])
def test_nan_odometry_pose_names_topic_and_message(tmp_path: Path, layout: str) -> None:
    # message 4 of the list is the second /odom message
    path = write_bag(layout, tmp_path, lambda k: _with(k, {4: odom_msg(k, T0 + STEP_NS + 1, x=float("nan"))}))
    _expect_error(path, "topic /odom: message 1", "non-finite pose (x nan")


@pytest.mark.parametrize("layout", ["bag", "mcap"])
def test_nan_odometry_orientation_names_topic_and_message(tmp_path: Path, layout: str) -> None:
    def messages(kind: BagKind) -> list[Message]:
        topic, msgtype, stamp, msg = odom_msg(kind, T0 + 1)
        msg.pose.pose.orientation.w = float("nan")
        return _with(kind, {2: (topic, msgtype, stamp, msg)})

    _expect_error(write_bag(layout, tmp_path, messages), "topic /odom: message 0", "yaw nan")


@pytest.mark.parametrize(
    ("fields", "expected"),
    [
        ({"angle_increment": float("nan")}, "non-finite beam angles (angle_min -0.5, angle_increment nan"),
        ({"angle_min": float("inf")}, "non-finite beam angles (angle_min inf"),
        ({"angle_increment": 3e38}, "non-finite beam angles"),
        ({"range_max": float("nan")}, "range limits [0.0, nan] m"),
        ({"range_min": 5.0, "range_max": 1.0}, "range limits [5.0, 1.0] m"),
    ],
)
def test_non_finite_scan_parameters_name_topic_and_message(
    tmp_path: Path, fields: dict[str, float], expected: str
) -> None:
    path = write_bag("bag", tmp_path, lambda k: _with(k, {3: scan_msg(k, T0 + STEP_NS, **fields)}))
    _expect_error(path, "topic /scan: message 1", expected)


@pytest.mark.parametrize("layout", ["bag", "mcap"])
def test_near_unit_tf_quaternion_is_normalised(tmp_path: Path, layout: str) -> None:
    half = 0.3
    q = 1.004 * np.array([0.0, 0.0, np.sin(half), np.cos(half)])
    path = write_bag(layout, tmp_path, lambda k: _with(k, {0: tf_static_msg(k, tuple(q))}))
    rec = open_dataset(path)
    np.testing.assert_allclose(rec.laser_in_base_xytheta, [0.1, 0.0, 2 * half], atol=1e-12)


@pytest.mark.parametrize(
    "quat",
    [(0.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0, float("nan")), (0.5, 0.5, 0.0, 0.0), (0.0, 0.0, 0.0, 2.0)],
    ids=["zero", "nan", "singular", "norm-2"],
)
def test_bad_tf_quaternion_is_refused(tmp_path: Path, quat: tuple[float, float, float, float]) -> None:
    path = write_bag("bag", tmp_path, lambda k: _with(k, {0: tf_static_msg(k, quat)}))
    _expect_error(path, "topic /tf_static: message 0: transform base_link -> laser", "not a unit quaternion")


@pytest.mark.parametrize(
    ("layout", "expected"),
    [
        ({"point_step": 8}, "field z (offset 8, 4 bytes) does not fit in point_step 8"),
        ({"point_step": 0, "row_step": 0}, "does not fit in point_step 0"),
        ({"data": b"\0" * 35}, "does not hold 1 rows of 3 points"),
        ({"width": 5}, "does not hold 1 rows of 5 points"),
        ({"width": 3, "height": 2}, "does not hold 2 rows of 3 points"),
        ({"row_step": 20}, "does not hold 1 rows of 3 points"),
        ({"width": 0x7FFFFFFF, "height": 0x7FFFFFFF, "row_step": 0xFFFFFFFF}, "does not hold"),
    ],
)
def test_inconsistent_point_cloud_layout(tmp_path: Path, layout: dict[str, Any], expected: str) -> None:
    def messages(kind: BagKind) -> list[Message]:
        msgs = standard_messages(kind, clouds=True)
        msgs[3] = cloud_msg(kind, T0 + STEP_NS, **layout)
        return msgs

    _expect_error(write_bag("mcap", tmp_path, messages), "topic /points: message 1", expected)


def _patch_u32(raw: bytes, at: int, value: int) -> bytes:
    return raw[:at] + struct.pack("<I", value) + raw[at + 4 :]


@pytest.mark.parametrize("layout", ["bag", "mcap"])
@pytest.mark.parametrize("length", [1 << 31, 0xFFFFFFFF])
def test_huge_array_length_inside_a_message(tmp_path: Path, layout: str, length: int) -> None:
    """A LaserScan whose ranges length field says 2^31 (or 2^32 - 1) beams: refused, never allocated."""

    def messages(kind: BagKind) -> list[Message]:
        topic, msgtype, stamp, msg = scan_msg(kind, T0 + STEP_NS)
        raw = serialize(kind, msgtype, msg)
        # ... ranges length (u32), SCAN_BEAMS float32, intensities length (u32) = 0
        at = len(raw) - 4 - 4 * SCAN_BEAMS - 4
        assert struct.unpack_from("<I", raw, at)[0] == SCAN_BEAMS
        return _with(kind, {3: (topic, msgtype, stamp, _patch_u32(raw, at, length))})

    _expect_error(write_bag(layout, tmp_path, messages), "topic /scan: a message cannot be decoded")


def test_point_cloud_without_points_ignores_a_huge_point_step(tmp_path: Path) -> None:
    """width 0 and point_step 2^31: no points (the layout is never turned into a 2 GiB numpy dtype)."""

    def messages(kind: BagKind) -> list[Message]:
        msgs = standard_messages(kind, clouds=True)
        msgs[3] = cloud_msg(kind, T0 + STEP_NS, point_step=1 << 31, width=0, row_step=0, data=b"")
        return msgs

    rec = open_dataset(write_bag("bag", tmp_path, messages))
    assert len(rec.scans) == 3 and np.isposinf(rec.scans[1].ranges_m).all()
    assert len(rec.clouds[1].points_xyz_m) == 0


def test_bad_tf_quaternion_off_the_laser_chain_is_ignored(tmp_path: Path) -> None:
    """A zero rotation on base_link -> camera does not concern the laser: the recording reads."""

    def messages(kind: BagKind) -> list[Message]:
        msgs = standard_messages(kind)
        camera = tf_static_msg(kind, (0.0, 0.0, 0.0, 0.0))[3].transforms[0]
        camera.child_frame_id = "camera"
        msgs[0][3].transforms.append(camera)
        return msgs

    rec = open_dataset(write_bag("bag", tmp_path, messages))
    np.testing.assert_allclose(rec.laser_in_base_xytheta, [0.1, 0.0, 0.0], atol=1e-12)
