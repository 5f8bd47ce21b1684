"""Open a ROS1 or ROS2 bag behind one small interface: topics, and decoded messages in time order.

Decoding (message definitions): a message type is decoded with the standard definition of
:func:`~datasets.ros.typestores.standard_typestore` when the bag's hash of it matches the standard one
(ROS1 MD5 / ROS2 RIHS01, or no hash recorded) -- identical hashes mean identical wire formats, so this also
decodes old bags whose embedded definitions no longer parse (``lsm-demo/demo_index_fixed.bag`` embeds a
``LaserScan`` built on the retired ``roslib/Header``; its MD5 90c7ef2dc6895d81024acba2ac42f369 is the
standard one). Other types are decoded with the definition embedded in the bag, checked against its hash.

ROS1 bags whose index is damaged (``lsm-demo/demo.bag``) are read by :mod:`datasets.ros.chunkscan`.
Every failure is a :class:`~datasets.errors.DatasetError` naming the file: the library errors of
:data:`BAG_IO_ERRORS`, connections whose fields have the wrong type (a damaged metadata.yaml or SQLite
table), and an index that lists a message of another connection than the one asked for.
"""

from __future__ import annotations

import sqlite3
import struct
from collections.abc import Callable, Collection, Iterator
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

import apsw
from rosbags import rosbag1, rosbag2
from rosbags.interfaces import MessageDefinitionFormat
from rosbags.rosbag2 import reader as rosbag2_reader
from rosbags.rosbag2 import storage_mcap
from rosbags.serde import SerdeError
from rosbags.typesys import Stores, TypesysError, get_types_from_idl, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from datasets.errors import DatasetError, first_line, shown, shown_name, shown_names
from datasets.ros.chunkscan import BagScanError, ChunkScanBag, first_overrun
from datasets.ros.typestores import BagKind, standard_typestore


def _zstd_errors() -> tuple[type[BaseException], ...]:
    """The error classes of the zstd module rosbags decompresses with (``backports.zstd`` before Python 3.14,
    ``compression.zstd`` since; ``zstandard`` in older rosbags), as rosbags' own modules import it."""
    found: list[type[BaseException]] = []
    for module in (rosbag2_reader, storage_mcap):
        cls = getattr(getattr(module, "zstd", None), "ZstdError", None)
        if isinstance(cls, type) and issubclass(cls, BaseException) and cls not in found:
            found.append(cls)
    return tuple(found)


def _zstd_failure(path: Path, exc: BaseException, declared: str | None) -> DatasetError:
    """The error for zstd data of the ROS 2 bag at ``path`` that does not decompress; ``declared``: the
    compression mode its metadata.yaml declares (``file`` / ``message``), None when unknown or none."""
    hint = ""
    if declared is not None or path.is_dir():
        mode = f"compression_mode {shown_name(declared)}" if declared else "compression"
        hint = f"; does metadata.yaml declare a zstd {mode} that the files do not have?"
    return DatasetError(
        f"{path}: corrupt ROS2 bag: zstd-compressed data does not decompress ({first_line(exc)}){hint}"
    )


#: What rosbags raises for zstd data that does not decompress: a ROS 2 bag whose metadata.yaml declares
#: ``compression_format: zstd`` (by FILE or by MESSAGE) while its files are not compressed, a damaged
#: ``.zstd`` file, a damaged zstd chunk of an MCAP file.
ZSTD_ERRORS: tuple[type[BaseException], ...] = _zstd_errors()

# What a damaged or cut bag can make rosbags (or the decompressors and SQLite under it) raise. Only calls into
# those libraries are guarded with it: a size field of 2^40 or 2^63 makes them allocate (MemoryError) or
# overflow (OverflowError); a metadata.yaml or SQLite row of the wrong type gives TypeError / AttributeError.
BAG_IO_ERRORS: tuple[type[BaseException], ...] = (
    rosbag1.ReaderError,
    rosbag2.ReaderError,
    SerdeError,
    TypesysError,
    AssertionError,
    struct.error,
    ValueError,
    KeyError,
    IndexError,
    EOFError,
    OSError,
    RuntimeError,
    MemoryError,
    OverflowError,
    TypeError,
    AttributeError,
    apsw.Error,
    sqlite3.Error,
    *ZSTD_ERRORS,
)


@dataclass(frozen=True)
class TopicInfo:
    """One topic of a bag: its message type (``pkg/msg/Name``) and message count."""

    name: str
    msgtype: str
    count: int


@dataclass
class _Conn:
    """What decoding needs to know about one connection."""

    topic: str
    msgtype: str
    digest: str
    msgdef_format: MessageDefinitionFormat
    msgdef: str
    handle: Any  # the reader's own connection object (or id)
    key: int  # the connection id, as the reader reports it with each message


@dataclass
class Bag:
    """An open bag: ``topics`` by name, ``messages(...)`` decoded, ``notes`` on fallbacks used."""

    path: Path
    kind: BagKind
    topics: dict[str, TopicInfo]
    notes: list[str] = field(default_factory=list)
    _conns: list[_Conn] = field(default_factory=list)
    _reader: Any = None
    _decoders: dict[tuple[str, str], Any] = field(default_factory=dict)

    def describe_topics(self) -> str:
        """``/a (pkg/msg/A), /b (pkg/msg/B)`` or ``none``."""
        if not self.topics:
            return "none"
        ordered = sorted(self.topics.values(), key=lambda t: t.name)
        return shown_names(f"{t.name} ({t.msgtype})" for t in ordered)

    def raw_messages(
        self, topics: Collection[str], start: int | None = None, stop: int | None = None
    ) -> Iterator[tuple[str, int, bytes]]:
        """``(topic, bag_time_ns, raw bytes)`` of ``topics`` in bag-time order."""
        for conn, t, raw in self._raw_messages(topics, start, stop):
            yield conn.topic, t, raw

    def _raw_messages(
        self, topics: Collection[str], start: int | None, stop: int | None
    ) -> Iterator[tuple[_Conn, int, bytes]]:
        """``(connection, bag_time_ns, raw bytes)``; every message must belong to a connection asked for.

        A damaged index can point at the record of another connection (the reader then reports the
        connection of the record itself): that is an error here, never a message decoded as the wrong type.
        """
        conns = [c for c in self._conns if c.topic in topics]
        if not conns:
            return
        by_key = {c.key: c for c in conns}
        try:
            for handle, t, raw in self._reader.messages([c.handle for c in conns], start, stop):
                conn = by_key.get(getattr(handle, "id", None))
                if conn is None:
                    other = getattr(handle, "topic", "?")
                    raise DatasetError(
                        f"{self.path}: corrupt bag index: it lists a message of topic {shown_name(other)} "
                        f"under {shown_names(sorted({c.topic for c in conns}))}"
                    )
                yield conn, t, raw
        except DatasetError:
            raise
        except ZSTD_ERRORS as exc:
            try:  # rosbags' Reader says what metadata.yaml declares ('message'); other readers have no such
                declared = getattr(self._reader, "compression_mode", None)
            except BAG_IO_ERRORS:
                declared = None
            raise _zstd_failure(self.path, exc, declared if isinstance(declared, str) else None) from None
        except (*BAG_IO_ERRORS, BagScanError) as exc:
            raise DatasetError(
                f"{self.path}: corrupt bag, reading messages failed ({first_line(exc)})"
            ) from None

    def messages(
        self, topics: Collection[str], start: int | None = None, stop: int | None = None
    ) -> Iterator[tuple[str, int, Any]]:
        """``(topic, bag_time_ns, message)`` of ``topics`` in bag-time order, decoded."""
        for conn, t, raw in self._raw_messages(topics, start, stop):
            msgtype = self.topics[conn.topic].msgtype
            if conn.msgtype != msgtype:
                types = shown_names([msgtype, conn.msgtype])
                raise DatasetError(
                    f"{self.path}: topic {shown_name(conn.topic)} holds messages of two types ({types})"
                )
            decode = self._decoder(conn)
            try:
                msg = decode(raw)
            except BAG_IO_ERRORS as exc:
                raise DatasetError(
                    f"{self.path}: topic {shown_name(conn.topic)}: a message cannot be decoded as "
                    f"{shown_name(msgtype)} ({first_line(exc)})"
                ) from None
            yield conn.topic, t, msg

    def _decoder(self, conn: _Conn):
        key = (conn.msgtype, conn.digest)
        if key not in self._decoders:
            store = self._store_for(conn)
            if self.kind == "ros1":
                self._decoders[key] = lambda raw, s=store, m=conn.msgtype: s.deserialize_ros1(raw, m)
            else:
                self._decoders[key] = lambda raw, s=store, m=conn.msgtype: s.deserialize_cdr(raw, m)
        return self._decoders[key]

    def _store_for(self, conn: _Conn) -> Typestore:
        standard = standard_typestore(self.kind)
        if conn.msgtype in standard.fielddefs:
            if self.kind == "ros1":
                have = standard.generate_msgdef(conn.msgtype)[1]
            else:
                have = standard.hash_rihs01(conn.msgtype)
            if not conn.digest or conn.digest == have:
                return standard
        topic, msgtype, digest = (shown_name(v) for v in (conn.topic, conn.msgtype, conn.digest))
        if conn.msgdef_format == MessageDefinitionFormat.NONE or not conn.msgdef:
            if conn.msgtype in standard.fielddefs:
                self.notes.append(
                    f"{topic}: hash {digest} differs from the standard {msgtype} and the bag "
                    "embeds no definition; decoded with the standard definition"
                )
                return standard
            raise DatasetError(
                f"{self.path}: topic {topic}: unknown message type {msgtype} and no definition in the bag"
            )
        store = get_typestore(Stores.EMPTY)
        try:
            if conn.msgdef_format == MessageDefinitionFormat.MSG:
                store.register(get_types_from_msg(conn.msgdef, conn.msgtype))
            else:
                sep = "=" * 80 + "\n"
                typs: dict = {}
                if conn.msgdef.startswith(f"{sep}IDL: "):
                    for part in conn.msgdef.split(sep)[1:]:
                        typs.update(get_types_from_idl(part.split("\n", 1)[1]))
                else:
                    typs.update(get_types_from_idl(conn.msgdef))
                store.register(typs)
            if self.kind == "ros1":
                have = store.generate_msgdef(conn.msgtype)[1]
            else:
                have = store.hash_rihs01(conn.msgtype)
        except (TypesysError, *BAG_IO_ERRORS) as exc:
            raise DatasetError(
                f"{self.path}: topic {topic}: the bag's definition of {msgtype} does not parse "
                f"({first_line(exc)}) and its hash {digest} is not the standard one"
            ) from None
        if conn.digest and have != conn.digest:
            raise DatasetError(
                f"{self.path}: topic {topic}: the bag's definition of {msgtype} hashes to "
                f"{shown_name(have)}, not to the declared {digest}"
            )
        return store

    def close(self) -> None:
        if self._reader is not None:
            reader, self._reader = self._reader, None
            try:
                reader.close()
            except BAG_IO_ERRORS:
                pass

    def __enter__(self) -> Bag:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _topics_of(conns: list[_Conn], counts: list[int]) -> dict[str, TopicInfo]:
    topics: dict[str, TopicInfo] = {}
    for conn, count in zip(conns, counts, strict=True):
        if conn.topic in topics:
            old = topics[conn.topic]
            topics[conn.topic] = TopicInfo(conn.topic, old.msgtype, old.count + count)
        else:
            topics[conn.topic] = TopicInfo(conn.topic, conn.msgtype, count)
    return topics


def _checked_conns(path: Path, raw: list[tuple[Any, ...]]) -> tuple[list[_Conn], list[int]]:
    """``_Conn`` objects and message counts from ``(topic, msgtype, digest, format, msgdef, handle, key,
    count)`` rows; a damaged metadata.yaml / SQLite table can hold any type there, so each is checked."""
    conns, counts = [], []
    for topic, msgtype, digest, fmt, msgdef, handle, key, count in raw:
        if not isinstance(topic, str) or not topic:
            raise DatasetError(f"{path}: corrupt bag: a topic name is {shown(topic)}, not a string")
        if not topic.isprintable():
            raise DatasetError(f"{path}: corrupt bag: topic name {shown(topic)} has control characters")
        name = f"{path}: corrupt bag: topic {shown_name(topic)}"
        if not isinstance(msgtype, str) or not msgtype or not msgtype.isprintable():
            raise DatasetError(f"{name} has message type {shown(msgtype)}")
        if not isinstance(digest, str) or not isinstance(msgdef, str):
            raise DatasetError(f"{name}: type hash or definition is not a string")
        if not digest.isprintable():
            raise DatasetError(f"{name} has type hash {shown(digest)}")
        if not isinstance(fmt, MessageDefinitionFormat):
            raise DatasetError(f"{name}: unknown definition format {shown(fmt)}")
        if isinstance(count, bool) or not isinstance(count, int) or count < 0:
            raise DatasetError(f"{name} has message count {shown(count)}")
        if isinstance(key, bool) or not isinstance(key, int):
            raise DatasetError(f"{name} has connection id {shown(key)}")
        conns.append(_Conn(topic, msgtype, digest, fmt, msgdef, handle, key))
        counts.append(count)
    return conns, counts


def _open_bag(path: Path, kind: BagKind, reader: Any, raw: list[tuple[Any, ...]]) -> Bag:
    """A :class:`Bag` on the open ``reader``; the reader is closed when its connections are corrupt."""
    try:
        conns, counts = _checked_conns(path, raw)
    except DatasetError:
        try:
            reader.close()
        except (*BAG_IO_ERRORS, BufferError):
            pass
        raise
    bag = Bag(path, kind, _topics_of(conns, counts), _conns=conns)
    bag._reader = reader
    return bag


MCAP_MAGIC = b"\x89MCAP0\r\n"


def mcap_overrun(path: Path) -> str | None:
    """Where a record of the MCAP file at ``path`` declares more bytes than the file holds, or None.

    A cheap walk over the top-level record lengths (opcode, u64 length), done before rosbags' reader, which
    allocates whatever such a length asks for (2^40 bytes: MemoryError; 2^63: OverflowError).
    """
    size = path.stat().st_size
    with path.open("rb") as fh:
        if fh.read(len(MCAP_MAGIC)) != MCAP_MAGIC or size < 2 * len(MCAP_MAGIC):
            return None  # not an MCAP file: the reader says so
        pos, end = len(MCAP_MAGIC), size - len(MCAP_MAGIC)
        while pos < end:
            fh.seek(pos + 1)
            raw = fh.read(8)
            if len(raw) < 8 or pos + 9 > end:
                return f"the record at byte {pos} is cut off"
            (length,) = struct.unpack("<Q", raw)
            if length > end - pos - 9:
                return f"the record at byte {pos} declares {length} bytes, past the end of the file"
            pos += 9 + length
    return None


@lru_cache(maxsize=256)
def _cached_walk(walk: Callable[[Path], str | None], path: Path, size: int, mtime_ns: int) -> str | None:
    return walk(path)


def overrun_of(walk: Callable[[Path], str | None], path: Path) -> str | None:
    """``walk(path)`` (:func:`mcap_overrun`, :func:`~datasets.ros.chunkscan.first_overrun`), remembered per
    file version: a lazy cloud sequence reopens its bag for every cloud."""
    st = path.stat()
    return _cached_walk(walk, path, st.st_size, st.st_mtime_ns)


def open_ros1(path: Path) -> Bag:
    """Open a ROS1 bag; a damaged index (or a record length running past the end) falls back to scanning the
    chunks, which reads the bag exactly or says precisely what is wrong."""
    if not path.is_file():
        raise DatasetError(f"{path}: no such file" if not path.exists() else f"{path}: not a file")
    try:
        # the strict reader allocates whatever a length field asks for: it is not given such a file
        strict_error = overrun_of(first_overrun, path)
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read ({exc.strerror})") from None
    if strict_error is None:
        reader = rosbag1.Reader(path)
        try:
            reader.open()
        except BAG_IO_ERRORS as exc:
            strict_error = first_line(exc)
        else:
            raw = [
                (c.topic, c.msgtype, c.digest, c.msgdef.format, c.msgdef.data, c, c.id, c.msgcount)
                for c in reader.connections
            ]
            return _open_bag(path, "ros1", reader, raw)
    try:
        scanned = ChunkScanBag(path)
    except BagScanError as exc:
        if exc.truncated:
            raise DatasetError(f"{path}: truncated ROS1 bag ({exc})") from None
        raise DatasetError(f"{path}: corrupt ROS1 bag ({exc}; strict reader: {strict_error})") from None
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read ({exc.strerror})") from None
    counts = scanned.message_counts()
    raw = [
        (c.topic, c.msgtype, c.md5sum, MessageDefinitionFormat.MSG, c.msgdef, c.id, c.id, counts[c.id])
        for c in scanned.connections.values()
    ]
    bag = _open_bag(path, "ros1", scanned, raw)
    bag.notes.append(f"damaged index bypassed by scanning the chunks (strict reader: {strict_error})")
    bag.notes.extend(scanned.notes)
    return bag


def open_ros2(path: Path) -> Bag:
    """Open a ROS2 bag: a folder with ``metadata.yaml``, or a single ``.mcap`` / ``.db3`` file."""
    if not path.exists():
        raise DatasetError(f"{path}: no such file or directory")
    try:
        for mcap in [path] if path.is_file() else sorted(path.glob("*.mcap")):
            if mcap.suffix == ".mcap" and (overrun := overrun_of(mcap_overrun, mcap)) is not None:
                where = "" if mcap == path else f"{mcap.name}: "
                raise DatasetError(f"{path}: corrupt or unreadable ROS2 bag ({where}{overrun})")
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read ({exc.strerror})") from None
    try:
        reader = rosbag2.Reader(path)
        reader.open()
        raw = [
            (c.topic, c.msgtype, c.digest or "", c.msgdef.format, c.msgdef.data, c, c.id, c.msgcount)
            for c in reader.connections
        ]
    except ZSTD_ERRORS as exc:
        raise _zstd_failure(path, exc, None) from None
    except (*BAG_IO_ERRORS, FileNotFoundError) as exc:
        raise DatasetError(f"{path}: corrupt or unreadable ROS2 bag ({first_line(exc)})") from None
    return _open_bag(path, "ros2", reader, raw)


def open_bag(path: Path, kind: BagKind) -> Bag:
    """Open the bag at ``path`` as ``kind``; use it as a context manager."""
    return open_ros1(path) if kind == "ros1" else open_ros2(path)
