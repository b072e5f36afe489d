"""Read readiness for many sockets from one edge-triggered epoll, so trio waits once for all.

trio waits on each socket by itself: every wait re-arms a one-shot registration with a system
call, and every wake-up goes through trio's bookkeeping for that descriptor. With a hundred
robots' WebSockets each waking fifty times a second, that was a good part of the fleet
benchmark's tail. Here the sockets stay registered (edge-triggered) in an epoll of our own;
trio waits on that one descriptor, and one task hands each ready socket to the task reading it.

Edge-triggered: an event comes only for data that arrives after the socket was last reported.
So a reader may wait only after a read that left the socket empty, one that failed with
EAGAIN or one shorter than it asked for (TCP hands over all it holds, so a short read emptied
the queue and whatever comes later is a new edge). `WebSocket` reads that way.

The hand-off costs a task switch and a pass of trio's loop per wake-up, which only pays when
wake-ups come for many sockets: with one master and one slave it cost ~18 us of CPU a command
more than trio's own wait. So readers wait on trio until `SHARED_FROM` sockets are attached.

Linux only (epoll); `ReadPoller.available()` says whether it can be used.
"""

from __future__ import annotations

import contextlib
import select

import trio

_EDGE_READ = getattr(select, "EPOLLIN", 0) | getattr(select, "EPOLLRDHUP", 0)
_EDGE_READ |= getattr(select, "EPOLLET", 0)
#: Attached sockets from which their readers wait here rather than each on trio.
SHARED_FROM = 8


class ReadPoller:
    """Wakes each socket's reader when new data arrives; run `run` in a nursery beside them."""

    def __init__(self, shared_from: int = SHARED_FROM) -> None:
        self.shared_from = shared_from
        self._epoll = select.epoll()
        self._sockets: dict[int, trio.socket.SocketType] = {}  # fd -> socket registered on it
        self._readers: dict[int, trio.lowlevel.Task] = {}  # fd -> the task waiting on it
        self._ready: set[int] = set()  # reported while no task was waiting
        self._attached: set[trio.socket.SocketType] = set()  # sockets whose readers use this
        self._running = False

    @staticmethod
    def available() -> bool:
        """Whether this system has epoll."""
        return hasattr(select, "epoll")

    async def run(self) -> None:
        """Hand ready sockets to their readers until cancelled; then readers wait on trio."""
        self._running = True
        try:
            while True:
                await trio.lowlevel.wait_readable(self._epoll.fileno())
                for fd, _ in self._epoll.poll(0):
                    reader = self._readers.pop(fd, None)
                    if reader is None:
                        self._ready.add(fd)
                    else:
                        trio.lowlevel.reschedule(reader)
        finally:
            self._running = False
            for reader in self._readers.values():  # they read again, then wait on trio
                trio.lowlevel.reschedule(reader)
            self._readers.clear()
            self._epoll.close()

    def attach(self, sock: trio.socket.SocketType) -> None:
        """A socket whose reader will wait here (until `forget`)."""
        self._attached.add(sock)

    async def wait_readable(self, sock: trio.socket.SocketType) -> None:
        """Wait until data arrives on `sock` after its last read that left it empty.

        With few sockets attached, this is trio's own wait. A socket that waited here before
        may then have an edge noted in `_ready`: it returns at once when it waits here again,
        and its reader finds the socket empty and waits anew, which is correct."""
        if not self._running or len(self._attached) < self.shared_from:
            await trio.lowlevel.wait_readable(sock)
            return
        fd = sock.fileno()
        if self._sockets.get(fd) is not sock:  # new, or a closed socket's number reused
            self._register(fd, sock)
        if fd in self._ready:
            self._ready.discard(fd)
            await trio.lowlevel.checkpoint()
            return
        if fd in self._readers:
            raise trio.BusyResourceError("another task is already reading this socket")
        self._readers[fd] = trio.lowlevel.current_task()

        def abort(_: trio.lowlevel.RaiseCancelT) -> trio.lowlevel.Abort:
            del self._readers[fd]
            return trio.lowlevel.Abort.SUCCEEDED

        await trio.lowlevel.wait_task_rescheduled(abort)

    def forget(self, sock: trio.socket.SocketType) -> None:
        """Stop watching `sock` (call before closing it); a task waiting on it wakes."""
        self._attached.discard(sock)
        fd = sock.fileno()
        if fd < 0 or self._sockets.get(fd) is not sock:
            return
        del self._sockets[fd]
        self._ready.discard(fd)
        with contextlib.suppress(OSError, ValueError):  # ValueError: the poller has stopped
            self._epoll.unregister(fd)
        reader = self._readers.pop(fd, None)
        if reader is not None:
            trio.lowlevel.reschedule(reader)

    def _register(self, fd: int, sock: trio.socket.SocketType) -> None:
        self._ready.discard(fd)
        try:
            self._epoll.register(fd, _EDGE_READ)
        except FileExistsError:  # still registered under a socket closed behind our back
            self._epoll.modify(fd, _EDGE_READ)
        self._sockets[fd] = sock
