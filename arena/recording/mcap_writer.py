"""An MCAP writer for many small messages.

mcap's own `Writer` spends about 5 us on each message (a record object, a buffer seek to patch
the length, index bookkeeping); a recording of 100 robots makes tens of thousands a second.
Here a message is one `struct.pack` into the open chunk's buffer. Every other record (header,
schemas, channels, metadata, chunks, the summary and footer) is built by mcap's own record
classes, so the file is plain MCAP: readable by mcap's readers and by Foxglove.

Layout: schemas, channels and metadata go into the data section when they are registered,
before any chunk that uses them, so a reader of a cut file still knows every channel it
meets. The summary repeats schemas and channels and lists statistics, chunk indexes and
metadata indexes, with summary offsets. No message indexes: readers find messages through the
chunk indexes, and a long recording would otherwise hold an index entry per channel per chunk
in memory until it ends.
"""

from __future__ import annotations

import struct
import zlib
from collections import Counter
from collections.abc import Iterable, Sequence
from typing import IO, Protocol

import zstandard
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)

MAGIC = b"\x89MCAP0\r\n"
#: A message record's head: opcode, length, channel id, sequence, log time, publish time.
_MESSAGE_HEAD = struct.Struct("<BQHIQQ")
_MESSAGE_FIXED = _MESSAGE_HEAD.size - 9  # the body's fixed part (the record length excludes 9)
_MESSAGE = int(Opcode.MESSAGE)
#: zstd's level 1: chunks of JSON records come out ~5 % larger than at the default level 3,
#: for half the time (the recording process's largest single cost at ~0.1 us a record).
_compress = zstandard.ZstdCompressor(level=1).compress


class _Record(Protocol):
    """Any of mcap's record classes."""

    def write(self, stream: RecordBuilder) -> None: ...


class ChunkedWriter:
    """Writes one MCAP file to `stream` (seekable or not), zstd chunks of about `chunk_size`."""

    def __init__(self, stream: IO[bytes], *, chunk_size: int = 64 * 1024) -> None:
        self._stream = stream
        self._offset = 0  # bytes written so far (the stream need not tell)
        self.chunk_size = chunk_size
        self._chunk = bytearray()
        self._chunk_start = 0  # log times of the messages in the open chunk
        self._chunk_end = 0
        self._schemas: list[Schema] = []
        self._channels: list[Channel] = []
        self._chunk_indexes: list[ChunkIndex] = []
        self._metadata_indexes: list[MetadataIndex] = []
        self._counts: Counter[int] = Counter()

    def start(self, profile: str, library: str) -> None:
        """The magic and the header."""
        self._write(MAGIC)
        self._write_record(Header(profile=profile, library=library))

    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        """A new schema; its id (from 1)."""
        schema = Schema(id=len(self._schemas) + 1, name=name, encoding=encoding, data=data)
        self._schemas.append(schema)
        self._write_record(schema)
        return schema.id

    def register_channel(self, topic: str, message_encoding: str, schema_id: int) -> int:
        """A new channel; its id (from 0)."""
        channel = Channel(
            id=len(self._channels),
            topic=topic,
            message_encoding=message_encoding,
            schema_id=schema_id,
            metadata={},
        )
        self._channels.append(channel)
        self._write_record(channel)
        return channel.id

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """A metadata record (indexed in the summary)."""
        offset = self._offset
        length = self._write_record(Metadata(name=name, metadata=data))
        self._metadata_indexes.append(MetadataIndex(offset=offset, length=length, name=name))

    def add_message(self, channel_id: int, log_time: int, data: bytes) -> None:
        """A message (its publish time is its log time); the chunk closes once it is full."""
        self.add_messages(((channel_id, log_time, data),))

    def add_messages(self, messages: Iterable[tuple[int, int, bytes]]) -> None:
        """Messages as (channel id, log time, data), in one loop: the recording process
        writes every record through it, and a call per record cost as much as the record."""
        chunk, counts, pack, size = self._chunk, self._counts, _MESSAGE_HEAD.pack, self.chunk_size
        for channel_id, log_time, data in messages:
            if not chunk:
                self._chunk_start = self._chunk_end = log_time
            elif log_time < self._chunk_start:
                self._chunk_start = log_time
            elif log_time > self._chunk_end:
                self._chunk_end = log_time
            chunk += pack(_MESSAGE, _MESSAGE_FIXED + len(data), channel_id, 0, log_time, log_time)
            chunk += data
            counts[channel_id] += 1
            if len(chunk) >= size:
                self.close_chunk()  # (empties `chunk` in place)

    def close_chunk(self) -> None:
        """Compress the open chunk and write it (nothing if it holds no message)."""
        if not self._chunk:
            return
        data = bytes(self._chunk)
        self._chunk.clear()
        compressed = _compress(data)
        chunk = Chunk(
            message_start_time=self._chunk_start,
            message_end_time=self._chunk_end,
            uncompressed_size=len(data),
            uncompressed_crc=zlib.crc32(data),
            compression="zstd",
            data=compressed,
        )
        start = self._offset
        length = self._write_record(chunk)
        self._chunk_indexes.append(
            ChunkIndex(
                message_start_time=chunk.message_start_time,
                message_end_time=chunk.message_end_time,
                chunk_start_offset=start,
                chunk_length=length,
                message_index_offsets={},
                message_index_length=0,
                compression="zstd",
                compressed_size=len(compressed),
                uncompressed_size=len(data),
            )
        )

    def flush(self) -> None:
        """Close the open chunk and hand everything to the OS."""
        self.close_chunk()
        self._stream.flush()

    def finish(self) -> None:
        """The last chunk, the end of the data section, the summary and the footer."""
        self.close_chunk()
        self._write_record(DataEnd(data_section_crc=0))
        summary_start = self._offset
        summary = RecordBuilder()
        offsets: list[SummaryOffset] = []
        chunks = self._chunk_indexes
        statistics = Statistics(
            message_count=sum(self._counts.values()),
            schema_count=len(self._schemas),
            channel_count=len(self._channels),
            attachment_count=0,
            metadata_count=len(self._metadata_indexes),
            chunk_count=len(self._chunk_indexes),
            message_start_time=min((c.message_start_time for c in chunks), default=0),
            message_end_time=max((c.message_end_time for c in chunks), default=0),
            channel_message_counts=dict(self._counts),
        )
        groups: list[tuple[Opcode, Sequence[_Record]]] = [
            (Opcode.SCHEMA, self._schemas),
            (Opcode.CHANNEL, self._channels),
            (Opcode.STATISTICS, [statistics]),
            (Opcode.CHUNK_INDEX, self._chunk_indexes),
            (Opcode.METADATA_INDEX, self._metadata_indexes),
        ]
        for opcode, records in groups:
            if not records:
                continue
            group_start = summary.count
            for record in records:
                record.write(summary)
            offsets.append(
                SummaryOffset(
                    group_opcode=opcode,
                    group_start=summary_start + group_start,
                    group_length=summary.count - group_start,
                )
            )
        summary_offset_start = summary_start + summary.count
        for offset in offsets:
            offset.write(summary)
        self._write(summary.end())
        footer = Footer(
            summary_start=summary_start,
            summary_offset_start=summary_offset_start,
            summary_crc=0,
        )
        self._write_record(footer)
        self._write(MAGIC)
        self._stream.flush()

    def _write_record(self, record: _Record) -> int:
        builder = RecordBuilder()
        record.write(builder)
        data = builder.end()
        self._write(data)
        return len(data)

    def _write(self, data: bytes) -> None:
        self._stream.write(data)
        self._offset += len(data)
