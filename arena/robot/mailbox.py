"""Non-blocking hand-offs from the actor to slower consumers.

The actor must never wait for a consumer. `LatestMailbox` keeps only the newest target (plus the
notices, which are never coalesced); `EventQueue` keeps a bounded backlog and drops the oldest.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from typing import Generic, TypeVar

import trio

from arena.robot.idle import IdleTurn

T = TypeVar("T")
N = TypeVar("N")


class _Parked:
    """Shared wake-up and close logic."""

    def __init__(self) -> None:
        self._lot = trio.lowlevel.ParkingLot()
        self._waiting = 0  # readers parked in `_lot` (an int: asking the lot is a call)
        self.closed = False
        self._holding = False

    def close(self) -> None:
        """No more items will come; waiting readers get `trio.EndOfChannel` once drained."""
        self.closed = True
        self._lot.unpark_all()

    def _wake(self) -> None:
        if self._waiting and not self._holding:
            self._lot.unpark_all()

    async def _park(self) -> None:
        self._waiting += 1
        try:
            await self._lot.park()
        finally:
            self._waiting -= 1

    def holding_wakes(self) -> _Holding:
        """Puts inside this block do not wake the reader; leaving it wakes them once if
        anything is still queued. For a caller that will take the items itself: the reader's
        task is then not woken only to find nothing. (A class, not a generator: it is
        entered for every command.)"""
        return _Holding(self)

    def _has_items(self) -> bool:
        raise NotImplementedError


class _Holding:
    """`_Parked.holding_wakes`."""

    __slots__ = ("_parked",)

    def __init__(self, parked: _Parked) -> None:
        self._parked = parked

    def __enter__(self) -> None:
        self._parked._holding = True

    def __exit__(self, *exc_info: object) -> None:
        parked = self._parked
        parked._holding = False
        if parked._has_items():
            parked._wake()


class LatestMailbox(_Parked, Generic[T, N]):
    """A one-slot box for targets where the newest wins, plus an ordered queue of notices.

    A notice that `clears` (an e-stop) throws away a target not yet taken, so a slave that was
    slow never acts on a target that the stop has overtaken.

    A consumer may offer `deliver_now`, a hand-off that never blocks (a write to a socket with
    room): in its reader's idle turn (`turn`: the reader waits and nothing is queued, see
    `arena.robot.idle`) an item goes straight through it, so no task is woken for it. It
    returns False to decline; the item is then queued as usual.
    """

    def __init__(self, max_notices: int = 64) -> None:
        super().__init__()
        self._target: T | None = None
        self._notices: deque[N] = deque(maxlen=max_notices)
        self.coalesced = 0  # targets replaced before being taken
        self.deliver_now: Callable[[T | N], bool] | None = None
        #: Open while the reader waits with nothing queued (`arena.robot.idle`).
        self.turn = IdleTurn()

    def put_target(self, target: T) -> None:
        """Offer the newest target, replacing one not yet taken."""
        if self._handed_off(target):
            return
        if self._target is not None:
            self.coalesced += 1
        self._target = target
        self.turn.close()
        self._wake()

    def put_notice(self, notice: N, *, clears: bool = False) -> None:
        """Queue a notice; `clears` drops the pending target."""
        if clears:
            self._target = None
        if self._handed_off(notice):
            return
        self._notices.append(notice)
        self.turn.close()
        self._wake()

    def close(self) -> None:
        """No more items will come; the reader gets `trio.EndOfChannel` once drained."""
        self.turn.close()
        super().close()

    def _handed_off(self, item: T | N) -> bool:
        # Only in the reader's idle turn: then nothing of its can be in flight, and the item
        # cannot overtake one that came before it.
        deliver_now = self.deliver_now
        return self.turn.is_open and deliver_now is not None and deliver_now(item)

    async def get(self) -> T | N:
        """The next notice if any, else the newest target; waits when there is neither."""
        while True:
            if self._notices:
                return self._notices.popleft()
            if self._target is not None:
                target, self._target = self._target, None
                return target
            if self.closed:
                raise trio.EndOfChannel
            self.turn.open()  # nothing queued, not closed: the reader's next item is the next put
            try:
                await self._park()
            finally:
                self.turn.close()

    def _has_items(self) -> bool:
        return self._target is not None or bool(self._notices)


class EventQueue(_Parked, Generic[T]):
    """A bounded queue that drops its oldest item when full, counting what it dropped."""

    def __init__(self, maxlen: int = 1024) -> None:
        super().__init__()
        self._items: deque[T] = deque(maxlen=maxlen)
        self.dropped = 0

    def put(self, item: T) -> None:
        """Append without ever blocking."""
        items = self._items
        if len(items) == items.maxlen:
            self.dropped += 1
        items.append(item)
        if self._waiting and not self._holding:  # `_wake`, inline: every event comes here
            self._lot.unpark_all()

    def _has_items(self) -> bool:
        return bool(self._items)

    def get_nowait(self) -> T:
        """The oldest item; raises `trio.WouldBlock` when empty."""
        if not self._items:
            raise trio.WouldBlock
        return self._items.popleft()

    def drain(self) -> list[T]:
        """Every queued item, oldest first, without waiting."""
        items = list(self._items)
        self._items.clear()
        return items

    async def get(self) -> T:
        """The oldest item, waiting for one; `trio.EndOfChannel` once closed and drained."""
        while True:
            if self._items:
                return self._items.popleft()
            if self.closed:
                raise trio.EndOfChannel
            await self._park()

    def __aiter__(self) -> EventQueue[T]:
        return self

    async def __anext__(self) -> T:
        try:
            return await self.get()
        except trio.EndOfChannel:
            raise StopAsyncIteration from None

    def __len__(self) -> int:
        return len(self._items)


class Observers(Generic[T]):
    """The observers' queues of one robot, each with the event types it takes, and the
    routing of an event to the queues that take its type (made on first use per type,
    forgotten when an observer comes or goes)."""

    def __init__(self) -> None:
        self._kinds: dict[EventQueue[T], frozenset[type] | None] = {}
        self._routes: dict[type, tuple[EventQueue[T], ...]] = {}

    def add(self, queue: EventQueue[T], kinds: frozenset[type] | None) -> None:
        """Give `queue` the events of the types `kinds` (None: every one) from now on."""
        self._kinds[queue] = kinds
        self._routes.clear()

    def remove(self, queue: EventQueue[T]) -> None:
        """Give `queue` nothing more, and close it."""
        del self._kinds[queue]
        self._routes.clear()
        queue.close()

    def close(self) -> None:
        """No more events: every queue ends once drained."""
        for queue in list(self._kinds):
            queue.close()

    def publish(self, event: T) -> None:
        """Put `event` on every queue that takes its type (never blocks)."""
        queues = self._routes.get(type(event))
        if queues is None:
            kind = type(event)
            queues = self._routes[kind] = tuple(
                queue for queue, kinds in self._kinds.items() if kinds is None or kind in kinds
            )
        for queue in queues:
            queue.put(event)
