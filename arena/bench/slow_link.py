"""A slow network on loopback: a TCP relay that delays, jitters, stalls, throttles and cuts.

`SlowLink` listens on 127.0.0.1 (port 0: the system's choice) and relays each connection to a
target, shaping each direction as `LinkShape` says, in the manner of toxiproxy (this machine's
kernel has no netem). The shape may change at any time: it applies to the bytes read after.

- `delay` and `jitter`: each chunk read is due `delay ± jitter` seconds later (uniform, never
  before the chunk ahead of it: TCP keeps the order, so a late chunk holds up the rest).
- `stall()` holds every byte in both directions until `release()` (or for `seconds`), then
  lets them go in one burst, as a link that stops and recovers does.
- `bandwidth`: bytes a second per direction, taken in at that rate: what the link has not
  taken waits unread in the sender's socket, unacknowledged, as it would before a real
  bottleneck (the sender's kernel sees its backlog; with `kernel_buffer` small, the relay's
  own sockets hide little of it). At most `buffer_bytes` wait in the relay (a stall's).
- `cut()` drops every connection at once (both ends see it closed); `refuse` drops new ones.

All waits are on trio's clock, so under `trio.testing.MockClock` the link's time is virtual
and a test of it is deterministic. `random_seed` fixes the jitter.
"""

from __future__ import annotations

import math
import random
import socket
from collections import deque
from dataclasses import dataclass

import trio

#: Largest chunk read or written at once (a bandwidth-limited chunk goes out in these).
CHUNK = 4096


@dataclass
class LinkShape:
    """How one direction of the link treats bytes (seconds, bytes a second)."""

    delay: float = 0.0
    jitter: float = 0.0
    bandwidth: float | None = None  # None: as fast as loopback
    buffer_bytes: int = 256 * 1024  # read ahead at most this much, then backpressure

    def due_after(self, rng: random.Random) -> float:
        """Seconds until a chunk read now may be written."""
        jitter = rng.uniform(-self.jitter, self.jitter) if self.jitter > 0 else 0.0
        return max(0.0, self.delay + jitter)


@dataclass
class DirectionStats:
    """What one direction passed."""

    chunks: int = 0
    bytes: int = 0


class SlowLink:
    """A shaping TCP relay to `target_host:target_port` (run `serve` in a nursery)."""

    def __init__(
        self,
        target_host: str,
        target_port: int,
        *,
        random_seed: int = 0,
        kernel_buffer: int | None = None,
    ) -> None:
        self.target = (target_host, target_port)
        #: The relay's sockets' kernel buffers (SO_RCVBUF, SO_SNDBUF), made small to model a
        #: link that queues little rather than a proxy that takes everything at once.
        self.kernel_buffer = kernel_buffer
        self.up = LinkShape()  # client -> target
        self.down = LinkShape()  # target -> client
        self.up_stats = DirectionStats()
        self.down_stats = DirectionStats()
        self.port = 0
        self.refuse = False  # new connections are closed at once
        self.connections = 0  # open now
        self.accepted = 0  # in all
        self._rng = random.Random(random_seed)
        self._released = trio.Event()
        self._released.set()
        self._scopes: set[trio.CancelScope] = set()

    # -- control ---------------------------------------------------------------------------------

    def shape(
        self,
        *,
        delay: float | None = None,
        jitter: float | None = None,
        bandwidth: float | None = None,
    ) -> None:
        """Set both directions (`delay` one way; `bandwidth` `math.inf` lifts the limit);
        what is not given stays."""
        for direction in (self.up, self.down):
            if delay is not None:
                direction.delay = delay
            if jitter is not None:
                direction.jitter = jitter
            if bandwidth is not None:
                direction.bandwidth = None if math.isinf(bandwidth) else float(bandwidth)

    @property
    def stalled(self) -> bool:
        """True while bytes are held."""
        return not self._released.is_set()

    def stall(self) -> None:
        """Hold every byte in both directions until `release`."""
        if self._released.is_set():
            self._released = trio.Event()

    def release(self) -> None:
        """Let the held bytes go, in one burst."""
        self._released.set()

    async def stall_for(self, seconds: float) -> None:
        """Stall now, release after `seconds`."""
        self.stall()
        await trio.sleep(seconds)
        self.release()

    def cut(self) -> None:
        """Drop every open connection now (both ends see it closed)."""
        for scope in list(self._scopes):
            scope.cancel()

    # -- running ---------------------------------------------------------------------------------

    async def serve(self, task_status: trio.TaskStatus[int] = trio.TASK_STATUS_IGNORED) -> None:
        """Listen on 127.0.0.1 and relay until cancelled; `task_status` gets the port."""
        listeners = await trio.open_tcp_listeners(0, host="127.0.0.1")
        self.port = listeners[0].socket.getsockname()[1]
        async with trio.open_nursery() as nursery:
            nursery.start_soon(trio.serve_listeners, self._relay, listeners)
            task_status.started(self.port)

    async def _relay(self, client: trio.SocketStream) -> None:
        self.accepted += 1
        if self.refuse:
            await trio.aclose_forcefully(client)
            return
        try:
            upstream = await trio.open_tcp_stream(*self.target)
        except OSError:
            await trio.aclose_forcefully(client)
            return
        if self.kernel_buffer is not None:
            for stream in (client, upstream):
                for option in (socket.SO_RCVBUF, socket.SO_SNDBUF):
                    stream.setsockopt(socket.SOL_SOCKET, option, self.kernel_buffer)
        scope = trio.CancelScope()
        self._scopes.add(scope)
        self.connections += 1
        try:
            with scope:
                async with trio.open_nursery() as nursery:
                    for source, sink, shape, stats in (
                        (client, upstream, self.up, self.up_stats),
                        (upstream, client, self.down, self.down_stats),
                    ):
                        nursery.start_soon(self._pump, source, sink, shape, stats, nursery)
        finally:
            self.connections -= 1
            self._scopes.discard(scope)
            with trio.CancelScope(shield=True):
                await trio.aclose_forcefully(client)
                await trio.aclose_forcefully(upstream)

    async def _pump(
        self,
        source: trio.SocketStream,
        sink: trio.SocketStream,
        shape: LinkShape,
        stats: DirectionStats,
        nursery: trio.Nursery,
    ) -> None:
        """One direction: a reader that takes chunks in at the bandwidth and stamps each with
        its due time, a writer that waits for it (and for a stall's end) before writing."""
        held: deque[tuple[float, bytes]] = deque()
        held_bytes = 0
        more = trio.lowlevel.ParkingLot()  # the writer waits here for chunks
        room = trio.lowlevel.ParkingLot()  # the reader waits here for buffer space
        ended = False

        async def read() -> None:
            nonlocal held_bytes, ended
            last_due = -math.inf
            free_at = -math.inf  # when the bandwidth allows the next byte in
            try:
                while True:
                    while held_bytes >= shape.buffer_bytes:
                        await room.park()
                    data = await source.receive_some(CHUNK)
                    if not data:
                        break
                    now = trio.current_time()
                    last_due = max(last_due, now + shape.due_after(self._rng))
                    held.append((last_due, data))
                    held_bytes += len(data)
                    more.unpark_all()
                    if shape.bandwidth:  # taken in at the link's rate: the rest waits unread
                        free_at = max(free_at, now) + len(data) / shape.bandwidth
                        await trio.sleep_until(free_at)
            except (trio.BrokenResourceError, trio.ClosedResourceError):
                pass
            ended = True
            more.unpark_all()

        async def write() -> None:
            nonlocal held_bytes
            while True:
                while not held:
                    if ended:
                        nursery.cancel_scope.cancel()  # one side closed: so does the relay
                        return
                    await more.park()
                due, data = held[0]
                await trio.sleep_until(due)
                await self._released.wait()
                held.popleft()
                held_bytes -= len(data)
                room.unpark_all()
                try:
                    await sink.send_all(data)
                except (trio.BrokenResourceError, trio.ClosedResourceError):
                    nursery.cancel_scope.cancel()
                    return
                stats.chunks += 1
                stats.bytes += len(data)

        nursery.start_soon(read)
        nursery.start_soon(write)
