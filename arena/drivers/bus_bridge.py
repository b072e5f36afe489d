"""From the servo-bus thread to trio: latest reading wins, events are kept in order.

The worker thread never blocks on trio: it stores what it saw and schedules one wake-up on the
trio loop (coalesced while one is pending).
"""

from __future__ import annotations

import collections
import contextlib
import os
import threading
from collections.abc import Callable, Mapping
from concurrent.futures import Future
from typing import TypeVar

import trio

from arena.protocol.errors import ArenaError, ErrorCode
from arena.servo.interface import ServoBus
from arena.servo.ports import check_serial_device, find_adapter
from arena.servo.worker import BusWorker, Reading, WorkerEvent, WorkerSettings

T = TypeVar("T")
BUSY_PORT_PATIENCE = 1.0  # seconds
#: The ports this process's arms hold (their real paths), and whose: a busy port held here is
#: not "another program's".
HELD_PORTS: dict[str, str] = {}


class BusBridge:
    """A `worker.Listener` whose readings and events a trio task takes with `next()`."""

    def __init__(self) -> None:
        self._token = trio.lowlevel.current_trio_token()
        self._lock = threading.Lock()
        self._reading: Reading | None = None
        self._events: collections.deque[WorkerEvent] = collections.deque(maxlen=10_000)
        self._wake = trio.Event()
        self._wake_pending = False
        self.readings = 0

    # -- worker thread side -------------------------------------------------------------------

    def reading(self, reading: Reading) -> None:
        """Keep the newest reading."""
        with self._lock:
            self._reading = reading
            self.readings += 1
            self._poke()

    def event(self, event: WorkerEvent) -> None:
        """Queue an event."""
        with self._lock:
            self._events.append(event)
            self._poke()

    def _poke(self) -> None:
        if self._wake_pending:
            return
        self._wake_pending = True
        with contextlib.suppress(trio.RunFinishedError):  # trio is gone: nobody listens
            self._token.run_sync_soon(self._wake_up)

    # -- trio side ----------------------------------------------------------------------------

    def _wake_up(self) -> None:
        with self._lock:
            self._wake_pending = False
        self._wake.set()

    def take_reading(self) -> Reading | None:
        """The newest reading not yet taken, without waiting."""
        with self._lock:
            reading, self._reading = self._reading, None
        return reading

    async def next(self) -> tuple[Reading | None, list[WorkerEvent]]:
        """Wait for news: the newest reading (None if only events came) and the events."""
        while True:
            self._wake = trio.Event()
            with self._lock:
                reading, self._reading = self._reading, None
                events = list(self._events)
                self._events.clear()
            if reading is not None or events:
                return reading, events
            await self._wake.wait()


async def start_worker(
    port: str | None,
    servo_ids: tuple[int, ...],
    settings: WorkerSettings,
    open_bus: Callable[[str], ServoBus],
    adapters: Mapping[tuple[int, int], str],
    holder: str = "an arm",
) -> tuple[str, BusWorker, BusBridge]:
    """Find the port (by `adapters`' USB ids when None), start a `BusWorker` on it, wait until
    every servo answered, and note it held by `holder` (`HELD_PORTS`, until `release_port`).
    Errors (no adapter, missing or busy port, a silent servo) say what to do."""
    if port is None:
        port = await trio.to_thread.run_sync(find_adapter, adapters)
    check_serial_device(port)
    chosen = port
    # A driver that just let go of this port (detach, then attach again at once) may still be
    # closing it: a busy port is retried for a moment before the caller hears about it.
    deadline = trio.current_time() + BUSY_PORT_PATIENCE
    while True:
        bridge = BusBridge()
        worker = BusWorker(lambda: open_bus(chosen), servo_ids, bridge, settings)
        worker.start()
        try:
            await wait_future(worker.first_connect)
        except ArenaError as error:
            await trio.to_thread.run_sync(worker.stop)
            if error.code is ErrorCode.PORT_BUSY and trio.current_time() < deadline:
                await trio.sleep(0.05)
                continue
            held = HELD_PORTS.get(os.path.realpath(chosen))
            if error.code is ErrorCode.PORT_BUSY and held is not None:
                raise ArenaError(
                    ErrorCode.PORT_BUSY,
                    f"Serial port {chosen} is in use by this server already: {held} holds it. "
                    "Detach that first, or give this one another port.",
                ) from None
            raise
        except BaseException:
            with trio.CancelScope(shield=True):
                await trio.to_thread.run_sync(worker.stop)
            raise
        HELD_PORTS[os.path.realpath(port)] = holder
        return port, worker, bridge


def release_port(port: str, holder: str) -> None:
    """`port` is no longer held here by `holder` (its worker stopped)."""
    key = os.path.realpath(port)
    if HELD_PORTS.get(key) == holder:
        del HELD_PORTS[key]


async def wait_future(future: Future[T]) -> T:
    """Wait in trio for a `concurrent.futures.Future` that another thread completes."""
    token = trio.lowlevel.current_trio_token()
    done = trio.Event()

    def finished(_: Future[T]) -> None:
        with contextlib.suppress(trio.RunFinishedError):
            token.run_sync_soon(done.set)

    future.add_done_callback(finished)
    await done.wait()
    return future.result()
