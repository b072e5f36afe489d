"""The recorder: follows every robot's events and writes them to MCAP without stalling control.

Each robot's events go into a large drop-oldest queue (a robot never waits for the recorder;
anything dropped is counted). Nothing wakes per event: one writer task drains the queues every
`batch_interval`, packs the events as they are in slices (other tasks run between them) and
hands the batch, from a worker thread, to the MCAP writer in its own process
(`writer_process`), where the records are made, compressed and written on another core than
control, and the chunk is closed and handed to the OS at least every `flush_interval`, which
bounds what a crash or a power cut can take. By default the two are the same quarter second:
one hand-off, one flush. Each hand-off wakes a thread, the writer process and the loop again,
and the writer pauses its work every few events to let anything waiting run, so fewer, larger
batches cost less than many small ones, in CPU and in the relay's tail (the figures are in
specs/performance.md, "Recording").
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
from collections import deque
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import trio

import arena
from arena.protocol.errors import ArenaError, ErrorCode
from arena.protocol.rest import DEFAULT_TENANT
from arena.recording.mcap_file import FileSeries
from arena.recording.writer_process import McapWriterProcess, WriteFailed, pack_events
from arena.robot.events import CameraFrame, RobotEvent
from arena.robot.handle import Robot
from arena.robot.mailbox import EventQueue

#: What the recorder follows: a robot's events or a camera's frames.
Followed = RobotEvent | CameraFrame

log = logging.getLogger(__name__)

#: Events packed between two checkpoints (~30 us of work), so a batch never holds up control
#: for long: with 256 records a slice (at ~1 us each, as they were packed then) the relay
#: benchmark's p99 rose by 100 us. An event now packs in ~0.2 us.
_PACK_SLICE = 128


#: What a highlight keeps of one robot at most while the recorder is off (events, and bytes
#: of camera frames): beyond either, the oldest go (specs/policy.md, "Rollout strategies").
MAX_KEPT_EVENTS = 500_000
MAX_KEPT_BYTES = 256 << 20


class Kept:
    """A robot's last `seconds` of events and camera frames, kept while the recorder writes
    nothing, for a highlight to write (bounded by `MAX_KEPT_EVENTS` and `MAX_KEPT_BYTES`)."""

    def __init__(self, seconds: float) -> None:
        self.seconds = seconds
        self.events: deque[Followed] = deque()
        self.bytes = 0
        self.dropped = 0  # events let go for the bounds, not for their age

    def add(self, events: list[Followed]) -> None:
        """Keep `events` (drained from one queue), letting the oldest go."""
        for event in events:
            self.events.append(event)
            if isinstance(event, CameraFrame):
                self.bytes += len(event.jpeg)
        # (Queues are drained one after the other: a batch's margin keeps the window whole.)
        oldest = events[-1].time - self.seconds - 1.0 if events else -math.inf
        kept = self.events
        while kept and (
            kept[0].time < oldest or len(kept) > MAX_KEPT_EVENTS or self.bytes > MAX_KEPT_BYTES
        ):
            gone = kept.popleft()
            if gone.time >= oldest:
                self.dropped += 1
            if isinstance(gone, CameraFrame):
                self.bytes -= len(gone.jpeg)

    def between(self, start: float, end: float) -> list[Followed]:
        """What is kept from `start` to `end` (trio time)."""
        return [event for event in self.events if start <= event.time <= end]

    def clear(self) -> None:
        """Forget everything (the recorder writes it all)."""
        self.events.clear()
        self.bytes = 0


class RecorderKeeper:
    """`arena.policy.strategy.Keeper` for one robot: a highlight strategy's side in the
    recorder."""

    def __init__(self, recorder: Recorder, robot_id: str) -> None:
        self.recorder = recorder
        self.robot_id = robot_id

    def keep(self, seconds: float) -> None:
        """Keep the robot's last `seconds` whenever the recorder is off."""
        self.recorder.kept[self.robot_id] = Kept(seconds)

    def release(self) -> None:
        """Keep nothing more."""
        self.recorder.kept.pop(self.robot_id, None)

    async def save(self, since: float, until: float) -> None:
        """Write what happened from `since` to `until` (`Recorder.save_kept`)."""
        await self.recorder.save_kept(self.robot_id, since, until)


@dataclass
class _Batch:
    """Events drained since the last batch, packed in slices for the writer process, by
    the tenant whose files they go to."""

    slices: dict[str, list[bytes]] = field(default_factory=dict)
    #: Events, by tenant.
    events: dict[str, int] = field(default_factory=dict)

    def add(self, robot_id: str, tenant: str, wall_offset: float, events: list[Followed]) -> None:
        packed = pack_events(robot_id, wall_offset, events)
        found = self.slices.get(tenant)
        if found is None:
            self.slices[tenant] = [packed]
            self.events[tenant] = len(events)
        else:
            found.append(packed)
            self.events[tenant] += len(events)

    def drop(self, tenant: str) -> int:
        """Leave out a tenant's events; returns how many."""
        self.slices.pop(tenant, None)
        return self.events.pop(tenant, 0)


class Backoff:
    """When to try again after a failure: `initial` seconds, doubling up to `maximum`. A full
    disk then costs one attempt now and then instead of one (and a new file) every batch."""

    def __init__(self, initial: float, maximum: float) -> None:
        self.initial = initial
        self.maximum = maximum
        self._delay = initial
        self._at = -math.inf

    def ready(self, now: float) -> bool:
        """Time for an attempt."""
        return now >= self._at

    def wait(self, now: float) -> float:
        """Seconds until the next attempt."""
        return max(0.0, self._at - now)

    def failed(self, now: float) -> None:
        """An attempt failed at `now`."""
        self._at = now + self._delay
        self._delay = min(self._delay * 2, self.maximum)

    def succeeded(self) -> None:
        """An attempt worked (or someone asked to try at once): back to the start."""
        self._delay = self.initial
        self._at = -math.inf


@dataclass
class _TenantHealth:
    """How writing a tenant's files goes: its last error and losses, and when to try
    again after a failure (each tenant on its own: one tenant's full disk or quota does not
    hold up the others)."""

    retry: Backoff
    error: str | None = None
    errors: int = 0  # failed attempts since the server started
    write_failures: int = 0  # records lost to disk errors
    dropped_by_gone: int = 0  # queue overflows of robots no longer followed


class Recorder:
    """Records every robot it is given into `folder`, rotating files by size and age. Each
    tenant's robots go into files of their own (`writer_process.TenantFiles`)."""

    def __init__(
        self,
        folder: Path,
        metadata: dict[str, str] | None = None,
        *,
        max_bytes: int = 256 << 20,
        max_seconds: float = 3600.0,
        flush_interval: float = 0.25,
        batch_interval: float = 0.25,
        queue_size: int = 100_000,
        active: bool = True,
        retry_initial: float = 1.0,
        retry_max: float = 30.0,
        foxglove: bool = True,
        foxglove_rate: float = 30.0,
    ) -> None:
        base = {"server": "arena", "version": arena.__version__}
        self.writer = McapWriterProcess(
            FileSeries(
                folder,
                {**base, **(metadata or {})},
                max_bytes,
                max_seconds,
                foxglove,
                foxglove_rate,
            )
        )
        self.flush_interval = flush_interval
        self.batch_interval = min(batch_interval, flush_interval)
        self.queue_size = queue_size
        self.active = active
        self._retry_initial = retry_initial
        self._retry_max = retry_max
        self._health: dict[str, _TenantHealth] = {}
        #: queue -> (robot id, its tenant when followed, the subscription)
        self._followed: dict[EventQueue[Any], tuple[str, str, contextlib.ExitStack]] = {}
        self._wall_offset = 0.0  # wall clock minus trio's clock, taken when `run` starts
        self._next_flush = 0.0
        self._unflushed = False  # records handed over since the last flush
        self._writing = trio.Lock()  # one batch from collection to the writer at a time
        #: Robots whose highlight strategy keeps their last seconds while recording is off.
        self.kept: dict[str, Kept] = {}

    @property
    def folder(self) -> Path:
        """Where the files go."""
        return self.writer.folder

    @property
    def current_file(self) -> Path | None:
        """The file of the default tenant being written, if any."""
        return self.writer.path

    def _of(self, tenant: str) -> _TenantHealth:
        found = self._health.get(tenant)
        if found is None:
            backoff = Backoff(self._retry_initial, self._retry_max)
            found = self._health[tenant] = _TenantHealth(backoff)
        return found

    @property
    def error(self) -> str | None:
        """Why the files of some tenant cannot be written now (a sentence naming neither a
        file nor a tenant), None when every tenant's can."""
        return next((h.error for h in self._health.values() if h.error is not None), None)

    @property
    def errors(self) -> int:
        """Disk errors since the server started (each failed attempt of a tenant once)."""
        return sum(health.errors for health in self._health.values())

    @property
    def current_files(self) -> dict[Path, str]:
        """Every file being written, and whose (its tenant)."""
        return self.writer.open_files

    async def run(self, *, task_status: Any = trio.TASK_STATUS_IGNORED) -> None:
        """Write until cancelled; then finish the open file and end the writer process."""
        try:
            if self.active:  # else the writer starts with the first batch
                await trio.to_thread.run_sync(self.writer.launch)
            self._wall_offset = time.time() - trio.current_time()
            task_status.started()
            await self._write_forever()
        finally:
            with trio.CancelScope(shield=True):
                await self._write_pending()
                await trio.to_thread.run_sync(self.writer.shutdown)
                for _, _, subscription in self._followed.values():
                    subscription.close()
                self._followed.clear()

    def follow(self, robot: Robot) -> None:
        """Record this robot from now on, into its tenant's files (its type and URDF go into
        the file's metadata)."""
        urdf = robot.model.urdf_path.read_text(encoding="utf-8")
        self.writer.models[robot.robot_id] = robot.model
        self.writer.robots[robot.robot_id] = {
            "robot_type": robot.model.robot_type,
            "name": robot.name,
            "urdf": urdf,
            "tenant": robot.tenant,
        }
        subscription = contextlib.ExitStack()
        queue = subscription.enter_context(robot.subscribe(maxlen=self.queue_size))
        self._followed[queue] = (robot.robot_id, robot.tenant, subscription)

    def follow_frames(
        self, robot_id: str, frames: contextlib.AbstractContextManager[EventQueue[CameraFrame]]
    ) -> None:
        """Record a camera's frames (`frames` is its subscription, with its own bound) from
        now on, until the camera closes the queue (into the files of the robot's tenant)."""
        subscription = contextlib.ExitStack()
        queue = subscription.enter_context(frames)
        tenant = self.writer.robots.get(robot_id, {}).get("tenant", DEFAULT_TENANT)
        self._followed[queue] = (robot_id, tenant, subscription)

    async def start(self) -> Path | None:
        """Resume recording into a new file (after `stop`); after a disk error, try again
        with the next batch instead of waiting out the backoff."""
        self.active = True
        for health in self._health.values():
            health.retry.succeeded()
        return self.writer.path

    async def stop(self) -> dict[Path, str]:
        """Pause recording and finish the current files; returns them, with their tenants."""
        # After the batch in flight, if any: its thread could otherwise reach the writer after
        # `close` and put what happened before the stop into the next file.
        async with self._writing:
            batch = await self._collect()  # what happened up to now still goes in
            self.active = False
            await self._write(batch)
            # The file is known only now: the batch in flight may be the one that opened it.
            return await trio.to_thread.run_sync(self.writer.close)

    async def _collect(self) -> _Batch:
        """Drain every followed robot's queue and pack the events (none while paused)."""
        batch = _Batch()
        packed = 0  # events packed since the last checkpoint
        for queue, (robot_id, tenant, subscription) in list(self._followed.items()):
            events = queue.drain()
            if queue.closed:  # the robot is gone (and its queue now empty)
                self._of(tenant).dropped_by_gone += queue.dropped
                del self._followed[queue]
                subscription.close()
            kept = self.kept.get(robot_id)
            if kept is not None:
                if self.active:
                    kept.clear()  # all of it goes into the file
                elif events:
                    kept.add(events)
            if not self.active:
                continue
            # Log times follow trio's clock from one wall-clock anchor: monotonic within a
            # file (no NTP jumps), and virtual time stays consistent in tests.
            for start in range(0, len(events), _PACK_SLICE):
                part = events[start : start + _PACK_SLICE]
                batch.add(robot_id, tenant, self._wall_offset, part)
                packed += len(part)
                if packed >= _PACK_SLICE:  # (a fleet's robots have a few events each)
                    packed = 0
                    await trio.lowlevel.checkpoint()
        return batch

    def keeper(self, robot_id: str) -> RecorderKeeper:
        """A highlight strategy's side in the recorder, for one robot."""
        return RecorderKeeper(self, robot_id)

    async def save_kept(self, robot_id: str, since: float, until: float) -> None:
        """A highlight of the robot was marked: recording, write what is pending now (the
        episode's marks with it; the rest of it is in the file already); not recording,
        write what was kept of the robot from `since` to `until` (trio time, with the
        marks) into a file of its own, at the times it happened."""
        async with self._writing:
            batch = await self._collect()  # (while off, this keeps the marks)
            if self.active:
                await self._write(batch)
                return
            kept = self.kept.get(robot_id)
            events = [] if kept is None else kept.between(since, until)
            if not events:
                return
            tenant = self.writer.robots.get(robot_id, {}).get("tenant", DEFAULT_TENANT)
            highlight = _Batch()
            for start in range(0, len(events), _PACK_SLICE):
                part = events[start : start + _PACK_SLICE]
                highlight.add(robot_id, tenant, self._wall_offset, part)
                await trio.lowlevel.checkpoint()
            await self._write(highlight)
            await trio.to_thread.run_sync(self.writer.close)  # a highlight is a file's whole

    async def _write_forever(self) -> None:
        # One batch per interval: a single thread hop however busy it is.
        while True:
            await trio.sleep(self.batch_interval)
            await self._write_pending(flush=trio.current_time() >= self._next_flush)

    async def _write_pending(self, flush: bool = True) -> None:
        async with self._writing:
            await self._write(await self._collect(), flush)

    async def _write(self, batch: _Batch, flush: bool = True) -> None:
        now = trio.current_time()
        for tenant in list(batch.events):
            health = self._of(tenant)
            if not health.retry.ready(now):  # its disk failed lately: not yet
                health.write_failures += batch.drop(tenant)
        if not batch.events and not (flush and self._unflushed):
            return
        failed: dict[str, str] = {}
        try:
            await trio.to_thread.run_sync(
                partial(self.writer.write_events, batch.slices, flush=flush)
            )
        except WriteFailed as exc:  # some tenants' files failed; the others' were written
            failed = exc.by_tenant
        except OSError as exc:  # the writer process itself: every tenant of the batch
            failed = dict.fromkeys(batch.events or self._health or [DEFAULT_TENANT], str(exc))
        now = trio.current_time()
        self._unflushed = not flush
        if flush:
            self._next_flush = now + self.flush_interval
        # A full or read-only disk must not stop control: say so, drop the tenant's batch,
        # and try a fresh file after its backoff.
        for tenant, error in failed.items():
            health = self._of(tenant)
            if health.error is None:
                log.error("recording tenant %r failed: %s", tenant, error)
            health.error = error
            health.errors += 1
            health.write_failures += batch.events.get(tenant, 0)  # its file was dropped
            health.retry.failed(now)
        for tenant in batch.events.keys() - failed.keys():
            health = self._of(tenant)
            if health.error is not None:
                log.warning("recording tenant %r resumed", tenant)
                health.error = None
            health.retry.succeeded()

    @property
    def dropped(self) -> int:
        """Records lost, of every tenant (`dropped_of`)."""
        tenants = {tenant for _, tenant, _ in self._followed.values()} | self._health.keys()
        return sum(self.dropped_of(tenant) for tenant in tenants)

    def dropped_of(self, tenant: str) -> int:
        """A tenant's records lost: events its robots' followers could not keep plus
        batches a disk refused."""
        health = self._health.get(tenant)
        followed = sum(q.dropped for q, (_, whose, _) in self._followed.items() if whose == tenant)
        if health is None:
            return followed
        return health.write_failures + health.dropped_by_gone + followed

    def status(self, tenant: str = DEFAULT_TENANT) -> dict[str, Any]:
        """What the recorder is doing for one tenant's files, for the REST API: nothing of
        another tenant's (its counts, its file's name, its errors)."""
        health = self._health.get(tenant)
        error = None if health is None else health.error
        theirs = sorted(path.name for path, whose in self.current_files.items() if whose == tenant)
        return {
            "active": self.active,
            "file": theirs[0] if theirs else None,
            "folder": str(self.folder),
            "messages": self.writer.messages_by_tenant.get(tenant, 0),
            "dropped": self.dropped_of(tenant),
            "error": error,
            "errors": 0 if health is None else health.errors,
            "retry_in": None
            if health is None or error is None
            else health.retry.wait(trio.current_time()),
        }


def check_name(folder: Path, name: str) -> Path:
    """The recording `name` inside `folder`; refuses anything that would leave the folder."""
    if (
        not name
        or "/" in name
        or "\\" in name
        or name.startswith(".")
        or not name.endswith(".mcap")
    ):
        raise ArenaError(
            ErrorCode.UNKNOWN_RECORDING,
            f"{name!r} is not a recording name (expected NAME.mcap, no folders).",
        )
    path = (folder / name).resolve()
    if path.parent != folder.resolve():
        raise ArenaError(ErrorCode.UNKNOWN_RECORDING, f"{name!r} is outside the recordings.")
    return path


def existing_recording(folder: Path, name: str) -> Path:
    """Like `check_name`, and the file must exist."""
    path = check_name(folder, name)
    if not path.is_file():
        raise ArenaError(ErrorCode.UNKNOWN_RECORDING, f"No recording called {name!r}.")
    return path
