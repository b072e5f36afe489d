"""One Arena WebSocket endpoint held open: `Session` (reconnection with `Backoff`, heartbeats),
`WatchingSession` (one that keeps a robot's newest state), and `running_session`, which runs
one for an `async with` block."""

from __future__ import annotations

import json
import logging
import random
from collections.abc import AsyncIterator, Callable, Iterator, Mapping
from contextlib import asynccontextmanager
from dataclasses import dataclass
from typing import Any, Self

import msgspec
import trio
from trio_websocket import (
    ConnectionClosed,
    HandshakeError,
    WebSocketConnection,
    open_websocket_url,
)

from arena.client import messages
from arena.client.errors import ClientTimeout, Disconnected
from arena.protocol.messages import encode

log = logging.getLogger(__name__)

#: Close codes after which retrying cannot help (bad key, no such robot): reported, and retried
#: only at the backoff's ceiling.
HOPELESS_CLOSES = frozenset({4401, 4403, 4404})


@dataclass(frozen=True)
class Backoff:
    """Reconnection delays: `initial * factor**n`, at most `maximum`, each scaled by a random
    factor in [1 - jitter, 1 + jitter] so that many clients do not come back in step."""

    initial: float = 0.5
    maximum: float = 30.0
    factor: float = 2.0
    jitter: float = 0.2

    def __post_init__(self) -> None:
        if not (0 < self.initial <= self.maximum and self.factor >= 1 and 0 <= self.jitter < 1):
            raise ValueError("backoff needs 0 < initial <= maximum, factor >= 1, 0 <= jitter < 1")

    def delays(self, rng: random.Random) -> Iterator[float]:
        """The delay before each retry, forever."""
        base = self.initial
        while True:
            yield base * rng.uniform(1 - self.jitter, 1 + self.jitter)
            base = min(self.maximum, base * self.factor)


class Session:
    """One Arena WebSocket endpoint held open: reconnection with backoff, heartbeats.

    `run()` loops until cancelled (or the session is `finished`): connect, call `on_connect`,
    hand every message (a dict) to `on_message`, and after a drop call `on_disconnect(reason)`
    and wait out the backoff. The backoff starts over after a connection that lasted
    `stable_after` seconds. `timeout` (seconds) bounds every wait of a call: a send, an answer.
    """

    def __init__(
        self,
        url: str,
        *,
        api_key: str | None = None,
        backoff: Backoff | None = None,
        heartbeat: float = 30.0,
        stable_after: float = 5.0,
        rng: random.Random | None = None,
        timeout: float = 5.0,
    ) -> None:
        if not timeout > 0:
            raise ValueError("timeout must be positive")
        self.url = url
        self.api_key = api_key
        self.backoff = backoff or Backoff()
        self.heartbeat = heartbeat
        self.stable_after = stable_after
        self.rng = rng or random.Random()
        self.timeout = timeout
        self.connects = 0
        self.last_error: str | None = None
        #: Set once the session is over for good (a released master): no reconnection.
        self.finished = False
        self._ws: WebSocketConnection | None = None
        self._up = trio.Event()
        self._opened_at: float | None = None

    @property
    def connected(self) -> bool:
        """Whether the WebSocket is open now."""
        return self._ws is not None

    async def wait_connected(self) -> None:
        """Until the WebSocket is open."""
        while self._ws is None:
            await self._up.wait()

    async def send(self, message: Mapping[str, Any] | msgspec.Struct) -> None:
        """Send a message now: a dict, or one of the protocol's structs (`client.messages`
        makes them); `Disconnected` while the link is down, `ClientTimeout` if the server does
        not take it within `timeout`, `ValueError` for a NaN or an infinity."""
        ws = self._ws
        if ws is None:
            raise Disconnected(self.last_error or "not connected")
        if isinstance(message, msgspec.Struct):
            text = encode(message)
        else:
            text = json.dumps(message, allow_nan=False)  # NaN is not JSON: refused here
        try:
            with trio.fail_after(self.timeout):
                await ws.send_message(text)
        except ConnectionClosed as closed:
            raise Disconnected(f"closed while sending ({closed.reason})") from None
        except trio.TooSlowError:
            raise ClientTimeout(f"the server took nothing for {self.timeout} s") from None

    async def try_send(self, message: Mapping[str, Any] | msgspec.Struct) -> bool:
        """Send if the link is up (whether it was); while it is down nothing is kept for
        later, so nothing stale goes out after a reconnection."""
        try:
            await self.send(message)
        except Disconnected:
            return False
        return True

    async def on_connect(self) -> None:
        """Called once each time the WebSocket opens."""

    async def on_message(self, message: dict[str, Any]) -> None:
        """Called for each message received."""

    async def on_disconnect(self, reason: str) -> None:
        """Called once each time an open WebSocket (or an attempt) is lost."""

    async def run(self) -> None:
        """Connect and reconnect until cancelled."""
        delays = self.backoff.delays(self.rng)
        while True:
            self._opened_at = None
            reason = await self._connect_once()
            self.last_error = reason
            with trio.CancelScope(shield=True):
                await self.on_disconnect(reason)
            if self.finished:
                return
            opened = self._opened_at
            if opened is not None and trio.current_time() - opened >= self.stable_after:
                delays = self.backoff.delays(self.rng)  # a good connection: start over
            delay = next(delays)
            log.info("%s: %s; retrying in %.2f s", self.url, reason, delay)
            await trio.sleep(delay)

    async def _connect_once(self) -> str:
        """One attempt, served until the connection ends: why it ended."""
        headers = [(b"Authorization", f"Bearer {self.api_key}".encode())] if self.api_key else []
        try:
            async with open_websocket_url(
                self.url, extra_headers=headers, connect_timeout=10, disconnect_timeout=2
            ) as ws:
                self._opened_at = trio.current_time()
                return await self._serve(ws)
        except HandshakeError as error:
            return f"cannot connect: {error}"
        except OSError as error:
            return f"cannot connect: {error.strerror or error}"
        except ConnectionClosed as closed:
            return _describe(closed)
        finally:
            if self._ws is not None:
                self._ws = None
                self._up = trio.Event()

    async def _serve(self, ws: WebSocketConnection) -> str:
        self._ws = ws
        self.connects += 1
        self.last_error = None
        self._up.set()
        async with trio.open_nursery() as nursery:
            nursery.start_soon(self._heartbeats)
            await self.on_connect()
            try:
                while True:
                    raw = await ws.get_message()
                    try:
                        message = json.loads(raw)
                    except ValueError:
                        continue
                    if isinstance(message, dict):
                        await self.on_message(message)
            except ConnectionClosed as closed:
                nursery.cancel_scope.cancel()
                return _describe(closed)
            finally:
                nursery.cancel_scope.cancel()

    async def _heartbeats(self) -> None:
        while True:
            await trio.sleep(self.heartbeat)
            try:
                await self.send(messages.heartbeat())
            except Disconnected:
                return


def _describe(closed: ConnectionClosed) -> str:
    reason = closed.reason
    if reason is None or reason.code in (None, 1005, 1006):
        return "connection lost"
    return f"closed by the server ({reason.code}: {reason.reason or reason.name})"


class WatchingSession(Session):
    """A session that keeps a robot's newest `state` and `joint_states` (a master's and a
    viewer's base)."""

    def __init__(self, url: str, **options: Any) -> None:
        super().__init__(url, **options)
        self.state: dict[str, Any] | None = None
        self.joints: dict[str, dict[str, Any]] = {}
        self._changed = trio.Event()

    async def wait_for(self, check: Callable[[Self], bool], timeout: float | None = None) -> None:
        """Until `check(self)` holds (checked after every message that changes something);
        `ClientTimeout` after `timeout` (default: the session's)."""
        limit = self.timeout if timeout is None else timeout
        with trio.move_on_after(limit) as waited:
            while not check(self):
                await self._changed.wait()
        if waited.cancelled_caught:
            raise ClientTimeout(f"what was waited for did not happen within {limit} s")

    def real(self, joint: str) -> float | None:
        """The newest real value of `joint`."""
        entry = self.joints.get(joint)
        return None if entry is None else entry.get("real_value")

    async def on_message(self, message: dict[str, Any]) -> None:
        kind = message.get("type")
        if kind == "state":
            self.state = message.get("data")
        elif kind == "joint_states":
            self.joints = {j["name"]: j for j in message.get("data") or []}
        self._changed.set()
        self._changed = trio.Event()


@asynccontextmanager
async def running_session(session: Session, connect_timeout: float = 10.0) -> AsyncIterator[None]:
    """Run `session` for the block, once connected (`ClientTimeout` if it cannot connect).

    The block's own exception comes out as it is, not in an exception group: the session's
    task never raises, so the block is the only thing in the nursery that can.
    """
    connected = True
    try:
        async with trio.open_nursery() as nursery:
            nursery.start_soon(session.run)
            with trio.move_on_after(connect_timeout):
                await session.wait_connected()
            connected = session.connected
            if connected:
                try:
                    yield
                finally:
                    nursery.cancel_scope.cancel()
            nursery.cancel_scope.cancel()
    except BaseExceptionGroup as group:
        if len(group.exceptions) != 1:
            raise
        single: BaseException | None = group.exceptions[0]
    else:
        single = None
    if single is not None:
        raise single  # (outside the handler: its own cause and context, as they were)
    if not connected:
        raise ClientTimeout(
            f"{session.url}: not connected within {connect_timeout} s ({session.last_error})"
        )
