"""Open a ROS1 or ROS2 bag behind one small interface: topics, and decoded messages in time order.

Decoding (message definitions): a message type is decoded with the standard definition of
:func:`~datasets.ros.typestores.standard_typestore` when the bag's hash of it matches the standard one
(ROS1 MD5 / ROS2 RIHS01, or no hash recorded) -- identical hashes mean identical wire formats, so this also
decodes old bags whose embedded definitions no longer parse (``lsm-demo/demo_index_fixed.bag`` embeds a
``LaserScan`` built on the retired ``roslib/Header``; its MD5 90c7ef2dc6895d81024acba2ac42f369 is the
standard one). Other types are decoded with the definition embedded in the bag, checked against its hash.

ROS1 bags whose index is damaged (``lsm-demo/demo.bag``) are read by :mod:`datasets.ros.chunkscan`.
Every failure is a :class:`~datasets.errors.DatasetError` naming the file.
"""

from __future__ import annotations

import struct
from collections.abc import Collection, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rosbags import rosbag1, rosbag2
from rosbags.interfaces import MessageDefinitionFormat
from rosbags.serde import SerdeError
from rosbags.typesys import Stores, TypesysError, get_types_from_idl, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from datasets.errors import DatasetError
from datasets.ros.chunkscan import BagScanError, ChunkScanBag
from datasets.ros.typestores import BagKind, standard_typestore

# What a damaged or cut bag can make rosbags (or the decompressors under it) raise.
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
)


def first_line(exc: BaseException) -> str:
    text = str(exc).strip() or type(exc).__name__
    return text.splitlines()[0]


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
        return ", ".join(
            f"{t.name} ({t.msgtype})" for t in sorted(self.topics.values(), key=lambda t: t.name)
        )

    def raw_messages(
        self, topics: Collection[str], start: int | None = None, stop: int | None = None
    ) -> Iterator[tuple[str, int, bytes]]:
        """``(topic, bag_time_ns, raw bytes)`` of ``topics`` in bag-time order."""
        conns = [c for c in self._conns if c.topic in topics]
        if not conns:
            return
        try:
            for conn, t, raw in self._reader.messages([c.handle for c in conns], start, stop):
                yield conn.topic, t, raw
        except DatasetError:
            raise
        except (*BAG_IO_ERRORS, BagScanError) as exc:
            raise DatasetError(
                f"{self.path}: corrupt bag, reading messages failed ({first_line(exc)})"
            ) from None

    def messages(
        self, topics: Collection[str], start: int | None = None, stop: int | None = None
    ) -> Iterator[tuple[str, int, Any]]:
        """``(topic, bag_time_ns, message)`` of ``topics`` in bag-time order, decoded."""
        for topic, t, raw in self.raw_messages(topics, start, stop):
            decode = self._decoder(topic)
            try:
                msg = decode(raw)
            except BAG_IO_ERRORS as exc:
                raise DatasetError(
                    f"{self.path}: topic {topic}: a message cannot be decoded as "
                    f"{self.topics[topic].msgtype} ({first_line(exc)})"
                ) from None
            yield topic, t, msg

    def _decoder(self, topic: str):
        conn = next(c for c in self._conns if c.topic == topic)
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
        if conn.msgdef_format == MessageDefinitionFormat.NONE or not conn.msgdef:
            if conn.msgtype in standard.fielddefs:
                self.notes.append(
                    f"{conn.topic}: hash {conn.digest} differs from the standard {conn.msgtype} and the bag "
                    "embeds no definition; decoded with the standard definition"
                )
                return standard
            raise DatasetError(
                f"{self.path}: topic {conn.topic}: unknown message type {conn.msgtype} "
                "and no definition in the bag"
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
                f"{self.path}: topic {conn.topic}: the bag's definition of {conn.msgtype} does not parse "
                f"({first_line(exc)}) and its hash {conn.digest} is not the standard one"
            ) from None
        if conn.digest and have != conn.digest:
            raise DatasetError(
                f"{self.path}: topic {conn.topic}: the bag's definition of {conn.msgtype} hashes to {have}, "
                f"not to the declared {conn.digest}"
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


def open_ros1(path: Path) -> Bag:
    """Open a ROS1 bag; a damaged index falls back to scanning the chunks."""
    if not path.is_file():
        raise DatasetError(f"{path}: no such file" if not path.exists() else f"{path}: not a file")
    reader = rosbag1.Reader(path)
    try:
        reader.open()
    except BAG_IO_ERRORS as strict_error:
        try:
            scanned = ChunkScanBag(path)
        except BagScanError as exc:
            if exc.truncated:
                raise DatasetError(f"{path}: truncated ROS1 bag ({exc})") from None
            raise DatasetError(
                f"{path}: corrupt ROS1 bag ({exc}; strict reader: {first_line(strict_error)})"
            ) from None
        except OSError as exc:
            raise DatasetError(f"{path}: cannot read ({exc.strerror})") from None
        conns = [
            _Conn(c.topic, c.msgtype, c.md5sum, MessageDefinitionFormat.MSG, c.msgdef, c.id)
            for c in scanned.connections.values()
        ]
        counts = scanned.message_counts()
        bag = Bag(path, "ros1", _topics_of(conns, [counts[c.handle] for c in conns]), _conns=conns)
        bag._reader = scanned
        bag.notes.append(
            f"damaged index bypassed by scanning the chunks (strict reader: {first_line(strict_error)})"
        )
        bag.notes.extend(scanned.notes)
        return bag
    conns = [
        _Conn(c.topic, c.msgtype, c.digest, c.msgdef.format, c.msgdef.data, c) for c in reader.connections
    ]
    bag = Bag(path, "ros1", _topics_of(conns, [c.handle.msgcount for c in conns]), _conns=conns)
    bag._reader = reader
    return bag


def open_ros2(path: Path) -> Bag:
    """Open a ROS2 bag: a folder with ``metadata.yaml``, or a single ``.mcap`` / ``.db3`` file."""
    if not path.exists():
        raise DatasetError(f"{path}: no such file or directory")
    try:
        reader = rosbag2.Reader(path)
        reader.open()
    except (*BAG_IO_ERRORS, FileNotFoundError) as exc:
        raise DatasetError(f"{path}: corrupt or unreadable ROS2 bag ({first_line(exc)})") from None
    conns = [
        _Conn(c.topic, c.msgtype, c.digest or "", c.msgdef.format, c.msgdef.data, c)
        for c in reader.connections
    ]
    bag = Bag(path, "ros2", _topics_of(conns, [c.handle.msgcount for c in conns]), _conns=conns)
    bag._reader = reader
    return bag


def open_bag(path: Path, kind: BagKind) -> Bag:
    """Open the bag at ``path`` as ``kind``; use it as a context manager."""
    return open_ros1(path) if kind == "ros1" else open_ros2(path)
