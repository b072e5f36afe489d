"""One accepted WebSocket of any endpoint: its key, its query switches, refusals, errors,
heartbeats, the reading loop, and the race between the client leaving, the robot ending the
link and the server shutting down.

Each connection runs its tasks in one nursery and ends in one of three ways: the client goes
away (for a master or slave that is a loss, and the robot's loss policy applies), the robot
ends the link (detached, deleted), or the server shuts down (closed with 1001 at once).
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Awaitable, Callable, Iterable
from typing import TypeVar

import trio

from arena.protocol import messages as wire
from arena.protocol.errors import ArenaError, ErrorCode
from arena.protocol.ws_frames import WebSocketClosed
from arena.robot.handle import Robot
from arena.server.access import WS_ROLE_FOR
from arena.server.auth import authorize, refuse
from arena.server.base import ArenaApp
from arena.server.identity import ANONYMOUS, Principal
from arena.server.ws.backpressure import Encoded, LatestWins, PeerSocket

T = TypeVar("T")

#: Ids of peers that do not name themselves (`ws-master-1`, ...), unique in this process.
peer_ids = itertools.count(1)

#: Close codes: 1000 normal, 1001 going away, 4000 + an HTTP-like status for refusals.
CLOSE_NORMAL, CLOSE_GOING_AWAY = 1000, 1001
CLOSE_FOR = {
    ErrorCode.UNAUTHORIZED: 4401,
    ErrorCode.FORBIDDEN: 4403,
    ErrorCode.UNKNOWN_ROBOT: 4404,
    ErrorCode.MASTER_ACTIVE: 4409,
    ErrorCode.ESTOPPED: 4423,
    ErrorCode.TAKEN_OVER: 4409,
    ErrorCode.MASTER_LOST: 4408,
    ErrorCode.NODE_LOST: 4503,
    ErrorCode.LIMIT_REACHED: 4429,
}

BINARY_REFUSAL = "Send JSON text frames, not binary frames."


def _switch(args: dict[str, str], name: str) -> bool:
    """A query parameter that is on unless it says off."""
    return args.get(name, "").lower() not in ("0", "false", "no", "off")


def flag(value: str | None) -> bool:
    """A query parameter that is off unless it says on."""
    return value is not None and value.lower() in ("1", "true", "yes", "on")


class Connection(LatestWins):
    """One accepted WebSocket: send helpers (`LatestWins`), refusals, and the shutdown race."""

    def __init__(self, app: ArenaApp, ws: PeerSocket, role: str) -> None:
        super().__init__(ws, app.metrics)
        self.app = app
        self.role = role  # master, slave or viewer
        self.args = ws.request.args
        #: Query parameters `acks=false`, `joint_states=false`: a fire-and-forget master
        #: hears only refusals; a viewer may watch state changes alone.
        self.wants_acks = _switch(self.args, "acks")
        self.wants_joint_states = _switch(self.args, "joint_states")
        self.closed = False
        #: Who connected (`authorized` sets it; a carried connection: the caller its node
        #: sent), and when on trio's clock their token expires (None: a key, or no
        #: credential needed).
        self.principal: Principal = ANONYMOUS
        self.expires_at: float | None = None
        self._authorized = False
        self._caller_key: tuple[str, str] | None = None  # (tenant, name) while counted
        #: The robots it is a peer of, once counted open (`count_open`): who sees them all
        #: sees it counted.
        self.robots: tuple[str, ...] = ()

    def count_open(self, robots: Iterable[str]) -> None:
        """Counted open in `/metrics` and `GET /`, by role, on `robots`."""
        self.robots = tuple(robots)
        self.app.metrics.connection_opened(self.role, self.robots)

    def count_closed(self) -> None:
        """Counted closed (after `count_open`)."""
        self.app.metrics.connection_closed(self.role, self.robots)

    def error(self, code: ErrorCode | str, message: str) -> Encoded:
        """An `error` message to send, counted."""
        self.app.metrics.message_errors[str(code)] += 1
        return Encoded("error", wire.error_message(code, message))

    async def send_error(self, code: ErrorCode | str, message: str) -> None:
        """Send an `error` message and count it."""
        await self.send(self.error(code, message))

    async def close(self, code: int, reason: str = "") -> None:
        """Close once."""
        if not self.closed:
            self.closed = True
            self.ws.close_nowait(code, reason)
            self._ended.set()
        await trio.lowlevel.checkpoint()

    async def refuse(self, error: ArenaError) -> None:
        """Tell the client why in an `error` message, then close with a 4xxx code."""
        await self.send_error(error.code, error.message)
        await self.close(CLOSE_FOR.get(error.code, 4400), error.message)

    async def run(self, body: Callable[[trio.Nursery], Awaitable[None]]) -> None:
        """Run `body` until it returns, the client leaves or the server shuts down."""
        self.app.connections.add(self)
        try:
            await self._run(body)
        finally:
            self.app.connections.discard(self)

    async def _run(self, body: Callable[[trio.Nursery], Awaitable[None]]) -> None:
        async with trio.open_nursery() as nursery:

            async def on_shutdown() -> None:
                await self.app.shutting_down.wait()
                await self.close(CLOSE_GOING_AWAY, "server shutting down")
                nursery.cancel_scope.cancel()

            async def main() -> None:
                await body(nursery)
                nursery.cancel_scope.cancel()

            async def on_closed() -> None:
                await self._ended.wait()
                nursery.cancel_scope.cancel()

            nursery.start_soon(on_shutdown)
            nursery.start_soon(on_closed)
            nursery.start_soon(self.catch_up_when_read)
            if self.expires_at is not None:
                nursery.start_soon(self._expire, self.expires_at)
            nursery.start_soon(main)

    async def _expire(self, deadline: float) -> None:
        """Close with 4401 when the token expires (its `exp`, leeway in, taken to trio's
        clock at connect)."""
        await trio.sleep_until(deadline)
        self.app.metrics.auth_refused["expired"] += 1
        await self.refuse(
            ArenaError(ErrorCode.UNAUTHORIZED, "The token has expired: connect with a new one.")
        )

    async def authorized(self) -> bool:
        """Check the key or token and the role; a refusal is sent and the answer is False. A
        connection carried from another node of the fleet was checked there (`trusted`); its
        caller's tenant and scope are checked here all the same (`sees`)."""
        if getattr(self.ws, "trusted", False):  # `principal`: the caller the node sent
            return True
        if self._authorized:  # (checked once: the master endpoint asks before a robot's)
            return True
        try:
            self.principal = authorize(
                self.app,
                self.ws.request.headers.get("authorization"),
                self.args.get("token"),
                WS_ROLE_FOR[self.role],
                f"The {self.role} WebSocket",
                read_only=self.role == "viewer",
            )
        except ArenaError as error:
            await self.refuse(error)
            return False
        if not await self._hold():
            return False
        expires = self.principal.expires
        if expires is not None:  # wall clock to trio's, once
            self.expires_at = trio.current_time() + (expires - time.time())
        self._authorized = True
        return True

    async def _hold(self) -> bool:
        """Count this socket among its caller's (`let_go` uncounts it); refused when the
        caller holds `max_websockets_per_caller` already."""
        key = (self.principal.tenant, self.principal.name)
        held, most = self.app.websockets_held, self.app.arena_config.max_websockets_per_caller
        if held[key] >= most:
            await self.refuse(
                ArenaError(
                    ErrorCode.LIMIT_REACHED,
                    f"{self.principal.name!r} holds {most} WebSockets open, the most allowed "
                    "(max_websockets_per_caller): close one first.",
                )
            )
            return False
        held[key] += 1
        self._caller_key = key
        return True

    def let_go(self) -> None:
        """The socket is closed: no longer its caller's to count."""
        if self._caller_key is not None:
            held = self.app.websockets_held
            held[self._caller_key] -= 1
            if not held[self._caller_key]:
                del held[self._caller_key]
            self._caller_key = None

    def sees(self, robot_id: str) -> bool:
        """The caller may see the robot (its tenant and scope); counted when not."""
        if self.app.access.sees(self.principal, robot_id):
            return True
        refuse(self.app, "scope")
        return False

    async def accept(self, robot_id: str) -> Robot | None:
        """Check the key and find the robot; a refusal is sent and the answer is None. A
        robot the caller may not see is refused as one that does not exist."""
        if not await self.authorized():
            return None
        try:
            robot = self.app.manager.get(robot_id)
            if not self.sees(robot_id):
                raise ArenaError(ErrorCode.UNKNOWN_ROBOT, f"No robot with id {robot_id!r}.")
        except ArenaError as error:
            await self.refuse(error)
            return None
        return robot

    async def receive_text(self) -> str | None:
        """The next text frame; binary frames are answered with an error and skipped."""
        while True:
            try:
                frame = await self.ws.receive()
            except WebSocketClosed:
                return None
            self.app.metrics.messages[self.role] += 1
            if isinstance(frame, str):
                return frame
            await self.send_error(ErrorCode.BINARY_NOT_SUPPORTED, BINARY_REFUSAL)

    async def heartbeats(self) -> None:
        """Send a heartbeat every `heartbeat_interval`, for ever."""
        interval = self.app.arena_config.heartbeat_interval
        while True:
            await trio.sleep(interval)
            await self.send(wire.HeartbeatMessage(timestamp=wire.now_iso()))

    async def answer_error(self, error: ArenaError) -> bool:
        """Answer a message's error with an `error` message; False (and the socket closed)
        when it is that the robot is gone."""
        if error.code is ErrorCode.ROBOT_STOPPED:
            await self.close(CLOSE_NORMAL, "robot deleted")
            return False
        await self.send_error(error.code, error.message)
        return True

    async def read_loop(
        self, decode: Callable[[str], T], handle: Callable[[T], Awaitable[None]]
    ) -> None:
        """Decode and handle frames until the client leaves; errors are answered, not fatal."""
        while True:
            raw = await self.receive_text()
            if raw is None:
                return
            started = time.perf_counter()
            try:
                await handle(decode(raw))
            except ArenaError as error:
                if not await self.answer_error(error):
                    return
            self.app.metrics.observe_latency(time.perf_counter() - started)

    def in_hand(self, first: str) -> tuple[list[str | bytes], bool]:
        """`first` and the frames in hand after it (the rest of a burst, up to the
        transport's fairness bound); True when the peer's close came among them."""
        frames: list[str | bytes] = [first]
        closed = False
        if self.ws.holds_more():  # (one at a time, nothing is)
            try:
                while (frame := self.ws.next_in_hand()) is not None:
                    frames.append(frame)
            except WebSocketClosed:
                closed = True
            self.app.metrics.messages[self.role] += len(frames) - 1
        return frames, closed
