"""`MasterSession`: a master of one robot (or group), its requests matched to their answers."""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import AsyncIterator, Mapping, Sequence
from contextlib import asynccontextmanager
from typing import Any, Self
from urllib.parse import quote

import msgspec
import trio

from arena.client import messages
from arena.client.errors import ArenaClientError, ClientTimeout, Disconnected, refusal
from arena.client.messages import now_iso, ws_url
from arena.client.session import WatchingSession, running_session

log = logging.getLogger(__name__)


class _Pending:
    """A request waiting for its answer: a message of type `expects` (`ack`, `released`), or
    an `error` (which answers the oldest request, as the server answers in order)."""

    __slots__ = ("answer", "done", "error", "expects")

    def __init__(self, expects: str) -> None:
        self.expects = expects
        self.answer: dict[str, Any] = {}
        self.error: ArenaClientError | None = None
        self.done = trio.Event()

    def settle(
        self, answer: dict[str, Any] | None = None, error: ArenaClientError | None = None
    ) -> None:
        """The answer came (or the error that ends the wait)."""
        if answer is not None:
            self.answer = answer
        self.error = error
        self.done.set()


class MasterSession(WatchingSession):
    """A master of one robot (or group): commands with their acknowledgments, state, joints.

    Every call ends: a refused command raises `Refused` (the server's code and message), a
    value that is not a finite number `ValueError` before anything is sent, a wait longer than
    `timeout` `ClientTimeout`, and a link that is down `Disconnected`. While the link is down
    the server applies its loss policy (an e-stop by default), so a reconnected master finds
    the robot e-stopped until a reset. `release()` hands the robot back (it holds where it is,
    `idle`); `open` releases on a normal end of its block, never after an exception.
    """

    #: Requests awaiting an answer at most (beyond, the oldest are failed): a server that
    #: stops answering cannot make the session grow.
    MAX_PENDING = 1024

    def __init__(self, url: str, **options: Any) -> None:
        super().__init__(url, **options)
        self.errors: deque[dict[str, Any]] = deque(maxlen=64)
        #: The `released` data once the robot was released.
        self.released: dict[str, Any] | None = None
        #: The newest `detached` data (taken over, e-stopped sequence, ...), if any.
        self.detached: dict[str, Any] | None = None
        #: The server has this master paused (`pause` until `resume`): send nothing.
        self.paused = False
        #: `pause` messages so far (one that came and went between two looks still counts).
        self.pauses = 0
        #: `stopped` data, newest last: motions of this master's the collision guard stopped
        #: on their way after accepting them (the arm holds where it got to).
        self.stops: deque[dict[str, Any]] = deque(maxlen=64)
        self.stop_count = 0  # `stopped` messages so far
        self._resumed = trio.Event()
        self._resumed.set()
        #: Why the server would not have this master (MASTER_ACTIVE, UNKNOWN_ROBOT, ...).
        self.refusal: ArenaClientError | None = None
        #: A refusal of the first connection ends the session (`open` sets it: its caller is
        #: told at once); else the session asks again with its backoff, as a driver waiting
        #: for the robot to be free does.
        self.stop_on_refusal = False
        self._pending: deque[_Pending] = deque()
        self._settled = trio.Event()  # accepted (a first `state`) or refused

    @classmethod
    @asynccontextmanager
    async def open(
        cls,
        base_url: str,
        robot_id: str,
        *,
        takeover: bool = False,
        master_id: str | None = None,
        release: bool = True,
        **options: Any,
    ) -> AsyncIterator[Self]:
        """Run a session to `/ws/master/{robot_id}` for the `async with` block, connected.

        When the block ends normally the robot is released (unless `release` is False, or the
        robot let this master go already: `detached`); when it ends with an exception the
        session just goes, and the loss policy applies.
        """
        query = {"takeover": "1" if takeover else "", "id": master_id or ""}
        session = cls(ws_url(base_url, f"/ws/master/{quote(robot_id)}", **query), **options)
        session.stop_on_refusal = True
        async with running_session(session):
            yield session
            # Reached only when the block ended without an exception.
            if release and session.released is None and session.detached is None:
                if session.connected:
                    await session.release()
                else:
                    log.warning(
                        "%s: not released: the link is down (%s)", session.url, session.last_error
                    )

    async def command(
        self, joints: Mapping[str, float], timeout: float | None = None, **data: Any
    ) -> dict[str, Any]:
        """Send a command and return its acknowledgment (`data.status`: accepted or clamped,
        with what was clamped). A refusal raises `Refused` with the server's code."""
        ack = await self._request(messages.command(joints, **data), "ack", timeout)
        if (ack.get("data") or {}).get("status") == "refused":
            raise refusal(ack)
        return ack

    async def pose(
        self,
        position: Sequence[float],
        orientation: Sequence[float] | None = None,
        *,
        gripper: float | None = None,
        duration: float | None = None,
        timeout: float | None = None,
    ) -> dict[str, Any]:
        """Move the hand to a pose (`position` metres in the robot's base frame, `orientation`
        a quaternion x, y, z, w; `duration` ms): the server solves the joints and sends them as
        this master's command. Its acknowledgment; `Refused` (UNREACHABLE, a rule) if not."""
        message = messages.pose(position, orientation, gripper, duration)
        ack = await self._request(message, "ack", timeout)
        if (ack.get("data") or {}).get("status") == "refused":
            raise refusal(ack)
        return ack

    async def move(
        self, goal: Mapping[str, Any], *, plan: bool = True, timeout: float | None = None
    ) -> dict[str, Any]:
        """A move to `goal` (`{"joints": {name: degrees}}` or `{"pose": {"position": [...],
        "orientation"?: [...]}}`), along a planned path with `plan`: the `move` message, where
        the server has it (else `Refused` with its UNKNOWN_MESSAGE_TYPE). Its acknowledgment;
        a planned path is then played as this master's commands."""
        data = {**goal, "plan": plan}
        message = {"type": "move", "timestamp": now_iso(), "data": data}
        ack = await self._request(message, "ack", timeout)
        if (ack.get("data") or {}).get("status") == "refused":
            raise refusal(ack)
        return ack

    async def play(self, sequence: Mapping[str, Any], timeout: float | None = None) -> None:
        """Play a sequence (`{"commands": [{"timestamp", "joints"}], ...}`) as this master;
        returns once the server accepted it."""
        # The caller's document as it is: the server checks it and refuses it with a code
        # (`Refused`), which is the contract for a sequence.
        message = {"type": "sequence", "timestamp": now_iso(), "data": dict(sequence)}
        ack = await self._request(message, "ack", timeout)
        if (ack.get("data") or {}).get("status") == "refused":
            raise refusal(ack)

    async def declare_policy(
        self, fps: float, stall_periods: int = 2, timeout: float | None = None
    ) -> None:
        """Say that this master runs a policy at `fps`: the server records its inferences
        (`send_inference`) and runs its watchdog over `stall_periods` periods."""
        ack = await self._request(messages.policy(fps, stall_periods), "ack", timeout)
        if (ack.get("data") or {}).get("status") == "refused":
            raise refusal(ack)

    async def release(self, timeout: float | None = None, *, hold: bool = False) -> dict[str, Any]:
        """Hand the robot back: it goes `idle` (it stays `estopped` if it was), no e-stop; the
        commands it accepted complete, unless `hold`: then the arm stops where it is. Returns
        the `released` data; the server then closes the socket, and the session does not
        reconnect."""
        answer = await self._request(messages.release(hold), "released", timeout)
        data: dict[str, Any] = answer.get("data") or {}
        return data

    async def estop(self, reason: str = "") -> None:
        """E-stop the robot."""
        await self.send(messages.estop(reason))

    async def reset(self) -> None:
        """Clear the robot's e-stop."""
        await self.send(messages.reset())

    async def _request(
        self, message: Mapping[str, Any] | msgspec.Struct, expects: str, timeout: float | None
    ) -> dict[str, Any]:
        limit = self.timeout if timeout is None else timeout
        pending = _Pending(expects)
        self._pending.append(pending)
        while len(self._pending) > self.MAX_PENDING:
            self._pending.popleft().settle(error=ClientTimeout("too many requests unanswered"))
        try:
            await self.send(message)
        except BaseException:
            if pending in self._pending:
                self._pending.remove(pending)  # never sent: nothing answers it
            raise
        # A request that times out stays in line: its late answer is still its own.
        with trio.move_on_after(limit) as waited:
            await pending.done.wait()
        if waited.cancelled_caught:
            raise ClientTimeout(f"no {expects} from the server within {limit} s")
        if pending.error is not None:
            raise pending.error
        return pending.answer

    def _answered(self, message: dict[str, Any], kind: str) -> None:
        """`message` answers the oldest request that expects a `kind`."""
        for pending in self._pending:
            if pending.expects == kind:
                self._pending.remove(pending)
                pending.settle(message)
                return

    def _fail_all(self, error: ArenaClientError) -> None:
        while self._pending:
            self._pending.popleft().settle(error=error)

    async def wait_connected(self) -> None:
        """Until the server has accepted this master (its first `state`); with
        `stop_on_refusal`, raises `Refused` if it would not have it (another master holds the
        robot, no such robot, ...)."""
        await self._settled.wait()
        if self.refusal is not None:
            raise self.refusal

    async def wait_resumed(self) -> None:
        """Return once the server does not have this master paused."""
        await self._resumed.wait()

    async def on_message(self, message: dict[str, Any]) -> None:
        kind = message.get("type")
        if kind == "ack":
            self._answered(message, "ack")
            return
        if kind == "error" and not self._settled.is_set() and self.stop_on_refusal:
            self.refusal = refusal(message)  # refused before it was accepted
            self.finished = True  # asking again would get the same answer
            self._settled.set()
        elif kind == "state":
            self._settled.set()
        elif kind == "pause" and not self.paused:
            self.paused, self._resumed = True, trio.Event()
            self.pauses += 1
        elif kind == "resume":
            self.paused = False
            self._resumed.set()
        elif kind == "stopped":
            self.stops.append(message.get("data") or {})
            self.stop_count += 1
        if kind == "released":
            self.released = message.get("data") or {}
            self.finished = True  # the server closes now: no reconnection
            self._answered(message, "released")
        elif kind == "error":
            self.errors.append(message)
            if self._pending:  # the server answers in order: the oldest request's answer
                self._pending.popleft().settle(error=refusal(message))
        elif kind == "detached":
            self.errors.append(message)
            self.detached = message.get("data") or {}
            self._fail_all(refusal(message))
        elif kind == "missed":  # answers dropped while this client did not read: the oldest
            data = message.get("data") or {}
            for _ in range(int(data.get("ack") or 0) + int(data.get("error") or 0)):
                if not self._pending:
                    break
                self._pending.popleft().settle(
                    error=ArenaClientError("MISSED", "the answer was dropped: read faster")
                )
        await super().on_message(message)

    async def on_connect(self) -> None:
        self.detached = None  # master again, on a new connection

    async def on_disconnect(self, reason: str) -> None:
        self._fail_all(Disconnected(f"the link dropped before the answer came ({reason})"))
