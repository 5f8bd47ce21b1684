"""Fuzzing the ROS1 / ROS2 readers: a damaged bag gives a valid recording or one DatasetError line, no crash.

Seed bags (LaserScan, Odometry, tf_static; PointCloud2 in the ``cloud`` seeds) are written once per module
with rosbags' own writers: ROS1 plain, bz2 and lz4 chunks; ROS2 MCAP and SQLite3, as single files and as
folders, plain or zstd-compressed (by file, by message, MCAP zstd chunks). The properties then damage them
(byte flips, truncations, length fields set to huge values; metadata.yaml values of the wrong type, YAML
tags, dates and 5000-digit numbers; a declared compression mode and format other than the files'; control
and non-UTF-8 bytes in every text field of ROS1 record headers and connections, of MCAP records and of the
SQLite topics table) or write new bags whose message fields hold non-finite, huge or inconsistent values,
and check :func:`~tests.fuzz.properties.reads_cleanly` on ``open_dataset``: a valid recording, or a
DatasetError whose message is one printable line.

Every crash found is kept under ``tests/fuzz/corpus/ros/`` (a file, or a folder for a ROS2 bag folder) and
replayed by :func:`test_corpus`.
"""

from __future__ import annotations

import copy
import json
import re
import shutil
import sqlite3
import struct
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import assume, event, given
from hypothesis import strategies as st
from ruamel.yaml import YAML

from datasets.registry import open_dataset
from datasets.ros.typestores import BagKind, header_msg, standard_typestore
from tests.fuzz.properties import CORPUS, YAML_ODD_SCALARS, reads_cleanly
from tests.test_bad_input_ros import (
    STEP_NS,
    T0,
    Message,
    cloud_msg,
    odom_msg,
    ros1_records,
    scan_msg,
    serialize,
    standard_messages,
    storage_file,
    tf_static_msg,
    write_bag,
    write_ros2,
)

ROS_CORPUS = CORPUS / "ros"
FILE_LAYOUTS = ["bag", "bag-bz2", "bag-lz4", "mcap", "db3"]
FOLDER_LAYOUTS = ["folder", "folder-db3"]
DERIVED_SEEDS = ["bag-cloud", "mcap-cloud", "bag-badindex", "bag-lz4-badindex"]
#: ROS 2 bags compressed by rosbags' writer: name -> (storage, zstd compression mode, open the folder?)
COMPRESSED_SEEDS = {
    "folder-zstd-file": ("mcap", "file", True),
    "folder-zstd-message": ("mcap", "message", True),
    "folder-db3-zstd-file": ("sqlite3", "file", True),
    "folder-db3-zstd-message": ("sqlite3", "message", True),
    "mcap-zstd-chunks": ("mcap", "storage", False),
}
ROS2_FOLDERS = [*FOLDER_LAYOUTS, *(name for name, (_, _, folder) in COMPRESSED_SEEDS.items() if folder)]
U32_HUGE = [0, 1, 0x7FFFFFFF, 0x80000000, 0xFFFFFFF0, 0xFFFFFFFF]
U64_HUGE = [0, 1, 1 << 31, 1 << 40, 1 << 62, 1 << 63, (1 << 64) - 1]


def _read(path: Path) -> Any:
    """``open_dataset(path)``, and the first cloud loaded when the recording has clouds."""
    rec = open_dataset(path)
    if rec.clouds is not None and len(rec.clouds) > 0:
        rec.clouds[0]
    return rec


def _outcome(out: object) -> None:
    """Tell the statistics (``--hypothesis-show-statistics``) whether the case was read or refused."""
    event("read" if out is not None else "refused (DatasetError)")


# -- seeds -------------------------------------------------------------------------------------------------


class Seed:
    """A valid bag kept in memory: ``files`` (relative path -> bytes); ``target`` is what to open."""

    def __init__(self, name: str, root: Path, target: Path) -> None:
        self.name = name
        self.target = target.relative_to(root)
        self.files = {p.relative_to(root): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}

    def __repr__(self) -> str:
        return f"Seed({self.name!r})"

    @property
    def data_file(self) -> Path:
        """The file holding the messages (the bag, .mcap or .db3)."""
        return next(p for p in self.files if p.suffix in (".bag", ".mcap", ".db3", ".zstd"))

    def write(self, root: Path, replace: dict[Path, bytes] | None = None) -> Path:
        for rel, data in {**self.files, **(replace or {})}.items():
            (root / rel).parent.mkdir(parents=True, exist_ok=True)
            (root / rel).write_bytes(data)
        return root / self.target


def _seed(base: Path, layout: str, clouds: bool = False, name: str | None = None) -> Seed:
    name = name or f"{layout}{'-cloud' if clouds else ''}"
    root = base / name
    root.mkdir()
    target = write_bag(layout, root, lambda kind: standard_messages(kind, n=3, clouds=clouds))
    return Seed(name, root, target)


def _compressed_seed(base: Path, name: str) -> Seed:
    """A seed of :data:`COMPRESSED_SEEDS`, written by rosbags with zstd compression."""
    storage, mode, folder = COMPRESSED_SEEDS[name]
    root = base / name
    root.mkdir()
    bag = write_ros2(root / "b2", standard_messages("ros2", n=3), storage, compression=mode)
    return Seed(name, root, bag if folder else storage_file(bag))


def _bad_index_seed(base: Path, layout: str) -> Seed:
    """A ROS1 seed whose index data records declare 4 bytes too many (as ``lsm-demo/demo.bag``): the strict
    reader refuses it, the chunk scanner reads it; damage then reaches the scanner's deeper paths."""
    seed = _seed(base, layout, name=f"{layout}-badindex")
    path = base / seed.name / seed.target
    data = bytearray(path.read_bytes())
    for r in ros1_records(bytes(data)):
        if r["fields"]["op"][1] == b"\x04":
            data[r["data_pos"] - 4 : r["data_pos"]] = struct.pack("<I", r["data_len"] + 4)
    path.write_bytes(data)
    return Seed(seed.name, base / seed.name, path)


@pytest.fixture(scope="module")
def seeds(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Seed]:
    base = tmp_path_factory.mktemp("ros-seeds")
    out = {layout: _seed(base, layout) for layout in FILE_LAYOUTS + FOLDER_LAYOUTS}
    out["bag-cloud"] = _seed(base, "bag", clouds=True)
    out["mcap-cloud"] = _seed(base, "mcap", clouds=True)
    for layout in ("bag", "bag-lz4"):
        out[f"{layout}-badindex"] = _bad_index_seed(base, layout)
    for name in COMPRESSED_SEEDS:
        out[name] = _compressed_seed(base, name)
    for name, seed in out.items():  # the seeds themselves read cleanly and completely
        with tempfile.TemporaryDirectory() as tmp:
            rec = _read(seed.write(Path(tmp)))
            assert rec.scans is not None and len(rec.scans) == 3, name
            assert ("badindex" in name) == any("damaged index" in n for n in rec.meta["notes"]), name
    return out


# -- where the length fields are ---------------------------------------------------------------------------


def _ros1_length_positions(data: bytes) -> list[int]:
    """Offsets of the u32 length fields of a ROS1 bag (records, header fields, uncompressed chunks)."""
    out: list[int] = []

    def walk(records: list[dict[str, Any]]) -> None:
        for r in records:
            out.extend([r["pos"], r["data_pos"] - 4])
            for name, (value_pos, _) in r["fields"].items():
                out.append(value_pos - len(name) - 1 - 4)
            fields = r["fields"]
            if fields.get("op", (0, b""))[1] == b"\x05" and fields.get("compression", (0, b""))[1] == b"none":
                walk(ros1_records(data, r["data_pos"], r["data_pos"] + r["data_len"]))

    try:
        walk(ros1_records(data))
    except (struct.error, IndexError, KeyError, ValueError):  # a damaged bag: the positions found so far
        pass
    return sorted(p for p in set(out) if 0 <= p <= len(data) - 4)


def _mcap_length_positions(data: bytes) -> list[int]:
    """Offsets of the u64 record lengths of an MCAP file."""
    out, pos = [], 8
    while pos + 9 <= len(data) - 8:
        out.append(pos + 1)
        (length,) = struct.unpack_from("<Q", data, pos + 1)
        pos += 9 + length
    return out


# -- byte-level damage -------------------------------------------------------------------------------------


@st.composite
def byte_damage(draw: st.DrawFn, seed: Seed) -> bytes:
    """``data`` with one to three of: flipped bytes, a cut, a zeroed run, a length field (or any word) set
    to a huge value."""
    suffix = seed.data_file.suffix
    out = bytearray(seed.files[seed.data_file])
    for _ in range(draw(st.integers(1, 3))):
        kind = draw(st.sampled_from(["flip", "cut", "length", "word", "zeros"]))
        if len(out) < 16:
            break
        if kind == "flip":
            at = draw(st.integers(0, len(out) - 1))
            out[at] ^= draw(st.integers(1, 255))
        elif kind == "cut":
            del out[draw(st.integers(0, len(out) - 1)) :]
        elif kind == "zeros":
            at = draw(st.integers(0, len(out) - 1))
            out[at : at + draw(st.integers(1, 64))] = bytes(min(64, len(out) - at))[: len(out[at : at + 64])]
        else:
            wide = suffix == ".mcap" and draw(st.booleans())
            width = 8 if wide else 4
            if kind == "length":
                places = _mcap_length_positions(bytes(out)) if wide else []
                if suffix == ".bag":
                    places = _ros1_length_positions(bytes(out))
                places = [p for p in places if p + width <= len(out)]
                at = draw(st.sampled_from(places)) if places else draw(st.integers(0, len(out) - width))
            else:
                at = draw(st.integers(0, len(out) - width))
            value = draw(st.sampled_from(U64_HUGE if wide else U32_HUGE) | st.integers(0, len(out) + 16))
            out[at : at + width] = struct.pack("<Q" if wide else "<I", value % (1 << (8 * width)))
    return bytes(out)


@given(
    data=st.data(),
    layout=st.sampled_from([*FILE_LAYOUTS, *FOLDER_LAYOUTS, *DERIVED_SEEDS, *COMPRESSED_SEEDS]),
)
def test_damaged_bytes_read_cleanly(seeds: dict[str, Seed], data: st.DataObject, layout: str) -> None:
    seed = seeds[layout]
    rel = seed.data_file
    damaged = data.draw(byte_damage(seed), label="damaged")
    with tempfile.TemporaryDirectory() as tmp:
        path = seed.write(Path(tmp), {rel: damaged})
        _outcome(reads_cleanly(lambda: _read(path)))


# -- metadata.yaml of the wrong types ----------------------------------------------------------------------


class RawYaml(str):
    """A scalar written into metadata.yaml as it is (a tag, a date, a 5000-digit number), not as a string."""


_ODD_VALUES = st.one_of(
    YAML_ODD_SCALARS.map(RawYaml),
    st.none(),
    st.booleans(),
    st.integers(-(2**70), 2**70),
    st.sampled_from([0, -1, 2**31, 2**63, 2**64]),
    st.floats(),
    st.text(max_size=6),
    st.just({}),
    st.just([]),
    st.lists(st.integers(-3, 3), max_size=2),
    st.dictionaries(st.sampled_from(["name", "type", "nanoseconds"]), st.integers(), max_size=2),
)


def _yaml_paths(node: Any, prefix: tuple = ()) -> list[tuple]:
    out = [prefix] if prefix else []
    if isinstance(node, dict):
        for k, v in node.items():
            out.extend(_yaml_paths(v, (*prefix, k)))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            out.extend(_yaml_paths(v, (*prefix, i)))
    return out


_METADATA_CACHE: dict[str, Any] = {}


def _metadata(seed: Seed, rel: Path) -> Any:
    """The seed's metadata.yaml parsed (once; a deep copy per case)."""
    key = str(id(seed))
    if key not in _METADATA_CACHE:
        _METADATA_CACHE[key] = YAML(typ="safe", pure=True).load(seed.files[rel])
    return copy.deepcopy(_METADATA_CACHE[key])


def _metadata_text(meta: Any) -> str:
    """``meta`` as flow YAML (JSON, whose NaN / Infinity come back as strings: another wrong type), every
    :class:`RawYaml` value written unquoted."""
    raw: list[str] = []

    def mark(node: Any) -> Any:
        if isinstance(node, RawYaml):
            raw.append(str(node))
            return f"@@RAW{len(raw) - 1}@@"
        if isinstance(node, dict):
            return {k: mark(v) for k, v in node.items()}
        if isinstance(node, list):
            return [mark(v) for v in node]
        return node

    text = json.dumps(mark(meta))
    for i, value in enumerate(raw):
        text = text.replace(f'"@@RAW{i}@@"', value)
    return text


@given(data=st.data(), layout=st.sampled_from(ROS2_FOLDERS))
def test_metadata_yaml_of_wrong_types_reads_cleanly(
    seeds: dict[str, Seed], data: st.DataObject, layout: str
) -> None:
    seed = seeds[layout]
    rel = next(p for p in seed.files if p.name == "metadata.yaml")
    meta = _metadata(seed, rel)
    for _ in range(data.draw(st.integers(1, 2), label="edits")):
        paths = _yaml_paths(meta)
        if not paths:
            break
        path = data.draw(st.sampled_from(paths), label="path")
        parent = meta
        for key in path[:-1]:
            parent = parent[key]
        if data.draw(st.booleans(), label="delete") and isinstance(parent, dict):
            del parent[path[-1]]
        else:
            parent[path[-1]] = data.draw(_ODD_VALUES, label="value")
    with tempfile.TemporaryDirectory() as tmp:
        target = seed.write(Path(tmp), {rel: _metadata_text(meta).encode()})
        _outcome(reads_cleanly(lambda: _read(target)))


# -- ROS 2 compression: declared against actual ----------------------------------------------------------

#: What metadata.yaml may declare: the values rosbags knows in any case, others, and odd text.
_DECLARED_MODES = st.sampled_from(["", "none", "NONE", "FILE", "file", "MESSAGE", "message", "STORAGE", "x"])
_DECLARED_FORMATS = st.sampled_from(["", "zstd", "ZSTD", "lz4", "gzip", "none"])


def _declared(meta_text: str, key: str, value: str) -> str:
    """``meta_text`` with the value of ``key`` (compression_mode / compression_format) set to ``value``."""
    quoted = json.dumps(value)  # a JSON string is a YAML double-quoted scalar
    text, n = re.subn(rf"(?m)^(\s*{key}:).*$", lambda m: f"{m.group(1)} {quoted}", meta_text)
    assert n == 1, meta_text
    return text


@given(
    data=st.data(),
    layout=st.sampled_from(ROS2_FOLDERS),
    mode=_DECLARED_MODES | st.text(max_size=6),
    fmt=_DECLARED_FORMATS | st.text(max_size=6),
    damage=st.booleans(),
)
def test_declared_compression_reads_cleanly(
    seeds: dict[str, Seed], data: st.DataObject, layout: str, mode: str, fmt: str, damage: bool
) -> None:
    """A ROS 2 folder (plain, or zstd by file or by message; MCAP or SQLite) whose metadata.yaml declares any
    compression mode and format, its storage file damaged or not: a recording or one DatasetError line
    (a declared zstd that the files do not hold was rosbags' ZstdError)."""
    seed = seeds[layout]
    rel = next(p for p in seed.files if p.name == "metadata.yaml")
    text = seed.files[rel].decode()
    text = _declared(_declared(text, "compression_mode", mode), "compression_format", fmt)
    replace = {rel: text.encode()}
    if damage:
        replace[seed.data_file] = data.draw(byte_damage(seed), label="damaged")
    with tempfile.TemporaryDirectory() as tmp:
        target = seed.write(Path(tmp), replace)
        _outcome(reads_cleanly(lambda: _read(target)))


# -- control and non-UTF-8 bytes in the text fields of record headers ---------------------------------------

_ROS1_TEXT_FIELDS = {"compression", "topic", "type", "md5sum", "message_definition", "callerid", "latching"}


def _ros1_text_fields(data: bytes) -> list[tuple[int, int]]:
    """(position, length) of every text field value of a ROS1 bag: in the record headers (top level and
    inside uncompressed chunks) and in the connection records' data (type, md5sum, definition, ...)."""
    out: list[tuple[int, int]] = []

    def fields_at(start: int, end: int) -> None:  # a header-like field list: <len><name>=<value>...
        pos = start
        while pos + 4 <= end:
            (flen,) = struct.unpack_from("<I", data, pos)
            name, sep, value = data[pos + 4 : pos + 4 + flen].partition(b"=")
            if sep and name.decode("latin-1") in _ROS1_TEXT_FIELDS:
                out.append((pos + 4 + len(name) + 1, len(value)))
            pos += 4 + flen

    def walk(records: list[dict[str, Any]]) -> None:
        for r in records:
            for name, (value_pos, value) in r["fields"].items():
                if name in _ROS1_TEXT_FIELDS:
                    out.append((value_pos, len(value)))
            op = r["fields"].get("op", (0, b""))[1]
            if op == b"\x07":
                fields_at(r["data_pos"], r["data_pos"] + r["data_len"])
            elif op == b"\x05" and r["fields"].get("compression", (0, b""))[1] == b"none":
                walk(ros1_records(data, r["data_pos"], r["data_pos"] + r["data_len"]))

    walk(ros1_records(data))
    return [(p, n) for p, n in out if n > 0]


def _mcap_strings(data: bytes, start: int, end: int, out: list[tuple[int, int]]) -> None:
    """(position, length) of the strings of the MCAP records between ``start`` and ``end``: header profile
    and library, schema name, encoding and definition, channel topic, encoding and metadata, chunk
    compression, metadata names and entries (and of the records inside uncompressed chunks)."""

    def string(pos: int) -> int:  # records the string at pos, returns the position after it
        (n,) = struct.unpack_from("<I", data, pos)
        out.append((pos + 4, n))
        return pos + 4 + n

    def string_map(pos: int) -> None:
        (size,) = struct.unpack_from("<I", data, pos)
        pos, stop = pos + 4, pos + 4 + size
        while pos < stop:
            pos = string(string(pos))

    pos = start
    while pos + 9 <= end:
        op = data[pos]
        (length,) = struct.unpack_from("<Q", data, pos + 1)
        body = pos + 9
        if op == 0x01:  # header
            string(string(body))
        elif op == 0x03:  # schema: id, name, encoding, data
            string(string(string(body + 2)))
        elif op == 0x04:  # channel: id, schema id, topic, message encoding, metadata
            string_map(string(string(body + 4)))
        elif op == 0x06:  # chunk: start, end, size, crc, compression, records
            after = string(body + 28)
            (records,) = struct.unpack_from("<Q", data, after)
            if after == body + 32:  # an empty compression string: walk the chunk's records
                _mcap_strings(data, after + 8, after + 8 + records, out)
        elif op == 0x0C:  # metadata: name, entries
            string_map(string(body))
        pos = body + length


def _mcap_text_fields(data: bytes) -> list[tuple[int, int]]:
    out: list[tuple[int, int]] = []
    _mcap_strings(data, 8, len(data) - 8, out)
    return [(p, n) for p, n in out if n > 0]


#: Bytes for a text field: control characters (NUL, newline, ESC, DEL), bytes that are no UTF-8 (alone or
#: starting a sequence), a bidi override in UTF-8, or any byte.
_TEXT_BYTE = st.one_of(
    st.sampled_from([0x00, 0x0A, 0x0D, 0x09, 0x1B, 0x7F, 0x85, 0xFF, 0xC3, 0xE2, 0x80, 0xAE]),
    st.integers(0, 255),
)


@st.composite
def text_field_damage(draw: st.DrawFn, seed: Seed) -> bytes:
    """The seed's data file with one to three of its text fields (or a run inside one) overwritten, in
    place, by control or non-UTF-8 bytes."""
    out = bytearray(seed.files[seed.data_file])
    fields = (
        _mcap_text_fields(bytes(out)) if seed.data_file.suffix == ".mcap" else _ros1_text_fields(bytes(out))
    )
    for _ in range(draw(st.integers(1, 3))):
        pos, length = draw(st.sampled_from(fields))
        start = draw(st.integers(0, length - 1))
        count = draw(st.integers(1, length - start))
        out[pos + start : pos + start + count] = bytes(
            draw(st.lists(_TEXT_BYTE, min_size=count, max_size=count))
        )
    return bytes(out)


@given(
    data=st.data(), layout=st.sampled_from(["bag", "bag-lz4", "bag-badindex", "mcap", "folder", "mcap-cloud"])
)
def test_text_fields_with_control_bytes_read_cleanly(
    seeds: dict[str, Seed], data: st.DataObject, layout: str
) -> None:
    """Control and non-UTF-8 bytes in every text field a message may quote: ROS1 header and connection
    fields (compression, topic, type, md5sum, definition, callerid, latching), MCAP strings (topic, schema
    name and definition, encodings, metadata, chunk compression)."""
    seed = seeds[layout]
    damaged = data.draw(text_field_damage(seed), label="damaged")
    with tempfile.TemporaryDirectory() as tmp:
        path = seed.write(Path(tmp), {seed.data_file: damaged})
        _outcome(reads_cleanly(lambda: _read(path)))


_DB3_TEXT = st.one_of(
    st.text(max_size=8),
    st.binary(max_size=8),
    st.lists(_TEXT_BYTE, max_size=8).map(bytes),
    st.sampled_from(["", "/scan\n", "\x1b[2J", "sensor_msgs/msg/LaserScan\x00"]),
    st.none(),
    st.integers(-(2**63), 2**63 - 1),
)


@given(
    data=st.data(),
    layout=st.sampled_from(["db3", "folder-db3"]),
    column=st.sampled_from(
        ["name", "type", "serialization_format", "offered_qos_profiles", "type_description_hash"]
    ),
)
def test_db3_topic_columns_read_cleanly(
    seeds: dict[str, Seed], data: st.DataObject, layout: str, column: str
) -> None:
    """A .db3 topics table whose text column holds control characters, bytes that are no UTF-8 (a BLOB),
    NULL or an integer (SQLite does not enforce the declared types)."""
    seed = seeds[layout]
    value = data.draw(_DB3_TEXT, label="value")
    row = data.draw(st.integers(1, 3), label="row")
    with tempfile.TemporaryDirectory() as tmp:
        path = seed.write(Path(tmp))
        db = sqlite3.connect(path if path.is_file() else storage_file(path))
        try:
            db.execute("PRAGMA writable_schema = ON")  # drop NOT NULL (a damaged file need not keep it)
            db.execute("UPDATE sqlite_master SET sql = replace(sql, 'NOT NULL', '') WHERE name = 'topics'")
            db.commit()
        finally:
            db.close()
        db = sqlite3.connect(path if path.is_file() else storage_file(path))
        try:
            db.execute(f"UPDATE topics SET {column} = ? WHERE id = ?", (value, row))
            db.commit()
        finally:
            db.close()
        _outcome(reads_cleanly(lambda: _read(path)))


# -- message fields: non-finite, huge, inconsistent --------------------------------------------------------

F32 = st.floats(width=32) | st.sampled_from([0.0, -0.0, 1e-45, 3.4e38, -3.4e38, float("nan"), float("inf")])
F64 = st.floats() | st.sampled_from([0.0, 1e7, 1e300, float("nan"), float("-inf")])
SMALL_OR_HUGE = st.integers(0, 40) | st.sampled_from([1 << 16, 1 << 31, (1 << 32) - 1])


@st.composite
def odd_scan(draw: st.DrawFn, kind: BagKind, stamp: int) -> Message:
    ranges = np.asarray(draw(st.lists(F32, max_size=12)), np.float32)
    fields = {
        name: draw(F32)
        for name in ("angle_min", "angle_increment", "range_min", "range_max")
        if draw(st.booleans())
    }
    return scan_msg(kind, stamp, ranges=ranges if draw(st.booleans()) else None, **fields)


@st.composite
def odd_odom(draw: st.DrawFn, kind: BagKind, stamp: int) -> Message:
    topic, msgtype, t, msg = odom_msg(kind, stamp, x=draw(F64), y=draw(F64))
    q = msg.pose.pose.orientation
    if draw(st.booleans()):
        q.x, q.y, q.z, q.w = (draw(F64) for _ in range(4))
    if draw(st.booleans()):
        msg.pose.covariance[draw(st.integers(0, 35))] = draw(F64)
    return topic, msgtype, t, msg


@st.composite
def odd_tf(draw: st.DrawFn, kind: BagKind) -> Message:
    quat = tuple(draw(F64) for _ in range(4)) if draw(st.booleans()) else (0.0, 0.0, 0.0, 1.0)
    topic, msgtype, t, msg = tf_static_msg(kind, quat)  # type: ignore[arg-type]
    tr = msg.transforms[0].transform.translation
    if draw(st.booleans()):
        tr.x, tr.y, tr.z = (draw(F64) for _ in range(3))
    return topic, msgtype, t, msg


@st.composite
def odd_cloud(draw: st.DrawFn, kind: BagKind, stamp: int) -> Message:
    n = draw(st.integers(0, 6))
    pts = np.asarray(draw(st.lists(F32, min_size=3 * n, max_size=3 * n)), np.float32).reshape(n, 3)
    layout: dict[str, Any] = {
        name: draw(SMALL_OR_HUGE)
        for name in ("point_step", "width", "height", "row_step")
        if draw(st.booleans())
    }
    if draw(st.booleans()):
        layout["data"] = bytes(draw(st.integers(0, 100)))
    if "row_step" not in layout:
        layout["row_step"] = (layout.get("point_step", 12) * layout.get("width", n)) % (1 << 32)
    topic, msgtype, t, msg = cloud_msg(kind, stamp, points=pts, **layout)
    if draw(st.booleans()):
        f = msg.fields[draw(st.integers(0, 2))]
        f.offset = draw(SMALL_OR_HUGE)
        f.datatype = draw(st.integers(0, 255))
    return topic, msgtype, t, msg


@st.composite
def odd_messages(draw: st.DrawFn, kind: BagKind, clouds: bool) -> list[Message]:
    """A few scans (or clouds), odometry and tf_static, some of them with odd values, odd stamps too."""
    out: list[Message] = [draw(odd_tf(kind)) if draw(st.booleans()) else tf_static_msg(kind)]
    for i in range(draw(st.integers(1, 3))):
        t = T0 + i * STEP_NS
        stamp = draw(st.sampled_from([t, 0, 2**61])) if draw(st.integers(0, 9)) == 0 else t
        if clouds:
            out.append(draw(odd_cloud(kind, stamp)) if draw(st.booleans()) else cloud_msg(kind, stamp))
        else:
            out.append(draw(odd_scan(kind, stamp)) if draw(st.booleans()) else scan_msg(kind, stamp))
        out.append(draw(odd_odom(kind, t + 1)) if draw(st.booleans()) else odom_msg(kind, t + 1))
    if draw(st.integers(0, 4)) == 0:  # a header stamp of the far future
        msg = out[-1][3]
        late = draw(st.sampled_from([(2**31 - 1) * 10**9, (2**32 - 1) * 10**9 if kind == "ros1" else 0]))
        msg.header = header_msg(standard_typestore(kind), kind, late, "odom")
    return out


@given(data=st.data(), layout=st.sampled_from(["bag", "mcap", "folder-db3"]), clouds=st.booleans())
def test_odd_message_values_read_cleanly(data: st.DataObject, layout: str, clouds: bool) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        try:
            path = write_bag(
                layout, Path(tmp), lambda kind: data.draw(odd_messages(kind, clouds), label="msgs")
            )
        except (OverflowError, ValueError, struct.error):  # not writable: nothing to read
            assume(False)
        _outcome(reads_cleanly(lambda: _read(path)))


# -- raw message bytes -------------------------------------------------------------------------------------


@given(data=st.data(), layout=st.sampled_from(["bag", "mcap"]), which=st.integers(0, 2), clouds=st.booleans())
def test_damaged_message_bytes_read_cleanly(
    data: st.DataObject, layout: str, which: int, clouds: bool
) -> None:
    """One message's serialized bytes damaged (array lengths set huge among others), written back as is."""

    def messages(kind: BagKind) -> list[Message]:
        msgs = standard_messages(kind, n=2, clouds=clouds)
        index = [0, 3, 4][which]  # tf_static, the second scan (or cloud), the second odometry
        topic, msgtype, t, msg = msgs[index]
        raw = bytearray(serialize(kind, msgtype, msg))
        for _ in range(data.draw(st.integers(1, 3), label="edits")):
            if not raw:
                break
            at = data.draw(st.integers(0, len(raw) - 1), label="at")
            if data.draw(st.booleans(), label="word"):
                value = data.draw(st.sampled_from(U32_HUGE) | st.integers(0, len(raw) + 8), label="value")
                raw[at : at + 4] = struct.pack("<I", value)
            elif data.draw(st.booleans(), label="cut"):
                del raw[at:]
            else:
                raw[at] ^= data.draw(st.integers(1, 255), label="xor")
        msgs[index] = (topic, msgtype, t, bytes(raw))
        return msgs

    with tempfile.TemporaryDirectory() as tmp:
        path = write_bag(layout, Path(tmp), messages)
        _outcome(reads_cleanly(lambda: _read(path)))


# -- the corpus of crashes found ---------------------------------------------------------------------------


def _corpus_entries() -> list[Path]:
    if not ROS_CORPUS.is_dir():
        return []
    return sorted(p for p in ROS_CORPUS.iterdir() if not p.name.startswith(("README", ".")))


@pytest.mark.parametrize("entry", _corpus_entries(), ids=lambda p: p.name)
def test_corpus(entry: Path, tmp_path: Path) -> None:
    """Each crash found so far (a bag file, or a ROS2 bag folder) reads cleanly."""
    target = tmp_path / entry.name
    if entry.is_dir():
        shutil.copytree(entry, target)
    else:
        shutil.copyfile(entry, target)
    reads_cleanly(lambda: _read(target))


def test_corpus_files_are_small() -> None:
    for entry in _corpus_entries():
        files = [p for p in entry.rglob("*") if p.is_file()] if entry.is_dir() else [entry]
        for f in files:
            assert f.stat().st_size < 20_000, f
