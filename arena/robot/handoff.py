"""Callbacks from a foreign thread, run in trio: the one way Zenoh's threads meet trio.

A library that calls back on threads of its own (Zenoh, for the fleet and for ROS 2) is given
`Handoff.callback(handler)`. The callback hands `(handler, item)` through the trio token into one
bounded memory channel; `Handoff.serve` drains it in trio, in arrival order, and runs each
handler there, so no robot state is ever touched from the foreign thread. A full channel drops
the item and counts it (`dropped`): a flood from the network costs bounded memory. A handler
may return an awaitable (answering a query, say), which runs in a task of its own.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Awaitable, Callable
from typing import Any

import trio

log = logging.getLogger(__name__)

Entry = tuple[Callable[[Any], Any], Any]


class Handoff:
    """A bounded hand-off of callbacks from foreign threads into trio."""

    def __init__(self, size: int, name: str) -> None:
        self.dropped = 0
        self._name = name  # for the log: "fleet", "ros2"
        self._token: trio.lowlevel.TrioToken | None = None
        self._send, self._receive = trio.open_memory_channel[Entry](size)

    def open(self) -> None:
        """Start taking callbacks (call in trio, before the library can call back)."""
        self._token = trio.lowlevel.current_trio_token()

    def callback(self, handler: Callable[[Any], Any]) -> Callable[[Any], None]:
        """A callback for the foreign thread that has `handler(item)` run in trio."""

        def callback(item: Any) -> None:
            token = self._token
            if token is None:
                return
            with contextlib.suppress(trio.RunFinishedError):
                token.run_sync_soon(self._enqueue, (handler, item))

        return callback

    def _enqueue(self, entry: Entry) -> None:
        try:
            self._send.send_nowait(entry)
        except trio.WouldBlock:
            self.dropped += 1
        except trio.ClosedResourceError:
            pass

    async def serve(self, nursery: trio.Nursery) -> None:
        """Run every handed-off handler, in order, until cancelled."""
        async for entry in self._receive:
            handler, item = entry
            # Nothing here may keep an item alive: Zenoh finishes a query (and the asker stops
            # waiting) only once its last reference is gone.
            del entry
            try:
                result = handler(item)
            except Exception:
                log.exception("%s: handling a message failed", self._name)
                continue
            finally:
                del item
            if isinstance(result, Awaitable):
                nursery.start_soon(self._guarded, result)
            del result

    async def _guarded(self, work: Awaitable[Any]) -> None:
        try:
            await work
        except Exception:
            log.exception("%s: handling a message failed", self._name)
