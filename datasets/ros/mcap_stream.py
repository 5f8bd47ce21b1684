"""One big message into an MCAP bag, written as it is produced, without holding it in memory.

``rosbags``' MCAP writer holds a message three more times before it reaches the file: its record, the
pending chunk and the chunk's uncompressed copy that it hands to zstd. A building's GridMap is hundreds of
megabytes (15 M cells x 7 float32 layers for fr-clinic), so writing one took several times that at once, on
machines where memory the process has not touched before is slow to get (docs/evaluation.md, "Memory is time
on some machines"). :func:`write_streamed` writes such a message as an MCAP chunk of its own, its bytes
passed in pieces through a streaming zstd compressor straight into the file, with the records the MCAP
specification asks for (chunk, message index, chunk index entry) and the same bookkeeping as
``McapWriter.close_chunk``, so the bag's summary and ``metadata.yaml`` count it. The chunk's CRC-32 is
computed, so readers check it.

It relies on the internals of ``rosbags.rosbag2.storage_mcap.McapWriter`` (version pinned in
``pyproject.toml``); :func:`streaming_storage` returns None when a writer does not look as expected, and the
caller writes the message whole. Tests read streamed messages back and compare their bytes.
"""

from __future__ import annotations

import sys
import zlib
from collections.abc import Iterable
from io import BytesIO
from typing import Any

from rosbags.rosbag2 import Writer as Rosbag2Writer
from rosbags.rosbag2.storage_mcap import (
    McapWriter,
    write_record,
    write_string,
    write_uint16,
    write_uint32,
    write_uint64,
)

if sys.version_info >= (3, 14):
    from compression import zstd
else:  # rosbags' own choice of zstd binding
    from backports import zstd

OP_MESSAGE = 0x05
OP_CHUNK = 0x06
OP_MESSAGE_INDEX = 0x07
MESSAGE_HEADER_BYTES = 2 + 4 + 8 + 8  # channel id, sequence, log time, publish time
_PENDING_ATTRIBUTES = ("bio", "chunk", "chunks", "channel_stats", "message_start_time", "message_end_time")


def streaming_storage(raw: Any) -> McapWriter | None:
    """The MCAP storage of an open ``rosbags`` ROS2 writer when :func:`write_streamed` can write into it
    (zstd or no chunk compression, the writer's known attributes present), else None."""
    if not isinstance(raw, Rosbag2Writer):
        return None
    storage = getattr(raw, "storage", None)
    if type(storage) is not McapWriter or not all(hasattr(storage, a) for a in _PENDING_ATTRIBUTES):
        return None
    if getattr(storage, "compression", None) not in ("", "zstd"):
        return None
    if not all(hasattr(raw, a) for a in ("counts", "min_timestamp", "max_timestamp")):
        return None
    return storage


def write_streamed(
    raw: Rosbag2Writer, connection: Any, stamp_ns: int, pieces: Iterable[bytes | memoryview], size: int
) -> None:
    """Append one message of ``size`` bytes, the concatenation of ``pieces``, on ``connection`` at
    ``stamp_ns`` as an MCAP chunk of its own (compressed like the bag's other chunks).

    ``raw`` must have a :func:`streaming_storage`. ValueError when the pieces do not add up to ``size``
    (the bag is then damaged; the caller's partial-write handling discards it).
    """
    storage = streaming_storage(raw)
    if storage is None:
        raise ValueError("the writer has no MCAP storage that can be streamed into")
    # Records pending in rosbags' chunk: closed as a chunk of their own when they include messages, else (the
    # schema and channel records of a new topic) moved to the front of this message's chunk.
    prefix = b""
    if storage.chunk.msgs:
        storage.close_chunk()
    elif storage.chunk.bio.tell():
        prefix = storage.chunk.bio.getvalue()
        storage.chunk.bio = BytesIO()
    cid = int(connection.id)
    bio = storage.bio
    message_record = BytesIO()
    message_record.write(OP_MESSAGE.to_bytes(1, "little"))
    write_uint64(message_record, MESSAGE_HEADER_BYTES + size)
    write_uint16(message_record, cid)
    write_uint32(message_record, 0)
    write_uint64(message_record, stamp_ns)
    write_uint64(message_record, stamp_ns)
    uncompressed_size = len(prefix) + message_record.tell() + size

    chunk_start = bio.tell()
    bio.write(OP_CHUNK.to_bytes(1, "little"))
    length_at = bio.tell()
    write_uint64(bio, 0)  # the chunk record's length, known at the end
    write_uint64(bio, stamp_ns)
    write_uint64(bio, stamp_ns)
    write_uint64(bio, uncompressed_size)
    crc_at = bio.tell()
    write_uint32(bio, 0)  # the CRC-32 of the uncompressed records, known at the end
    write_string(bio, storage.compression)
    compressed_size_at = bio.tell()
    write_uint64(bio, 0)  # the compressed size, known at the end
    data_start = bio.tell()

    compressor = None
    if storage.compression == "zstd":
        compressor = zstd.ZstdCompressor()
        compressor.set_pledged_input_size(uncompressed_size)
    crc = 0

    def put(piece: bytes | memoryview) -> None:
        nonlocal crc
        crc = zlib.crc32(piece, crc)
        bio.write(piece if compressor is None else compressor.compress(piece))

    put(prefix)
    put(message_record.getbuffer())
    written = 0
    for p in pieces:
        piece = memoryview(p).cast("B")
        written += len(piece)
        if written > size:  # checked before zstd sees more than it was promised
            break
        put(piece)
    if written != size:
        held = f"at least {written}" if written > size else str(written)
        raise ValueError(f"the message's pieces hold {held} bytes, not the {size} announced")
    if compressor is not None:
        bio.write(compressor.flush())
    chunk_end = bio.tell()
    bio.seek(length_at)
    write_uint64(bio, chunk_end - length_at - 8)
    bio.seek(crc_at)
    write_uint32(bio, crc)
    bio.seek(compressed_size_at)
    write_uint64(bio, chunk_end - data_start)
    bio.seek(chunk_end)

    index_at = bio.tell()
    index = BytesIO()
    write_uint16(index, cid)
    write_uint32(index, 16)
    write_uint64(index, stamp_ns)
    write_uint64(index, len(prefix))  # the message's offset in the uncompressed chunk
    write_record(bio, OP_MESSAGE_INDEX, index)

    entry = BytesIO()  # the chunk index entry, written with the summary when the bag closes
    write_uint64(entry, stamp_ns)
    write_uint64(entry, stamp_ns)
    write_uint64(entry, chunk_start)
    write_uint64(entry, chunk_end - chunk_start)
    write_uint32(entry, 10)
    write_uint16(entry, cid)
    write_uint64(entry, index_at)
    write_uint64(entry, bio.tell() - chunk_end)
    write_string(entry, storage.compression)
    write_uint64(entry, chunk_end - data_start)
    write_uint64(entry, uncompressed_size)
    storage.chunks.append(entry)

    storage.message_start_time = min(stamp_ns, storage.message_start_time)
    storage.message_end_time = max(stamp_ns, storage.message_end_time)
    storage.channel_stats[cid] += 1
    raw.counts[cid] += 1
    raw.min_timestamp = min(stamp_ns, raw.min_timestamp)
    raw.max_timestamp = max(stamp_ns, raw.max_timestamp)
