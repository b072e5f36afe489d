"""The test relay (arena/bench/slow_link.py): delay, jitter, stalls, bandwidth and cuts, on
trio's mock clock (virtual time: every figure here is exact, none depends on the machine)."""

from __future__ import annotations

import os
from collections.abc import AsyncIterator
from dataclasses import dataclass, field

import pytest
import trio
from trio.testing import MockClock

from arena.bench.slow_link import CHUNK, SlowLink


@dataclass
class Echo:
    """A TCP server that echoes, noting when (trio time) each chunk came."""

    port: int = 0
    arrivals: list[tuple[float, bytes]] = field(default_factory=list)
    closed: trio.Event = field(default_factory=trio.Event)

    async def handle(self, stream: trio.SocketStream) -> None:
        try:
            while data := await stream.receive_some(65536):
                self.arrivals.append((trio.current_time(), data))
                await stream.send_all(data)
        except trio.BrokenResourceError:
            pass
        finally:
            self.closed.set()

    def received(self) -> bytes:
        return b"".join(data for _, data in self.arrivals)


@pytest.fixture
async def echo(nursery: trio.Nursery) -> Echo:
    server = Echo()
    listeners = await trio.open_tcp_listeners(0, host="127.0.0.1")
    await nursery.start(trio.serve_listeners, server.handle, listeners)
    server.port = listeners[0].socket.getsockname()[1]
    return server


@pytest.fixture
async def link(nursery: trio.Nursery, echo: Echo) -> AsyncIterator[SlowLink]:
    relay = SlowLink("127.0.0.1", echo.port, random_seed=7)
    await nursery.start(relay.serve)
    yield relay


async def receive_exactly(stream: trio.SocketStream, size: int) -> bytes:
    data = b""
    while len(data) < size:
        chunk = await stream.receive_some(size - len(data))
        assert chunk, "closed early"
        data += chunk
    return data


async def test_bytes_pass_unchanged_and_in_order_through_jitter(
    autojump_clock: MockClock, link: SlowLink, echo: Echo
) -> None:
    link.shape(delay=0.1, jitter=0.08)  # jitter nearly as large as the delay: order must hold
    payload = os.urandom(200_000)
    async with (
        await trio.open_tcp_stream("127.0.0.1", link.port) as stream,
        trio.open_nursery() as nursery,
    ):
        nursery.start_soon(stream.send_all, payload)
        assert await receive_exactly(stream, len(payload)) == payload
    assert echo.received() == payload
    assert link.up_stats.bytes == link.down_stats.bytes == len(payload)


async def test_delay_and_jitter_bound_each_chunk(
    autojump_clock: MockClock, link: SlowLink, echo: Echo
) -> None:
    link.shape(delay=0.2, jitter=0.05)
    sent: list[float] = []
    async with await trio.open_tcp_stream("127.0.0.1", link.port) as stream:
        for n in range(40):
            sent.append(trio.current_time())
            await stream.send_all(bytes([n]))
            await receive_exactly(stream, 1)  # one round trip each: chunks stay apart
            await trio.sleep(0.05)
    lags = [arrived - at for at, (arrived, _) in zip(sent, echo.arrivals, strict=True)]
    assert all(0.15 - 1e-9 <= lag <= 0.25 + 1e-9 for lag in lags)
    assert max(lags) - min(lags) > 0.05  # the jitter is there (seeded: the same every run)


async def test_a_stall_holds_everything_then_lets_it_go_in_one_burst(
    autojump_clock: MockClock, link: SlowLink, echo: Echo
) -> None:
    link.shape(delay=0.05)
    async with await trio.open_tcp_stream("127.0.0.1", link.port) as stream:
        await stream.send_all(b"before")
        await receive_exactly(stream, 6)
        link.stall()
        stalled_at = trio.current_time()
        for n in range(60):  # 30 a second for 2 s, all held
            await stream.send_all(b"%02d" % n)
            await trio.sleep(1 / 30)
        await trio.sleep_until(stalled_at + 2.1)
        assert echo.received() == b"before"  # nothing got through
        link.release()
        released_at = trio.current_time()
        await receive_exactly(stream, 120)
    burst = echo.arrivals[1:]
    assert b"".join(data for _, data in burst) == b"".join(b"%02d" % n for n in range(60))
    assert {at for at, _ in burst} == {released_at}  # one burst, at the release


async def test_bandwidth_limits_the_rate_and_pushes_back_on_the_sender(
    autojump_clock: MockClock, link: SlowLink, echo: Echo
) -> None:
    link.shape(bandwidth=10_000)  # 10 kB/s each way
    link.up.buffer_bytes = 8192
    payload = os.urandom(50_000)
    async with await trio.open_tcp_stream("127.0.0.1", link.port) as stream:
        started = trio.current_time()
        async with trio.open_nursery() as nursery:
            nursery.start_soon(stream.send_all, payload)
            await receive_exactly(stream, len(payload))
        took = trio.current_time() - started
    assert echo.received() == payload
    # 5 s at 10 kB/s, but for the last chunk taken in (the way back overlaps the way there,
    # as two links do)
    assert (len(payload) - CHUNK) / 10_000 <= took <= (len(payload) + 4 * CHUNK) / 10_000


async def test_a_cut_closes_both_ends_and_refuse_turns_new_connections_away(
    autojump_clock: MockClock, link: SlowLink, echo: Echo
) -> None:
    stream = await trio.open_tcp_stream("127.0.0.1", link.port)
    await stream.send_all(b"hi")
    assert await receive_exactly(stream, 2) == b"hi"
    assert link.connections == 1
    link.cut()
    with pytest.raises((trio.BrokenResourceError, AssertionError)):
        await receive_exactly(stream, 1)  # the end (or a reset)
    await echo.closed.wait()  # the target's end too
    await stream.aclose()
    assert link.connections == 0
    link.refuse = True
    stream = await trio.open_tcp_stream("127.0.0.1", link.port)
    with pytest.raises((trio.BrokenResourceError, AssertionError)):
        await receive_exactly(stream, 1)
    await stream.aclose()
    link.refuse = False
    async with await trio.open_tcp_stream("127.0.0.1", link.port) as stream:
        await stream.send_all(b"again")
        assert await receive_exactly(stream, 5) == b"again"
