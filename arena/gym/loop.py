"""A trio run in a thread of its own, called from plain (blocking) code such as a Gymnasium
environment: the run's tasks live as long as the loop, and every call is one async function run
in it (`trio.from_thread.run`), its exception raised in the caller's thread."""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Awaitable, Callable
from typing import Any, TypeVar

import trio

T = TypeVar("T")

#: How long closing waits for the run to end (seconds of real time).
CLOSE_TIMEOUT = 10.0


class TrioLoop:
    """Runs `serve(task_status)` in a new thread's trio run (on `clock`, if given) until
    `close`. `serve` calls `task_status.started()` once it is ready for calls and then waits;
    it is cancelled on close."""

    def __init__(
        self,
        serve: Callable[[trio.TaskStatus[None]], Awaitable[None]],
        clock: trio.abc.Clock | None = None,
        name: str = "arena-gym",
    ) -> None:
        self._serve = serve
        self._clock = clock
        self._token: trio.lowlevel.TrioToken | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._cancel: trio.CancelScope | None = None
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()
        self._ready.wait()
        if self._error is not None:
            self._thread.join()
            raise self._error

    def _run(self) -> None:
        try:
            trio.run(self._main, clock=self._clock)
        except BaseException as exc:  # reported to whoever waits for the start
            self._error = exc
        finally:
            self._ready.set()

    async def _main(self) -> None:
        self._token = trio.lowlevel.current_trio_token()
        async with trio.open_nursery() as nursery:
            self._cancel = nursery.cancel_scope
            await nursery.start(self._serve)
            self._ready.set()

    @property
    def running(self) -> bool:
        """The run has not ended."""
        return self._thread.is_alive()

    def call(self, function: Callable[..., Awaitable[T]], *args: Any) -> T:
        """Run `function(*args)` in the loop and return its result (or raise its error)."""
        if self._token is None or not self.running:
            raise RuntimeError("the environment's loop has ended (closed, or it failed)")
        return trio.from_thread.run(function, *args, trio_token=self._token)

    def close(self) -> None:
        """Cancel the run and wait for its thread to end."""
        if self._token is not None and self.running and self._cancel is not None:
            cancel = self._cancel
            with contextlib.suppress(trio.RunFinishedError):
                trio.from_thread.run_sync(cancel.cancel, trio_token=self._token)
        self._thread.join(CLOSE_TIMEOUT)
