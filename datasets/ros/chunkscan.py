"""Reading a ROS1 bag whose index is damaged, by scanning its chunks (fallback of :mod:`datasets.ros.bag`).

A ROS1 v2.0 bag is a sequence of records ``<header_len><header><data_len><data>``: the bag header, then
chunks (each followed by one index record per connection), then the index section (connections and chunk
infos) at ``index_pos``. Strict readers trust the per-chunk index records; when one of them declares a wrong
length (``lsm-demo/demo.bag``) they fail. This scanner never uses the index records' contents: it reads
every chunk, takes each message's connection and time from the message's own record header, skips an index
record by its entry ``count`` (12 bytes each), and then cross-checks what it found against the index
section (number of chunks, their positions, per-connection message counts). Anything inconsistent raises
:class:`BagScanError`; a file shorter than its declared structure is reported as truncated. It never
guesses: it reads the bag exactly or refuses it.
"""

from __future__ import annotations

import bz2
import mmap
import struct
from collections.abc import Collection, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import lz4.frame
from rosbags.rosbag1.reader import normalize as normalize_topic
from rosbags.typesys.msg import normalize_msgtype

from datasets.errors import first_line, shown

OP_MSGDATA = 2
OP_BAGHEADER = 3
OP_IDXDATA = 4
OP_CHUNK = 5
OP_CHUNK_INFO = 6
OP_CONNECTION = 7
MAGIC = b"#ROSBAG V2.0\n"

_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")
_TIME = struct.Struct("<II")
_DECOMPRESS_STEP = 1 << 24  # bytes decompressed per step: allocation follows the data, not a size field


class BagScanError(Exception):
    """The bag cannot be read exactly; ``truncated`` tells a short file from a corrupt one."""

    def __init__(self, message: str, truncated: bool = False) -> None:
        super().__init__(message)
        self.truncated = truncated


@dataclass(frozen=True)
class ScannedConnection:
    id: int
    topic: str
    msgtype: str  # normalized, e.g. sensor_msgs/msg/LaserScan
    md5sum: str
    msgdef: str


@dataclass(frozen=True)
class _Chunk:
    data_pos: int
    data_len: int
    size: int
    compression: bytes  # the header field as found: b"none", b"bz2", b"lz4" or anything a damaged bag holds


def _parse_fields(block: bytes | memoryview, where: str) -> dict[str, bytes]:
    fields: dict[str, bytes] = {}
    pos, n = 0, len(block)
    while pos < n:
        if pos + 4 > n:
            raise BagScanError(f"{where}: header field length overruns the header")
        (flen,) = _U32.unpack_from(block, pos)
        pos += 4
        if pos + flen > n:
            raise BagScanError(f"{where}: header field overruns the header")
        name, sep, value = bytes(block[pos : pos + flen]).partition(b"=")
        if not sep:
            raise BagScanError(f"{where}: header field without '='")
        fields[name.decode("latin-1")] = value
        pos += flen
    return fields


def _u32(fields: dict[str, bytes], key: str, where: str) -> int:
    try:
        return _U32.unpack(fields[key])[0]
    except (KeyError, struct.error):
        raise BagScanError(f"{where}: missing or malformed field '{key}'") from None


def _record(buf: bytes | mmap.mmap | memoryview, pos: int, end: int, where: str, truncated_ok: bool):
    """(fields, data_pos, data_len) of the record at ``pos``; the record must end before ``end``."""

    def short(what: str) -> BagScanError:
        return BagScanError(f"{where} at byte {pos}: {what}", truncated=truncated_ok)

    if pos + 4 > end:
        raise short("record header length cut off")
    (hlen,) = _U32.unpack_from(buf, pos)
    if pos + 4 + hlen + 4 > end:
        raise short(f"record header of {hlen} bytes runs past the end")
    # a copy, never a view: a view into the mmap would keep it from closing when this record is refused
    fields = _parse_fields(bytes(buf[pos + 4 : pos + 4 + hlen]), f"{where} at byte {pos}")
    dpos = pos + 4 + hlen
    (dlen,) = _U32.unpack_from(buf, dpos)
    return fields, dpos + 4, dlen


def _op(fields: dict[str, bytes], where: str) -> int:
    op = fields.get("op")
    if op is None or len(op) != 1:
        raise BagScanError(f"{where}: record without an op code")
    return op[0]


def _connection(fields: dict[str, bytes], data: bytes | memoryview, where: str) -> ScannedConnection:
    conn = _u32(fields, "conn", where)
    info = _parse_fields(data, where)
    try:
        topic = normalize_topic(fields["topic"].decode())
        msgtype = info["type"].decode()
        md5 = info["md5sum"].decode()
        msgdef = info.get("message_definition", b"").decode()
    except (KeyError, IndexError, UnicodeDecodeError):
        raise BagScanError(f"{where}: connection record without topic, type or md5sum") from None
    return ScannedConnection(conn, topic, normalize_msgtype(msgtype), md5, msgdef)


def _decompress(raw: bytes, compression: bytes, size: int, where: str) -> bytes:
    """``raw`` decompressed; more than the declared ``size`` bytes is an error (never decompressed)."""
    if compression == b"none":
        return raw
    if compression == b"bz2":
        decompressor: Any = bz2.BZ2Decompressor()
    elif compression == b"lz4":
        decompressor = lz4.frame.LZ4FrameDecompressor()
    else:
        raise BagScanError(f"{where}: unsupported compression {shown(compression)}")
    name = compression.decode("ascii")
    parts: list[bytes] = []
    total = 0
    data = raw
    try:
        while not decompressor.eof:
            part = decompressor.decompress(data, max_length=min(size + 1 - total, _DECOMPRESS_STEP))
            data = b""
            parts.append(part)
            total += len(part)
            if total > size:
                raise BagScanError(f"{where}: decompresses to more than the {size} bytes its header declares")
            if not part and decompressor.needs_input:
                raise BagScanError(f"{where}: {name} data is cut off")
    except (OSError, ValueError, RuntimeError, EOFError, MemoryError) as exc:
        raise BagScanError(f"{where}: {name} data does not decompress ({first_line(exc)})") from None
    return b"".join(parts)


def first_overrun(path: Path) -> str | None:
    """Where a top-level record of the ROS1 bag at ``path`` declares more bytes than the file holds, or None.

    A cheap walk over the record lengths (nothing else is read), done before the strict reader, which
    allocates whatever a length field asks for (4 GiB from a damaged u32) before it finds the file shorter.
    """
    size = path.stat().st_size
    with path.open("rb") as fh:
        if fh.read(len(MAGIC)) != MAGIC:
            return None  # not a bag at all: the readers say so
        pos = len(MAGIC)
        while pos < size:
            fh.seek(pos)
            head = fh.read(4)
            if len(head) < 4:
                return f"record at byte {pos}: its header length is cut off"
            (hlen,) = _U32.unpack(head)
            if pos + 4 + hlen + 4 > size:
                return f"record at byte {pos}: its header of {hlen} bytes runs past the end of the file"
            fh.seek(pos + 4 + hlen)
            (dlen,) = _U32.unpack(fh.read(4))
            if pos + 8 + hlen + dlen > size:
                return f"record at byte {pos}: its data of {dlen} bytes runs past the end of the file"
            pos += 8 + hlen + dlen
    return None


class ChunkScanBag:
    """A ROS1 bag read by scanning its chunks; ``messages`` yields ``(connection, time_ns, raw bytes)``.

    ``notes`` lists the index damage that was bypassed (one line each).
    """

    def __init__(self, path: Path) -> None:
        self.path = path
        self.notes: list[str] = []
        self.connections: dict[int, ScannedConnection] = {}
        self._chunks: list[_Chunk] = []
        self._chunk_pos: list[int] = []  # file position of each chunk record
        # per message: time_ns, connection id, chunk index, offset in the chunk, length
        self._messages: list[tuple[int, int, int, int, int]] = []
        with path.open("rb") as fh:
            self._size = path.stat().st_size
            if self._size == 0:
                raise BagScanError("empty file", truncated=True)
            self._buf = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ)
        try:
            self._scan()
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        """Release the file mapping (left to the garbage collector while a view of it is alive)."""
        try:
            self._buf.close()
        except BufferError:
            pass

    # -- scanning -------------------------------------------------------------------------------------

    def _scan(self) -> None:
        buf, size = self._buf, self._size
        if buf[: len(MAGIC)] != MAGIC:
            raise BagScanError("not a ROS1 v2.0 bag (bad magic line)")
        fields, dpos, dlen = _record(buf, len(MAGIC), size, "bag header", True)
        if _op(fields, "bag header") != OP_BAGHEADER:
            raise BagScanError("the first record is not a bag header")
        raw_index_pos = fields.get("index_pos", b"")
        if len(raw_index_pos) != 8:
            raise BagScanError("bag header without index_pos")
        (index_pos,) = _U64.unpack(raw_index_pos)
        conn_count = _u32(fields, "conn_count", "bag header")
        chunk_count = _u32(fields, "chunk_count", "bag header")
        if index_pos == 0:
            raise BagScanError("not indexed: the recording was not closed (try `rosbag reindex`)")
        if index_pos > size:
            raise BagScanError(f"{size} bytes, but its index starts at byte {index_pos}", True)
        pos = dpos + dlen
        chunk_counts: list[dict[int, int]] = []
        while pos < index_pos:
            fields, dpos, dlen = _record(buf, pos, index_pos, "record", False)
            op = _op(fields, f"record at byte {pos}")
            if op == OP_CHUNK:
                where = f"chunk at byte {pos}"
                if dpos + dlen > index_pos:
                    raise BagScanError(f"{where}: its data runs into the index")
                compression = fields.get("compression", b"")
                chunk = _Chunk(dpos, dlen, _u32(fields, "size", where), compression)
                counts = self._scan_chunk(len(self._chunks), chunk, pos, where)
                self._chunks.append(chunk)
                self._chunk_pos.append(pos)
                chunk_counts.append(counts)
                pos = dpos + dlen
            elif op == OP_IDXDATA:
                where = f"index record at byte {pos}"
                count = _u32(fields, "count", where)
                if dlen != 12 * count:
                    self.notes.append(f"{where} declares {dlen} bytes for {count} entries; used {12 * count}")
                pos = dpos + 12 * count
            elif op == OP_CONNECTION:
                if dpos + dlen > index_pos:
                    raise BagScanError(f"connection at byte {pos}: its data runs into the index")
                c = _connection(fields, buf[dpos : dpos + dlen], f"connection at byte {pos}")
                self.connections.setdefault(c.id, c)
                pos = dpos + dlen
            else:
                raise BagScanError(f"unexpected record (op {op}) at byte {pos} before the index")
        if pos != index_pos:
            raise BagScanError(f"records end at byte {pos}, not at the index (byte {index_pos})")
        self._check_index(index_pos, conn_count, chunk_count, chunk_counts)
        self._messages.sort(key=lambda m: m[0])  # stable: file order among equal times

    def _scan_chunk(self, index: int, chunk: _Chunk, pos: int, where: str) -> dict[int, int]:
        data = self._chunk_data(chunk, where)
        counts: dict[int, int] = {}
        ipos, n = 0, len(data)
        while ipos < n:
            fields, dpos, dlen = _record(data, ipos, n, f"{where}, inner record", False)
            if dpos + dlen > n:
                raise BagScanError(f"{where}: inner record at offset {ipos} runs past the chunk")
            op = _op(fields, f"{where}, inner record at offset {ipos}")
            if op == OP_MSGDATA:
                conn = _u32(fields, "conn", where)
                t = fields.get("time", b"")
                if len(t) != 8:
                    raise BagScanError(f"{where}: message at offset {ipos} without a time")
                sec, nsec = _TIME.unpack(t)
                self._messages.append((sec * 1_000_000_000 + nsec, conn, index, dpos, dlen))
                counts[conn] = counts.get(conn, 0) + 1
            elif op == OP_CONNECTION:
                c = _connection(fields, data[dpos : dpos + dlen], f"{where}, connection")
                self.connections.setdefault(c.id, c)
            else:
                raise BagScanError(f"{where}: unexpected inner record (op {op}) at offset {ipos}")
            ipos = dpos + dlen
        return counts

    def _check_index(
        self, index_pos: int, conn_count: int, chunk_count: int, chunk_counts: list[dict[int, int]]
    ) -> None:
        buf, size = self._buf, self._size
        pos = index_pos
        for _ in range(conn_count):
            fields, dpos, dlen = _record(buf, pos, size, "index connection", True)
            if dpos + dlen > size:
                raise BagScanError(f"index connection at byte {pos} runs past the end", True)
            c = _connection(fields, buf[dpos : dpos + dlen], f"index connection at byte {pos}")
            self.connections.setdefault(c.id, c)
            pos = dpos + dlen
        if len(self._chunks) != chunk_count:
            raise BagScanError(f"found {len(self._chunks)} chunks but the bag header declares {chunk_count}")
        for i in range(chunk_count):
            where = f"chunk info at byte {pos}"
            fields, dpos, dlen = _record(buf, pos, size, "chunk info", True)
            if _op(fields, where) != OP_CHUNK_INFO or dpos + dlen > size:
                raise BagScanError(f"{where}: not a complete chunk info record", True)
            chunk_pos = _U64.unpack(fields.get("chunk_pos", b"\0" * 8))[0]
            count = _u32(fields, "count", where)
            if chunk_pos != self._chunk_pos[i] or dlen != 8 * count:
                raise BagScanError(f"{where}: does not describe chunk {i} at byte {self._chunk_pos[i]}")
            declared = {
                _U32.unpack_from(buf, dpos + 8 * k)[0]: _U32.unpack_from(buf, dpos + 8 * k + 4)[0]
                for k in range(count)
            }
            if declared != chunk_counts[i]:
                found = shown(chunk_counts[i])
                raise BagScanError(
                    f"{where}: declares message counts {shown(declared)} but the chunk holds {found}"
                )
            pos = dpos + dlen
        unknown = {m[1] for m in self._messages} - self.connections.keys()
        if unknown:
            raise BagScanError(f"messages of undeclared connections {shown(sorted(unknown))}")

    def _chunk_data(self, chunk: _Chunk, where: str) -> bytes:
        raw = self._buf[chunk.data_pos : chunk.data_pos + chunk.data_len]
        data = _decompress(raw, chunk.compression, chunk.size, where)
        if len(data) != chunk.size:
            raise BagScanError(f"{where}: {len(data)} bytes after decompression, header says {chunk.size}")
        return data

    # -- reading --------------------------------------------------------------------------------------

    def message_counts(self) -> dict[int, int]:
        counts: dict[int, int] = dict.fromkeys(self.connections, 0)
        for m in self._messages:
            counts[m[1]] += 1
        return counts

    def messages(
        self, connection_ids: Collection[int], start: int | None = None, stop: int | None = None
    ) -> Iterator[tuple[ScannedConnection, int, bytes]]:
        """Messages of ``connection_ids`` in time order, with ``start <= time < stop``."""
        wanted = set(connection_ids)
        cached: tuple[int, bytes] = (-1, b"")
        for time_ns, conn, chunk_index, offset, length in self._messages:
            if conn not in wanted or (start is not None and time_ns < start):
                continue
            if stop is not None and time_ns >= stop:
                break
            if cached[0] != chunk_index:
                chunk = self._chunks[chunk_index]
                cached = (chunk_index, self._chunk_data(chunk, f"chunk {chunk_index}"))
            yield self.connections[conn], time_ns, cached[1][offset : offset + length]
