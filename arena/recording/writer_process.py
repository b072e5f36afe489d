"""The MCAP writer in a child process, so that writing never competes with control for the GIL.

Writing MCAP (building records, compressing chunks, file I/O) costs a microsecond or more a
message, and every command leaves two or three records. `McapWriterProcess` offers the same
calls as `McapFileWriter` and runs one in a child Python process (`python -m
arena.recording.writer_process`), which does that work on the other core at idle priority.
The parent only packs the robots' events as they are (msgspec encodes the dataclasses in one
call) and writes them into a pipe; the child turns them into records.

The protocol on the child's stdin/stdout is a series of frames (8-byte big-endian length, then a
pickle), one request and one reply at a time:
  first frame      the `FileSeries`, no reply
  ("write", items, robots, flush)   append records (`items` packed with msgpack, which costs
                                    the parent a third of what pickle does); `robots` holds
                                    (metadata, model or None) of robots new to the child (the
                                    model, for Foxglove's view, spares the child loading the
                                    robot type, yourdfpy and all); `flush` closes the
                                    chunk and hands it to the OS
  ("events", slices, robots, flush)  the same from robot events: `slices` holds, by tenant,
                                    robots' events as msgpack (`pack_events`, one robot's a
                                    slice); the child makes the records
                                    (`records.record_of`) and writes them in time order,
                                    each tenant's into its own files (`TenantFiles`)
  ("close", None, None, True)       finish the current files
and each reply is ({tenant: error} of the tenants whose files failed (each error a sentence
naming no file: `describe`), the default tenant's current path or None, {tenant: messages
written}, every file opened, {path: tenant} of every file being written). One tenant's disk
error never stops the others' records.
End of input makes the child finish its file and exit: a killed server still leaves a complete
file behind.
"""

from __future__ import annotations

import contextlib
import dataclasses
import operator
import os
import pickle
import struct
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

import msgspec

from arena.protocol.rest import DEFAULT_TENANT
from arena.recording import images
from arena.recording.mcap_file import FileSeries, Item, McapFileWriter
from arena.recording.records import camera_kind, record_of
from arena.robot.events import CameraFrame, Observed, RobotEvent
from arena.robot.model import RobotModel

if TYPE_CHECKING:
    from arena.recording.foxglove import Twins

_LENGTH = struct.Struct(">Q")
#: How long the child may take to finish its file at shutdown before it is killed.
SHUTDOWN_TIMEOUT = 10.0
_pack_items = msgspec.msgpack.Encoder().encode
_unpack_items = msgspec.msgpack.Decoder(list[tuple[str, str, bytes, int]]).decode
_pack_slice = msgspec.msgpack.Encoder().encode
_unpack_slice = msgspec.msgpack.Decoder(tuple[str, float, list[RobotEvent | CameraFrame]]).decode
_json = msgspec.json.Encoder()
_LOG_TIME = operator.itemgetter(3)
#: Events handled between two pauses (`pause` in `items_of_events`).
_PAUSE_EVERY = 32


def pack_events(robot_id: str, wall_offset: float, events: Sequence[Observed]) -> bytes:
    """A slice of one robot's events for the writer process, packed in one call (the events
    are tagged structs). `wall_offset` is the wall clock minus trio's clock: an event's MCAP
    log time is `int((event.time + wall_offset) * 1e9)`, wall-clock ns."""
    return _pack_slice((robot_id, wall_offset, events))


def items_of_events(
    slices: list[bytes], twins: Twins | None = None, pause: Callable[[], object] | None = None
) -> list[Item]:
    """The records of packed event slices (and with `twins`, Foxglove's view of them), in
    log-time order; `pause` is called every few events."""
    items: list[Item] = []
    append = items.append
    for packed in slices:
        robot_id, wall_offset, events = _unpack_slice(packed)
        for start in range(0, len(events), _PAUSE_EVERY):
            if pause is not None:
                pause()
            for event in events[start : start + _PAUSE_EVERY]:
                at = int((event.time + wall_offset) * 1e9)
                if isinstance(event, CameraFrame):
                    image = images.encode(event, at)
                    append((robot_id, camera_kind(event.camera), image, at))
                    continue
                kind, record = record_of(event)
                append((robot_id, kind, _json.encode(record), at))
                if twins is not None and twins.shows(event):
                    items.extend(twins.items(robot_id, event, at))
    if twins is not None:
        items.extend(twins.flush())
    items.sort(key=_LOG_TIME)
    return items


def describe(error: OSError) -> str:
    """A disk error as a sentence that names no file (a file's name says whose it is, and
    the error may be shown to another tenant or to anyone asking `/readyz`)."""
    if error.strerror:
        return f"{error.strerror} (errno {error.errno})" if error.errno else error.strerror
    return f"the recording could not be written ({type(error).__name__})"


class WriteFailed(OSError):
    """Some tenants' records were not written: `by_tenant` says why, for each (the
    others' were)."""

    def __init__(self, by_tenant: dict[str, str]) -> None:
        super().__init__("; ".join(f"{t}: {e}" for t, e in sorted(by_tenant.items())))
        self.by_tenant = by_tenant


def send_frame(stream: IO[bytes], value: object) -> None:
    """Write one length-prefixed pickle and flush it."""
    payload = pickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL)
    stream.write(_LENGTH.pack(len(payload)) + payload)
    stream.flush()


def receive_frame(stream: IO[bytes]) -> Any:
    """Read one frame; `EOFError` when the other side has gone."""
    header = stream.read(_LENGTH.size)
    if len(header) < _LENGTH.size:
        raise EOFError("the pipe closed")
    (length,) = _LENGTH.unpack(header)
    payload = stream.read(length)
    if len(payload) < length:
        raise EOFError("the pipe closed mid-frame")
    return pickle.loads(payload)


class McapWriterProcess:
    """`McapFileWriter`'s calls, served by a child process (started by `launch` or on first use).

    Thread-safe: each call holds a lock for its request and reply. A failure of the child (or
    of its disk) comes back as `OSError`, as it would from a local writer; the next call starts
    a fresh child if the old one is gone.
    """

    def __init__(self, series: FileSeries) -> None:
        self.series = series
        self.folder = series.folder
        self.robots: dict[str, dict[str, str]] = {}  # robot id -> metadata, set by the recorder
        self.models: dict[str, RobotModel] = {}  # robot id -> model, set by the recorder
        self.path: Path | None = None
        #: Every file being written, and its tenant.
        self.open_files: dict[Path, str] = {}
        self.files: list[Path] = []
        #: Records written, by tenant (since the server started).
        self.messages_by_tenant: dict[str, int] = {}
        self._process: subprocess.Popen[bytes] | None = None
        #: The metadata the child has of each robot (sent again when a robot id is made anew,
        #: of another tenant maybe).
        self._robots_sent: dict[str, dict[str, str]] = {}
        #: Written by children that have gone, by tenant, and their files.
        self._earlier_messages: dict[str, int] = {}
        self._earlier_files: list[Path] = []
        self._lock = threading.Lock()

    @property
    def messages(self) -> int:
        """Records written, of every tenant."""
        return sum(self.messages_by_tenant.values())

    def launch(self) -> None:
        """Start the child now (it takes ~0.1 s), so that the first batch does not wait for it."""
        with self._lock:
            self._running()

    def write(self, items: list[Item], *, flush: bool = True) -> None:
        """Append records (the child opens or rotates files as needed); `flush` as in
        `McapFileWriter.write`."""
        self._append("write", _pack_items(items), flush)

    def write_events(self, slices: dict[str, list[bytes]], *, flush: bool = True) -> None:
        """Like `write`, from slices of events packed with `pack_events`, by tenant."""
        self._append("events", slices, flush)

    def _append(self, kind: str, payload: object, flush: bool) -> None:
        with self._lock:
            self._running()  # first: a child started now knows no robot, so all go with this
            new = {
                r: (meta, self.models.get(r))
                for r, meta in self.robots.items()
                if self._robots_sent.get(r) is not meta
            }
            self._request((kind, payload, new, flush))
            self._robots_sent.update((r, meta) for r, (meta, _) in new.items())

    def close(self) -> dict[Path, str]:
        """Finish the current files (after any write in flight); the child stays for the
        next ones. Returns the files finished, with their tenants."""
        with self._lock:
            files = dict(self.open_files)
            if self._process is not None:
                self._request(("close", None, None, True))
            return files

    def shutdown(self) -> None:
        """Finish the current file and end the child."""
        with self._lock:
            process, self._process = self._process, None
            if process is None:
                return
            assert process.stdin is not None
            try:
                process.stdin.close()  # end of input: the child finishes its file
                process.wait(SHUTDOWN_TIMEOUT)
            except (OSError, subprocess.TimeoutExpired):
                process.kill()
                process.wait()
            self.path = None
            self.open_files = {}

    def _request(self, request: tuple[str, object, object, bool]) -> None:
        process = self._running()
        assert process.stdin is not None and process.stdout is not None
        try:
            send_frame(process.stdin, request)
            errors, path, messages, files, open_files = receive_frame(process.stdout)
        except (OSError, EOFError, pickle.PickleError) as exc:
            self._abandon_child()
            raise OSError(f"the recording process failed: {exc}") from exc
        self.path = None if path is None else Path(path)
        self.open_files = {Path(name): tenant for name, tenant in open_files.items()}
        earlier = self._earlier_messages
        tenants = earlier.keys() | messages.keys()
        self.messages_by_tenant = {t: earlier.get(t, 0) + messages.get(t, 0) for t in tenants}
        self.files = self._earlier_files + [Path(f) for f in files]
        if errors:
            raise WriteFailed(errors)

    def _running(self) -> subprocess.Popen[bytes]:
        if self._process is not None and self._process.poll() is None:
            return self._process
        if self._process is not None:
            self._abandon_child()
        package_root = str(Path(__file__).resolve().parents[2])
        path = os.environ.get("PYTHONPATH")
        env = {**os.environ, "PYTHONPATH": package_root + (os.pathsep + path if path else "")}
        process = subprocess.Popen(
            [sys.executable, "-m", "arena.recording.writer_process"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            env=env,
            close_fds=True,
            start_new_session=True,  # a Ctrl-C at the terminal is the server's to handle
        )
        assert process.stdin is not None
        send_frame(process.stdin, self.series)
        self._process = process
        self._robots_sent.clear()  # a new child knows no robot yet
        return process

    def _abandon_child(self) -> None:
        process, self._process = self._process, None
        self.path = None
        self.open_files = {}
        self._earlier_messages = dict(self.messages_by_tenant)
        self._earlier_files = list(self.files)
        if process is not None:
            process.kill()
            process.wait()


@dataclasses.dataclass
class _Lane:
    """One tenant's writer, what it knows of the tenant's robots, and Foxglove's view."""

    writer: McapFileWriter
    models: dict[str, RobotModel]
    twins: Twins | None


class TenantFiles:
    """The child's writers: one `McapFileWriter` (and Foxglove's view) for each tenant, made
    when its first robot is known. A tenant's robots are recorded into files of their own, so
    a file can be given to a tenant whole; each file says its tenant in its `arena` metadata,
    and a tenant's other than the default's is named `arena-...TENANT.mcap`. Each tenant's
    writer knows only its own robots' metadata: a robot id made anew in another tenant never
    names the new robot in the old tenant's files."""

    def __init__(self, series: FileSeries) -> None:
        self.series = series
        self._lanes: dict[str, _Lane] = {}
        self._tenant_of: dict[str, str] = {}  # robot id -> its tenant, as last told
        #: Tenants whose files failed in the request being served, and why.
        self.errors: dict[str, str] = {}

    def know(self, robot_id: str, metadata: dict[str, str], model: RobotModel | None) -> None:
        """A robot's metadata (with its `tenant`) and model, for its tenant's files."""
        tenant = metadata.get("tenant", DEFAULT_TENANT)
        lane = self.lane(tenant)
        lane.writer.robots[robot_id] = metadata
        if model is not None:
            lane.models[robot_id] = model
        self._tenant_of[robot_id] = tenant

    def lane(self, tenant: str) -> _Lane:
        """The tenant's writer and view (made on first use; a file opens with a record)."""
        found = self._lanes.get(tenant)
        if found is not None:
            return found
        metadata = {**self.series.metadata, "tenant": tenant}
        writer = McapFileWriter(dataclasses.replace(self.series, metadata=metadata, tenant=tenant))
        models: dict[str, RobotModel] = {}
        twins = None
        if self.series.foxglove:
            from arena.recording.foxglove import Twins  # the SDK loads only when it is used

            twins = Twins(writer.robots, models, self.series.foxglove_rate)
            writer.first_in_file = twins.introduce
        lane = self._lanes[tenant] = _Lane(writer, models, twins)
        return lane

    def write_events(self, slices: dict[str, list[bytes]]) -> None:
        """Records of each tenant's events, into its files (a tenant whose disk fails loses
        its own, said in `errors`)."""
        for tenant, theirs in slices.items():
            lane = self.lane(tenant)
            with self._lane_of(tenant):
                _write_in_pieces(lane.writer, items_of_events(theirs, lane.twins, _PAUSE))

    @contextlib.contextmanager
    def _lane_of(self, tenant: str) -> Iterator[None]:
        """Work on one tenant's files: a disk error there is that tenant's alone (the file
        is abandoned, the others go on)."""
        try:
            yield
        except OSError as exc:
            self.errors.setdefault(tenant, describe(exc))

    def write_items(self, items: list[Item]) -> None:
        """Records made already, each into its robot's tenant's files."""
        by_tenant: dict[str, list[Item]] = {}
        for item in items:
            tenant = self._tenant_of.get(item[0], DEFAULT_TENANT)
            by_tenant.setdefault(tenant, []).append(item)
        for tenant, theirs in by_tenant.items():
            with self._lane_of(tenant):
                _write_in_pieces(self.lane(tenant).writer, theirs)

    def flush(self) -> None:
        """Every tenant's chunk in progress handed to the OS."""
        for tenant, lane in self._lanes.items():
            with self._lane_of(tenant):
                try:
                    lane.writer.flush()
                except OSError:
                    lane.writer.abandon()  # (as `write` does: the next record starts anew)
                    raise

    def close(self) -> None:
        """Finish every tenant's current file."""
        for tenant, lane in self._lanes.items():
            with self._lane_of(tenant):
                try:
                    lane.writer.close()
                except OSError:
                    lane.writer.abandon()
                    raise

    def reply(self) -> tuple[Any, ...]:
        """The answer to a request (see the module); the errors are then forgotten."""
        errors, self.errors = self.errors, {}
        writers = {tenant: lane.writer for tenant, lane in self._lanes.items()}
        default = writers.get(DEFAULT_TENANT)
        path = None if default is None or default.path is None else str(default.path)
        return (
            errors,
            path,
            {tenant: writer.messages for tenant, writer in writers.items()},
            [str(f) for writer in writers.values() for f in writer.files],
            {str(w.path): tenant for tenant, w in writers.items() if w.path is not None},
        )


def _write_in_pieces(writer: McapFileWriter, items: list[Item]) -> None:
    for start in range(0, len(items), _WRITE_PIECE):
        writer.write(items[start : start + _WRITE_PIECE], flush=False)
        _PAUSE()


def serve(requests: IO[bytes], replies: IO[bytes]) -> None:
    """The child's loop: each tenant's `McapFileWriter`, driven by frames until end of
    input."""
    files = TenantFiles(receive_frame(requests))
    try:
        while True:
            try:
                kind, items, robots, flush = receive_frame(requests)
            except EOFError:
                return
            try:
                if kind in ("write", "events"):
                    for robot_id, (metadata, model) in robots.items():
                        files.know(robot_id, metadata, model)
                    if kind == "write":
                        files.write_items(_unpack_items(items))
                    else:
                        files.write_events(items)
                    if flush:
                        files.flush()
                else:
                    files.close()
            except OSError as exc:  # not a tenant's own: every tenant of the request's
                tenants = set(items) if kind == "events" else {DEFAULT_TENANT}
                for tenant in tenants or {DEFAULT_TENANT}:
                    files.errors.setdefault(tenant, describe(exc))
            send_frame(replies, files.reply())
    finally:
        with contextlib.suppress(OSError):
            files.close()


#: Records written between pauses (`_PAUSE`).
_WRITE_PIECE = 256
#: The child gives up its CPU now and then (after each slice of events, each piece of
#: records): on the development VM an idle-priority process was not always preempted when
#: the server's client woke on its CPU, and a batch's 2-3 ms of work showed as spikes of that
#: size in the relay's latency, one every batch in some runs. A yield every ~100 us of work
#: lets whatever waits run.
_PAUSE: Callable[[], object] = getattr(os, "sched_yield", lambda: None)


def _yield_to_everything_else() -> None:
    """Run only on a core nothing else wants (Linux's SCHED_IDLE; elsewhere the lowest nice).

    When the cores are busy the writer falls behind (its batches grow) rather than take CPU
    from the server: a plain lower priority still lets it delay the server's wake-ups by a few
    milliseconds, which showed in the fleet benchmark's p99.
    """
    try:
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    except (AttributeError, OSError):
        os.nice(19)


if __name__ == "__main__":
    _yield_to_everything_else()
    serve(sys.stdin.buffer, sys.stdout.buffer)
