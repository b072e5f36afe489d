"""The recorder: follows every robot's events and writes them to MCAP without stalling control.

Each robot gets a follower task with a large drop-oldest queue (a robot never waits for the
recorder; anything dropped is counted). One writer task batches the records and hands each
batch, from a worker thread, to the MCAP writer in its own process (`writer_process`), where
encoding, compression and file I/O run on another core than control.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from pathlib import Path
from typing import Any

import msgspec
import trio

import arena
from arena.protocol.errors import ArenaError, ErrorCode
from arena.recording.mcap_file import FileSeries, Item
from arena.recording.records import record_of
from arena.recording.writer_process import McapWriterProcess
from arena.robot.actor import Robot
from arena.robot.events import RobotEvent
from arena.robot.mailbox import EventQueue

log = logging.getLogger(__name__)

_encoder = msgspec.json.Encoder()


class Recorder:
    """Records every robot it is given into `folder`, rotating files by size and age."""

    def __init__(
        self,
        folder: Path,
        metadata: dict[str, str] | None = None,
        *,
        max_bytes: int = 256 << 20,
        max_seconds: float = 3600.0,
        flush_interval: float = 0.25,
        queue_size: int = 100_000,
        active: bool = True,
    ) -> None:
        base = {"server": "arena", "version": arena.__version__}
        self.writer = McapWriterProcess(
            FileSeries(folder, {**base, **(metadata or {})}, max_bytes, max_seconds)
        )
        self.flush_interval = flush_interval
        self.queue_size = queue_size
        self.active = active
        self.error: str | None = None
        self._write_failures = 0  # records lost to disk errors
        self._follower_queues: set[EventQueue[RobotEvent]] = set()
        self._pending: deque[Item] = deque()
        self._nursery: trio.Nursery | None = None
        self._wall_offset = 0.0

    @property
    def folder(self) -> Path:
        """Where the files go."""
        return self.writer.folder

    @property
    def current_file(self) -> Path | None:
        """The file being written, if any."""
        return self.writer.path

    async def run(self, *, task_status: Any = trio.TASK_STATUS_IGNORED) -> None:
        """Write until cancelled; then finish the open file and end the writer process."""
        try:
            if self.active:  # else the writer starts with the first batch
                await trio.to_thread.run_sync(self.writer.launch)
            async with trio.open_nursery() as nursery:
                self._nursery = nursery
                self._wall_offset = time.time() - trio.current_time()
                task_status.started()
                await self._write_forever()
        finally:
            with trio.CancelScope(shield=True):
                await self._write_pending()
                await trio.to_thread.run_sync(self.writer.shutdown)

    def follow(self, robot: Robot) -> None:
        """Record this robot from now on (its type and URDF go into the file's metadata)."""
        urdf = robot.model.urdf_path.read_text(encoding="utf-8")
        self.writer.robots[robot.robot_id] = {
            "robot_type": robot.model.robot_type,
            "name": robot.name,
            "urdf": urdf,
        }
        assert self._nursery is not None
        self._nursery.start_soon(self._follow, robot)

    async def start(self) -> Path | None:
        """Resume recording into a new file (after `stop`)."""
        self.active = True
        return self.writer.path

    async def stop(self) -> Path | None:
        """Pause recording and finish the current file; returns its path."""
        self.active = False
        path = self.writer.path
        await self._write_pending()
        await trio.to_thread.run_sync(self.writer.close)
        return path

    async def _follow(self, robot: Robot) -> None:
        with robot.subscribe(maxlen=self.queue_size) as events:
            self._follower_queues.add(events)
            async for event in events:
                if not self.active:
                    continue
                kind, record = record_of(event)
                # Log times follow trio's clock from one wall-clock anchor: monotonic within a
                # file (no NTP jumps), and virtual time stays consistent in tests.
                log_time = int((event.time + self._wall_offset) * 1e9)
                self._pending.append((robot.robot_id, kind, _encoder.encode(record), log_time))

    async def _write_forever(self) -> None:
        # One batch per interval: a single thread hop and a single chunk however busy it is.
        while True:
            await trio.sleep(self.flush_interval)
            await self._write_pending()

    async def _write_pending(self) -> None:
        if not self._pending:
            return
        batch = list(self._pending)
        self._pending.clear()
        try:
            await trio.to_thread.run_sync(self.writer.write, batch)
            if self.error is not None:
                log.warning("recording resumed in %s", self.writer.path)
            self.error = None
        except OSError as exc:
            # A full or read-only disk must not stop control: say so, drop the batch, and try
            # a fresh file with the next one.
            if self.error is None:
                log.error("recording failed: %s", exc)
            self.error = f"{type(exc).__name__}: {exc}"
            self._write_failures += len(batch)  # the writer has dropped its file

    @property
    def dropped(self) -> int:
        """Records lost: events the followers could not keep plus batches a disk refused."""
        return self._write_failures + sum(q.dropped for q in self._follower_queues)

    def status(self) -> dict[str, Any]:
        """What the recorder is doing, for the REST API."""
        return {
            "active": self.active,
            "file": self.writer.path.name if self.writer.path else None,
            "folder": str(self.folder),
            "messages": self.writer.messages,
            "dropped": self.dropped,
            "error": self.error,
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
