"""MCAP files, synchronously: the writer (run in a worker thread) and a forgiving reader.

The writer keeps chunks small and is flushed often, so a process killed mid-recording loses at
most the last flush interval; the reader reads every complete record of such a file. While a
file is written its writer holds an exclusive `flock` on it: a file without its footer is *in
progress* while that lock is held and *truncated* (its writer gone) once it is not.
"""

from __future__ import annotations

import contextlib
import datetime
import fcntl
import functools
import json
import re
import struct
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import zstandard
from mcap.exceptions import McapError
from mcap.records import Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader

from arena.protocol.errors import ArenaError, ErrorCode
from arena.protocol.rest import DEFAULT_TENANT
from arena.recording import images
from arena.recording.mcap_writer import ChunkedWriter
from arena.recording.records import (
    CAMERA_PREFIX,
    RECORD_TYPES,
    is_view_topic,
    schema_of,
    split_topic,
    topic,
)

SUFFIX = ".mcap"
PROFILE = "arena"


def new_file_name(now: float | None = None, tenant: str | None = None) -> str:
    """`arena-YYYYmmdd-HHMMSS-mmm.mcap` from the start time (UTC); a tenant's other than
    the default's ends in `.TENANT.mcap`."""
    stamp = datetime.datetime.fromtimestamp(now or time.time(), datetime.UTC)
    whose = "" if tenant in (None, DEFAULT_TENANT) else f".{tenant}"
    return f"arena-{stamp:%Y%m%d-%H%M%S}-{stamp.microsecond // 1000:03d}{whose}{SUFFIX}"


_NAMED = re.compile(r"arena-\d{8}-\d{6}-\d{3}(?:\.(?P<tenant>[^/]+))?" + re.escape(SUFFIX))


def tenant_in_name(name: str) -> str | None:
    """The tenant a recorder's file name says (`new_file_name`): the `.TENANT` part, the
    default tenant without one; None for a name the recorder does not give."""
    named = _NAMED.fullmatch(name)
    if named is None:
        return None
    return named["tenant"] or DEFAULT_TENANT


#: One record to write: (robot id, kind, JSON bytes, log time in ns).
Item = tuple[str, str, bytes, int]


@dataclass(frozen=True)
class FileSeries:
    """Where a recorder's files go and when a new one starts (by size or age)."""

    folder: Path
    metadata: dict[str, str]  # written into every file
    max_bytes: int = 256 << 20
    max_seconds: float = 3600.0
    #: Foxglove's view beside the records: transforms, the 3D model and a log (`foxglove.py`).
    foxglove: bool = True
    #: Transforms of each tree at most this many a second (0: one per record).
    foxglove_rate: float = 30.0
    #: Whose robots the files hold (`writer_process.TenantFiles` gives each tenant its
    #: series); None: any robot's.
    tenant: str | None = None


class McapFileWriter:
    """Writes records into a rotating series of MCAP files in one folder. Not thread-safe:
    one thread at a time (the recorder's writer task guarantees it)."""

    def __init__(self, series: FileSeries, *, chunk_size: int = 64 * 1024) -> None:
        self.folder = series.folder
        self.metadata = series.metadata
        self.tenant = series.tenant
        self.max_bytes = series.max_bytes
        self.max_seconds = series.max_seconds
        self.chunk_size = chunk_size
        self.robots: dict[str, dict[str, str]] = {}  # robot id -> metadata, set by the recorder
        #: What a robot's first records in a file bring along (its 3D model), given its id
        #: and the log time.
        self.first_in_file: Callable[[str, int], list[Item]] | None = None
        self.path: Path | None = None
        self.files: list[Path] = []
        self._stream: IO[bytes] | None = None
        self._writer: ChunkedWriter | None = None
        self._opened_at = 0.0
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._robots_written: set[str] = set()
        #: (robot id, kind) -> channel id in the current file (the topic's name not made again)
        self._channel_ids: dict[tuple[str, str], int] = {}
        self.messages = 0
        self._flushed = False  # the current file has had a flush (a message is on disk)

    def write(self, items: list[Item], *, flush: bool = True) -> None:
        """Append records, opening or rotating files as needed, then (with `flush`) close the
        chunk in progress and hand it to the OS.

        On `OSError` (a full or vanished disk) the current file is abandoned and the error
        raised: the next call starts a fresh file.
        """
        try:
            writer = self._current() if items else None
            channels = self._channel_ids
            messages: list[tuple[int, int, bytes]] = []
            for robot_id, kind, data, log_time in items:
                channel = channels.get((robot_id, kind))
                if channel is None:  # a robot's first record of a kind in this file
                    assert writer is not None
                    writer.add_messages(messages)  # what came before goes first
                    messages = []
                    channel = self._first_of_kind(writer, robot_id, kind, log_time)
                messages.append((channel, log_time, data))
            if writer is not None:
                writer.add_messages(messages)
            self.messages += len(items)
            if flush:
                self.flush()
        except OSError:
            self.abandon()
            raise

    def flush(self) -> None:
        """Close the chunk in progress and hand everything to the OS."""
        if self._writer is not None:
            self._writer.flush()
            assert self._stream is not None
            self._flushed = True
            if (
                self._stream.tell() > self.max_bytes
                or time.monotonic() - self._opened_at > self.max_seconds
            ):
                self.close()

    def close(self) -> None:
        """Finish the current file (summary and index written)."""
        if self._writer is not None:
            self._writer.finish()
            assert self._stream is not None
            self._stream.close()
        self._writer = self._stream = None
        self.path = None

    def abandon(self) -> None:
        """Drop the current file without finishing it (after an I/O error). A file that
        never held a flushed message is removed: a full disk must not leave empty files."""
        if self._stream is not None:
            with contextlib.suppress(OSError):
                self._stream.close()
        if self.path is not None and not self._flushed:
            with contextlib.suppress(OSError):
                self.path.unlink()
            if self.path in self.files:
                self.files.remove(self.path)
        self._writer = self._stream = None
        self.path = None

    def _current(self) -> ChunkedWriter:
        if self._writer is None:
            self.folder.mkdir(parents=True, exist_ok=True)
            path = self.folder / new_file_name(tenant=self.tenant)
            while path.exists():  # two files within a millisecond: keep both
                path = path.with_name(path.stem + "-1" + SUFFIX)
            self._stream = open(path, "wb")  # noqa: SIM115 - closed in close()
            # Readers tell a file being written from a cut one by this lock; the kernel lets it
            # go when the file is closed or its process dies. A file system without locks
            # records all the same (its unfinished files then read as truncated).
            with contextlib.suppress(OSError):
                fcntl.flock(self._stream.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
            self.path = path  # before the first write, so that `abandon` can remove it
            self.files.append(path)
            self._flushed = False
            writer = ChunkedWriter(self._stream, chunk_size=self.chunk_size)
            writer.start(profile=PROFILE, library="arena")
            writer.add_metadata("arena", self.metadata)
            self._writer = writer
            self._opened_at = time.monotonic()
            self._schemas.clear()
            self._channels.clear()
            self._channel_ids.clear()
            self._robots_written.clear()
        return self._writer

    def _first_of_kind(self, writer: ChunkedWriter, robot_id: str, kind: str, log_time: int) -> int:
        """The channel of a robot's kind of record, new in this file; a robot's first record
        in the file brings its metadata and introduction (its 3D model) before it."""
        if robot_id not in self._robots_written and robot_id in self.robots:
            self._robots_written.add(robot_id)
            writer.add_metadata(f"robot/{robot_id}", self.robots[robot_id])
            for _, extra, payload, at in self._introduce(robot_id, log_time):
                writer.add_message(self._channel(writer, robot_id, extra), at, payload)
                self.messages += 1
        channel = self._channel_ids[robot_id, kind] = self._channel(writer, robot_id, kind)
        return channel

    def _introduce(self, robot_id: str, log_time: int) -> list[Item]:
        return [] if self.first_in_file is None else self.first_in_file(robot_id, log_time)

    def _channel(self, writer: ChunkedWriter, robot_id: str, kind: str) -> int:
        name = topic(robot_id, kind)
        channel = self._channels.get(name)
        if channel is None:
            schema_name, schema_encoding, schema_data, encoding = channel_format(kind)
            schema = self._schemas.get(schema_name)
            if schema is None:
                schema = writer.register_schema(schema_name, schema_encoding, schema_data)
                self._schemas[schema_name] = schema
            channel = writer.register_channel(name, encoding, schema)
            self._channels[name] = channel
        return channel


@functools.lru_cache(maxsize=64)
def channel_format(kind: str) -> tuple[str, str, bytes, str]:
    """(schema name, schema encoding, schema, message encoding) of a topic kind: Arena's
    records are JSON with JSON Schemas; Foxglove's kinds are protobuf with Foxglove's schemas.
    Made once per kind (~0.1 ms each), not once per robot and file."""
    if kind in RECORD_TYPES:
        return kind, "jsonschema", json.dumps(schema_of(kind)).encode(), "json"
    if kind.startswith(CAMERA_PREFIX):
        name, encoding, data = images.schema()
        return name, encoding, data, encoding
    from arena.recording import foxglove  # only a writer that records transforms needs it

    name, encoding, data = foxglove.schema(kind)
    return name, encoding, data, encoding


@dataclass
class RecordedMessage:
    """One message read back: where it came from and its decoded JSON."""

    topic: str
    robot_id: str
    kind: str
    log_time: int
    data: dict[str, Any]


@dataclass(frozen=True, slots=True)
class RawMessage:
    """A message kept as bytes (Foxglove's view of a robot): enough to write it again."""

    topic: str
    schema: tuple[str, str, bytes]  # name, encoding, data
    encoding: str
    log_time: int
    data: bytes


@dataclass
class Recording:
    """Everything in a file: metadata, schemas by topic, messages, and whether it was cut."""

    path: Path
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    schemas: dict[str, dict[str, Any]] = field(default_factory=dict)
    messages: list[RecordedMessage] = field(default_factory=list)
    #: Foxglove's topics of each robot (transforms, model, log), undecoded.
    views: list[RawMessage] = field(default_factory=list)
    #: No footer and no writer: the file was cut off (a killed writer, a copy in progress).
    truncated: bool = False
    #: No footer yet: its writer is still writing it (it holds the file's lock).
    in_progress: bool = False
    foreign_topics: int = 0

    @property
    def message_count(self) -> int:
        """Every message read: Arena's records and Foxglove's view (what `recover` writes)."""
        return len(self.messages) + len(self.views)


def read_recording(path: str | Path) -> Recording:
    """Read a whole recording, also one being written (`in_progress`) or whose writer was
    killed (`truncated`).

    Raises `ArenaError(INVALID_RECORDING)` for a file that is not MCAP at all.
    """
    path = Path(path)
    recording = Recording(path)
    try:
        stream = open(path, "rb")  # noqa: SIM115
    except OSError as exc:
        raise ArenaError(ErrorCode.INVALID_RECORDING, f"Cannot open {path}: {exc}") from exc
    with stream:
        if stream.read(8) != b"\x89MCAP0\r\n":
            raise ArenaError(
                ErrorCode.INVALID_RECORDING, f"{path.name} is not an MCAP file (bad magic)."
            )
        stream.seek(0)
        if not _read_into(recording, iter_records(stream)):
            recording.in_progress = being_written(stream)
            recording.truncated = not recording.in_progress
    return recording


def being_written(stream: IO[bytes]) -> bool:
    """True while a writer holds the lock of the file open as `stream` (see the module)."""
    try:
        fcntl.flock(stream.fileno(), fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    except OSError:  # a file system without locks: no telling, call it cut
        return False
    fcntl.flock(stream.fileno(), fcntl.LOCK_UN)
    return False


#: What reading a file cut mid-record raises: mcap's own errors, a short struct or length,
#: a truncated zstd frame, JSON cut mid-message. Anything else is a bug and is let out.
_CUT_FILE_ERRORS = (McapError, EOFError, struct.error, ValueError, zstandard.ZstdError)


def iter_records(stream: IO[bytes]) -> Iterator[Any]:
    """Every record of a stream, chunks opened; stops quietly where a record is cut off."""
    yield from StreamReader(stream).records


def _read_into(recording: Recording, records: Iterator[Any]) -> bool:
    """Fill `recording`; True when the file ended properly (with its footer)."""
    channels: dict[int, Channel] = {}
    schemas: dict[int, Schema] = {}
    complete = False
    try:
        for record in records:
            if isinstance(record, Schema):
                schemas[record.id] = record
            elif isinstance(record, Channel):
                channels[record.id] = record
            elif isinstance(record, Metadata):
                recording.metadata[record.name] = dict(record.metadata)
            elif isinstance(record, Message):
                channel = channels.get(record.channel_id)
                parsed = split_topic(channel.topic) if channel else None
                if channel is not None and parsed is None and is_view_topic(channel.topic):
                    recording.views.append(_raw(channel, schemas.get(channel.schema_id), record))
                    continue
                if channel is None or parsed is None:
                    recording.foreign_topics += 1
                    continue
                if channel.topic not in recording.schemas and channel.schema_id in schemas:
                    recording.schemas[channel.topic] = json.loads(schemas[channel.schema_id].data)
                recording.messages.append(
                    RecordedMessage(
                        channel.topic,
                        parsed[0],
                        parsed[1],
                        record.log_time,
                        json.loads(record.data),
                    )
                )
            elif type(record).__name__ == "Footer":
                complete = True
    except _CUT_FILE_ERRORS:
        # A cut-off record (killed writer, copy in progress): keep everything before it.
        return False
    return complete


def _raw(channel: Channel, schema: Schema | None, message: Message) -> RawMessage:
    found = ("", "", b"") if schema is None else (schema.name, schema.encoding, schema.data)
    return RawMessage(
        channel.topic, found, channel.message_encoding, message.log_time, bytes(message.data)
    )


def write_recording(recording: Recording, path: Path) -> int:
    """Write everything read from `recording` as a complete, indexed MCAP file at `path`."""
    with open(path, "wb") as stream:
        writer = ChunkedWriter(stream, chunk_size=1 << 20)
        writer.start(profile=PROFILE, library="arena")
        for name, values in recording.metadata.items():
            writer.add_metadata(name, values)
        schema_ids: dict[str, int] = {}
        channel_ids: dict[str, int] = {}
        for view in recording.views:
            channel = channel_ids.get(view.topic)
            if channel is None:
                schema = schema_ids.get(view.schema[0])
                if schema is None:
                    schema = writer.register_schema(*view.schema)
                    schema_ids[view.schema[0]] = schema
                channel = writer.register_channel(view.topic, view.encoding, schema)
                channel_ids[view.topic] = channel
            writer.add_message(channel, view.log_time, view.data)
        for message in recording.messages:
            channel = channel_ids.get(message.topic)
            if channel is None:
                schema = schema_ids.get(message.kind)
                if schema is None:
                    text = json.dumps(recording.schemas.get(message.topic, schema_of(message.kind)))
                    schema = writer.register_schema(message.kind, "jsonschema", text.encode())
                    schema_ids[message.kind] = schema
                channel = writer.register_channel(message.topic, "json", schema)
                channel_ids[message.topic] = channel
            data = json.dumps(message.data, separators=(",", ":")).encode()
            writer.add_message(channel, message.log_time, data)
        writer.finish()
    return recording.message_count
