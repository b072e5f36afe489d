"""The edge-triggered read poller on real loopback TCP sockets (virtual time for the waits)."""

from __future__ import annotations

import os
from collections.abc import AsyncIterator

import pytest
import trio
import trio.testing

from arena.server.read_poller import ReadPoller

pytestmark = pytest.mark.skipif(not ReadPoller.available(), reason="epoll is Linux only")

SocketPair = tuple[trio.socket.SocketType, trio.socket.SocketType]


async def _connected(listener: trio.socket.SocketType) -> SocketPair:
    """(the server's end, the client's end) of a new loopback TCP connection."""
    client = trio.socket.socket()
    await client.connect(listener.getsockname())
    server, _ = await listener.accept()
    return server, client


@pytest.fixture
async def listener() -> AsyncIterator[trio.socket.SocketType]:
    sock = trio.socket.socket()
    await sock.bind(("127.0.0.1", 0))
    sock.listen()
    yield sock
    sock.close()


@pytest.fixture
async def connection(listener: trio.socket.SocketType) -> AsyncIterator[SocketPair]:
    """A loopback TCP connection: (the server's end, the client's end), closed after the test."""
    pair = await _connected(listener)
    yield pair
    for sock in pair:
        sock.close()


@pytest.fixture
async def poller(nursery: trio.Nursery) -> ReadPoller:
    poller = ReadPoller(shared_from=0)  # every reader waits on the poller's epoll
    nursery.start_soon(poller.run)
    await trio.testing.wait_all_tasks_blocked()
    return poller


async def _waits_forever(poller: ReadPoller, sock: trio.socket.SocketType) -> bool:
    """True if `wait_readable` is still waiting after a virtual minute."""
    with trio.move_on_after(60) as scope:
        await poller.wait_readable(sock)
    return scope.cancelled_caught


async def test_a_waiting_reader_wakes_when_data_arrives(
    poller: ReadPoller, connection: SocketPair, autojump_clock: trio.testing.MockClock
) -> None:
    server, client = connection
    assert await _waits_forever(poller, server)  # nothing sent: nothing to wake for
    woke = trio.Event()

    async def reader() -> None:
        await poller.wait_readable(server)
        woke.set()

    with trio.fail_after(60):  # virtual time: fails at once if the reader is never woken
        async with trio.open_nursery() as nursery:
            nursery.start_soon(reader)
            await trio.testing.wait_all_tasks_blocked()
            assert not woke.is_set()
            await client.send(b"command")
    assert os.read(server.fileno(), 100) == b"command"


async def test_data_that_arrives_while_the_reader_is_busy_is_not_missed(
    poller: ReadPoller, connection: SocketPair, autojump_clock: trio.testing.MockClock
) -> None:
    server, client = connection
    await client.send(b"first")
    assert not await _waits_forever(poller, server)  # there when the socket was registered
    assert os.read(server.fileno(), 100) == b"first"
    # The reader is busy (not waiting) when the next data comes: the poller keeps the edge.
    await client.send(b"second")
    await trio.testing.wait_all_tasks_blocked()
    assert not await _waits_forever(poller, server)
    assert os.read(server.fileno(), 100) == b"second"
    assert await _waits_forever(poller, server)  # the edge was used up


async def test_a_cancelled_wait_leaves_no_reader_behind(
    poller: ReadPoller, connection: SocketPair, autojump_clock: trio.testing.MockClock
) -> None:
    server, client = connection
    assert await _waits_forever(poller, server)
    await client.send(b"late")
    assert not await _waits_forever(poller, server)  # not "already being read"


async def test_two_readers_of_one_socket_are_refused(
    poller: ReadPoller, connection: SocketPair, autojump_clock: trio.testing.MockClock
) -> None:
    server, _ = connection
    async with trio.open_nursery() as nursery:
        nursery.start_soon(poller.wait_readable, server)
        await trio.testing.wait_all_tasks_blocked()
        with pytest.raises(trio.BusyResourceError):
            await poller.wait_readable(server)
        nursery.cancel_scope.cancel()


async def test_forgetting_a_socket_wakes_its_reader(
    poller: ReadPoller, connection: SocketPair, autojump_clock: trio.testing.MockClock
) -> None:
    server, _ = connection
    with trio.fail_after(60):
        async with trio.open_nursery() as nursery:
            nursery.start_soon(poller.wait_readable, server)
            await trio.testing.wait_all_tasks_blocked()
            poller.forget(server)  # the reader returns (and would find the socket closed)


async def test_a_socket_number_reused_after_a_close_is_watched_again(
    poller: ReadPoller, listener: trio.socket.SocketType, autojump_clock: trio.testing.MockClock
) -> None:
    old_server, old_client = await _connected(listener)
    assert await _waits_forever(poller, old_client)  # registered
    number = old_client.fileno()
    old_client.close()  # behind the poller's back: the kernel drops its registration
    client = trio.socket.socket()  # the lowest free number: the old one
    assert client.fileno() == number
    await client.connect(listener.getsockname())
    server, _ = await listener.accept()
    await server.send(b"to the new socket")
    assert not await _waits_forever(poller, client)
    assert os.read(client.fileno(), 100) == b"to the new socket"
    for sock in (old_server, server, client):
        sock.close()


async def _read_when_ready(poller: ReadPoller, sock: trio.socket.SocketType) -> bytes:
    """Wait and read as the transport does: a wake-up that finds nothing waits again."""
    with trio.fail_after(60):  # virtual time: fails at once if the reader is never woken
        while True:
            await poller.wait_readable(sock)
            try:
                return os.read(sock.fileno(), 100)
            except BlockingIOError:
                continue


async def test_readers_wait_on_trio_until_enough_sockets_share_the_poller(
    nursery: trio.Nursery,
    listener: trio.socket.SocketType,
    autojump_clock: trio.testing.MockClock,
) -> None:
    poller = ReadPoller(shared_from=2)
    nursery.start_soon(poller.run)
    (server, client), (other, _) = await _connected(listener), await _connected(listener)
    poller.attach(server)
    assert await _waits_forever(poller, server)
    assert not poller._sockets  # one socket: trio's own wait, nothing registered here
    await client.send(b"alone")
    assert await _read_when_ready(poller, server) == b"alone"
    poller.attach(other)  # two: both wait on the poller from now on
    assert await _waits_forever(poller, server)
    assert server.fileno() in poller._sockets
    await client.send(b"shared")
    assert await _read_when_ready(poller, server) == b"shared"
    poller.forget(other)  # back to one: trio's wait again, with the edge the poller kept
    await client.send(b"alone again")
    assert await _read_when_ready(poller, server) == b"alone again"
    assert await _waits_forever(poller, server)


async def test_once_the_poller_stops_readers_wait_on_trio(
    listener: trio.socket.SocketType, autojump_clock: trio.testing.MockClock
) -> None:
    poller = ReadPoller(shared_from=0)
    server, client = await _connected(listener)
    woke = trio.Event()

    async def reader() -> None:
        await poller.wait_readable(server)
        woke.set()

    with trio.fail_after(60):
        async with trio.open_nursery() as readers, trio.open_nursery() as polling:
            polling.start_soon(poller.run)
            await trio.testing.wait_all_tasks_blocked()
            readers.start_soon(reader)
            await trio.testing.wait_all_tasks_blocked()
            assert not woke.is_set()
            polling.cancel_scope.cancel()
    assert woke.is_set()  # woken when the poller stopped, not left waiting
    assert await _waits_forever(poller, server)
    await client.send(b"after")
    assert not await _waits_forever(poller, server)
    server.close()
    client.close()
