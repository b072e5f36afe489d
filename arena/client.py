"""A Python client for Arena servers: REST helpers and WebSocket sessions that reconnect.

REST: `Arena` (blocking, for plain scripts) and `AsyncArena` (for trio code) offer the same
methods. WebSockets (trio): `MasterSession`, `SlaveSession` and `ViewerSession` hold one
endpoint open, reconnect with exponential backoff and jitter, and send heartbeats. A plain
script runs its session code with `trio.run(main)`; see the README's agent example.

    async def main() -> None:
        async with MasterSession.open("http://127.0.0.1:8080", "arm-1") as master:
            ack = await master.command({"Rotation": 30})

Every call ends: what the server refuses raises `Refused` (with its `code` and `message`), a
wait that runs out raises `ClientTimeout`, a dropped link `Disconnected`; all three are
`ArenaClientError`s. A master session that ends normally releases the robot (it holds where
it is, `idle`); one that ends with an exception leaves without a word, and the server applies
its loss policy (an e-stop by default).
"""

from __future__ import annotations

import json
import logging
import math
import random
from collections import deque
from collections.abc import AsyncIterator, Awaitable, Callable, Iterator, Mapping
from contextlib import asynccontextmanager
from dataclasses import dataclass
from typing import Any, Generic, Self, TypeVar
from urllib.parse import quote

import httpx
import trio
from trio_websocket import (
    ConnectionClosed,
    HandshakeError,
    WebSocketConnection,
    open_websocket_url,
)

log = logging.getLogger(__name__)

T = TypeVar("T")

#: Close codes after which retrying cannot help (bad key, no such robot): reported, and retried
#: only at the backoff's ceiling.
HOPELESS_CLOSES = frozenset({4401, 4403, 4404})


class ArenaClientError(Exception):
    """An Arena server answered with an error: `code` is its machine-readable code."""

    def __init__(self, code: str, message: str, status: int | None = None) -> None:
        super().__init__(f"{code}: {message}")
        self.code = code
        self.message = message
        self.status = status


class Refused(ArenaClientError):
    """The server refused a request: a command acknowledged as `refused`, or an `error` (or
    `detached`) message in answer. `code` and `message` are the server's."""


class Disconnected(ArenaClientError):
    """The session's WebSocket is down (it is reconnecting)."""

    def __init__(self, message: str = "not connected") -> None:
        super().__init__("DISCONNECTED", message)


class ClientTimeout(ArenaClientError, TimeoutError):
    """No answer came within the call's `timeout` (code `TIMEOUT`)."""

    def __init__(self, message: str) -> None:
        super().__init__("TIMEOUT", message)


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


def ws_url(base: str, path: str, **query: str) -> str:
    """`http(s)://host:port` or `ws(s)://...` plus `path` -> the WebSocket URL."""
    base = base.rstrip("/")
    if base.startswith("http"):
        base = "ws" + base[len("http") :]
    params = "&".join(f"{k}={quote(v)}" for k, v in query.items() if v)
    return f"{base}{path}" + (f"?{params}" if params else "")


def now_iso() -> str:
    """The wire's timestamp format."""
    from arena.protocol.messages import now_iso as wire_now

    return wire_now()


def finite_joints(joints: Mapping[str, Any]) -> dict[str, float]:
    """`joints` as {name: float}; `ValueError` naming the joint whose value is not a finite
    number (NaN, infinity, None, a string, a bool): such a command never leaves the client."""
    checked: dict[str, float] = {}
    for name, value in joints.items():
        if (
            isinstance(value, bool)
            or not isinstance(value, int | float)
            or not math.isfinite(value)
        ):
            raise ValueError(f"joint {name!r}: {value!r} is not a finite number of degrees")
        checked[name] = float(value)
    return checked


def command_message(joints: Mapping[str, float], **data: Any) -> dict[str, Any]:
    """A master `command` in the seed's format; values not finite raise `ValueError`."""
    checked = finite_joints(joints)
    entries = [{"name": name, "value": value} for name, value in checked.items()]
    return {"type": "command", "timestamp": now_iso(), "data": {"joints": entries, **data}}


def joint_states_message(joints: Mapping[str, float]) -> dict[str, Any]:
    """A slave's `joint_states` report: real values in degrees."""
    entries = [{"name": n, "value": v, "real_value": v} for n, v in joints.items()]
    return {"type": "joint_states", "timestamp": now_iso(), "data": entries}


# --- WebSocket sessions -----------------------------------------------------------------------


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

    async def send(self, message: Mapping[str, Any]) -> None:
        """Send a message now; `Disconnected` while the link is down, `ClientTimeout` if the
        server does not take it within `timeout`, `ValueError` for a NaN or an infinity."""
        ws = self._ws
        if ws is None:
            raise Disconnected(self.last_error or "not connected")
        text = json.dumps(message, allow_nan=False)  # NaN is not JSON: refused here
        try:
            with trio.fail_after(self.timeout):
                await ws.send_message(text)
        except ConnectionClosed as closed:
            raise Disconnected(f"closed while sending ({closed.reason})") from None
        except trio.TooSlowError:
            raise ClientTimeout(f"the server took nothing for {self.timeout} s") from None

    async def try_send(self, message: Mapping[str, Any]) -> bool:
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
                await self.send({"type": "heartbeat", "timestamp": now_iso()})
            except Disconnected:
                return


def _describe(closed: ConnectionClosed) -> str:
    reason = closed.reason
    if reason is None or reason.code in (None, 1005, 1006):
        return "connection lost"
    return f"closed by the server ({reason.code}: {reason.reason or reason.name})"


class _Watching(Session):
    """A session that keeps a robot's newest `state` and `joint_states`."""

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


def _refusal(message: Mapping[str, Any]) -> Refused:
    """The `Refused` of an error, a detach or a refused ack (a group's names each member's)."""
    data = message.get("data") or {}
    members = data.get("members")
    if not data.get("code") and isinstance(members, dict) and members:
        codes = {str(answer.get("code")) for answer in members.values()}
        text = "; ".join(f"{robot}: {answer.get('message')}" for robot, answer in members.items())
        return Refused(codes.pop() if len(codes) == 1 else "REFUSED", text)
    return Refused(str(data.get("code") or "REFUSED"), str(data.get("message") or ""))


class MasterSession(_Watching):
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
        async with _running(session):
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
        ack = await self._request(command_message(joints, **data), "ack", timeout)
        if (ack.get("data") or {}).get("status") == "refused":
            raise _refusal(ack)
        return ack

    async def play(self, sequence: Mapping[str, Any], timeout: float | None = None) -> None:
        """Play a sequence (`{"commands": [{"timestamp", "joints"}], ...}`) as this master;
        returns once the server accepted it."""
        message = {"type": "sequence", "timestamp": now_iso(), "data": dict(sequence)}
        ack = await self._request(message, "ack", timeout)
        if (ack.get("data") or {}).get("status") == "refused":
            raise _refusal(ack)

    async def release(self, timeout: float | None = None) -> dict[str, Any]:
        """Hand the robot back: it holds where it is and goes `idle` (it stays `estopped` if
        it was), no e-stop. Returns the `released` data; the server then closes the socket,
        and the session does not reconnect."""
        answer = await self._request(
            {"type": "release", "timestamp": now_iso()}, "released", timeout
        )
        data: dict[str, Any] = answer.get("data") or {}
        return data

    async def estop(self, reason: str = "") -> None:
        """E-stop the robot."""
        await self.send({"type": "estop", "timestamp": now_iso(), "data": {"reason": reason}})

    async def reset(self) -> None:
        """Clear the robot's e-stop."""
        await self.send({"type": "reset", "timestamp": now_iso()})

    async def _request(
        self, message: Mapping[str, Any], expects: str, timeout: float | None
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

    async def on_message(self, message: dict[str, Any]) -> None:
        kind = message.get("type")
        if kind == "ack":
            self._answered(message, "ack")
            return
        if kind == "error" and not self._settled.is_set() and self.stop_on_refusal:
            self.refusal = _refusal(message)  # refused before it was accepted
            self.finished = True  # asking again would get the same answer
            self._settled.set()
        elif kind == "state":
            self._settled.set()
        if kind == "released":
            self.released = message.get("data") or {}
            self.finished = True  # the server closes now: no reconnection
            self._answered(message, "released")
        elif kind == "error":
            self.errors.append(message)
            if self._pending:  # the server answers in order: the oldest request's answer
                self._pending.popleft().settle(error=_refusal(message))
        elif kind == "detached":
            self.errors.append(message)
            self.detached = message.get("data") or {}
            self._fail_all(_refusal(message))
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


class SlaveSession(Session):
    """A slave of one robot: `on_target` gets each `execute_command` as {joint: degrees}."""

    def __init__(
        self,
        url: str,
        on_target: Callable[[dict[str, float]], Awaitable[None]] | None = None,
        **options: Any,
    ) -> None:
        super().__init__(url, **options)
        self.on_target = on_target
        self.notices: deque[str] = deque(maxlen=64)
        self.targets = 0

    @classmethod
    @asynccontextmanager
    async def open(
        cls,
        base_url: str,
        robot_id: str,
        on_target: Callable[[dict[str, float]], Awaitable[None]] | None = None,
        *,
        slave_id: str | None = None,
        **options: Any,
    ) -> AsyncIterator[Self]:
        """Run a session to `/ws/slave/{robot_id}` for the `async with` block, connected."""
        url = ws_url(base_url, f"/ws/slave/{quote(robot_id)}", id=slave_id or "")
        session = cls(url, on_target, **options)
        async with _running(session):
            yield session

    async def report(self, joints: Mapping[str, float]) -> None:
        """Report real joint values in degrees."""
        await self.send(joint_states_message(joints))

    async def on_message(self, message: dict[str, Any]) -> None:
        kind = message.get("type")
        if kind == "execute_command":
            self.targets += 1
            joints = {j["name"]: float(j["value"]) for j in message["data"]["joints"]}
            if self.on_target is not None:
                await self.on_target(joints)
        elif isinstance(kind, str) and kind != "heartbeat":
            self.notices.append(kind)


class ViewerSession(_Watching):
    """A read-only watcher of one robot: its newest state and joint states."""

    @classmethod
    @asynccontextmanager
    async def open(cls, base_url: str, robot_id: str, **options: Any) -> AsyncIterator[Self]:
        """Run a session to `/ws/robots/{robot_id}/state` for the `async with` block."""
        session = cls(ws_url(base_url, f"/ws/robots/{quote(robot_id)}/state"), **options)
        async with _running(session):
            yield session


@asynccontextmanager
async def _running(session: Session, connect_timeout: float = 10.0) -> AsyncIterator[None]:
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


# --- REST -------------------------------------------------------------------------------------


class _Endpoints(Generic[T]):
    """Every REST call once; `_call` makes it blocking (`Arena`) or awaitable (`AsyncArena`)."""

    def _call(self, method: str, path: str, body: Any = None) -> T:
        raise NotImplementedError

    def status(self) -> T:
        """`GET /`: the server's status."""
        return self._call("GET", "/")

    def robots(self) -> T:
        """Every robot."""
        return self._call("GET", "/api/robots")

    def robot(self, robot_id: str) -> T:
        """One robot: state, peers, joints."""
        return self._call("GET", f"/api/robots/{quote(robot_id)}")

    def create_robot(self, robot_id: str | None = None, robot_type: str = "so-arm100") -> T:
        """Create a robot."""
        body = {"robot_type": robot_type, **({"id": robot_id} if robot_id else {})}
        return self._call("POST", "/api/robots", body)

    def delete_robot(self, robot_id: str) -> T:
        """Delete a robot (its peers are let go)."""
        return self._call("DELETE", f"/api/robots/{quote(robot_id)}")

    def attach_slave(self, robot_id: str, config: Mapping[str, Any]) -> T:
        """Attach a slave driver (`{"type": "mock-slave"}`, `usb-slave`, `websocket-slave`)."""
        return self._call("POST", f"/api/robots/{quote(robot_id)}/slaves", dict(config))

    def attach_master(self, robot_id: str, config: Mapping[str, Any]) -> T:
        """Attach a master driver (`mock-sequence`, `replay`, `usb-master`, `remote-server`)."""
        return self._call("POST", f"/api/robots/{quote(robot_id)}/master", dict(config))

    def detach_master(self, robot_id: str) -> T:
        """Detach the robot's master."""
        return self._call("DELETE", f"/api/robots/{quote(robot_id)}/master")

    def estop(self, robot_id: str | None = None, reason: str | None = None) -> T:
        """E-stop one robot, or every robot when `robot_id` is None."""
        path = f"/api/robots/{quote(robot_id)}/estop" if robot_id else "/api/estop"
        return self._call("POST", path, {"reason": reason} if reason else {})

    def reset(self, robot_id: str) -> T:
        """Clear a robot's e-stop."""
        return self._call("POST", f"/api/robots/{quote(robot_id)}/reset")

    def set_joints(self, robot_id: str, joints: Mapping[str, float]) -> T:
        """Manual control (no master): move joints to these degrees."""
        entries = [{"name": n, "value": v} for n, v in joints.items()]
        return self._call("PUT", f"/api/robots/{quote(robot_id)}/joints", {"joints": entries})

    def groups(self) -> T:
        """Every robot group."""
        return self._call("GET", "/api/groups")

    def create_group(self, group_id: str, members: list[str], *, stop_together: bool = False) -> T:
        """Create a group one master can drive."""
        body = {"id": group_id, "members": members, "stopTogether": stop_together}
        return self._call("POST", "/api/groups", body)

    def group(self, group_id: str) -> T:
        """One group with its members' states."""
        return self._call("GET", f"/api/groups/{quote(group_id)}")

    def estop_group(self, group_id: str, reason: str | None = None) -> T:
        """E-stop every member of a group."""
        body = {"reason": reason} if reason else {}
        return self._call("POST", f"/api/groups/{quote(group_id)}/estop", body)

    def reset_group(self, group_id: str) -> T:
        """Clear every member's e-stop."""
        return self._call("POST", f"/api/groups/{quote(group_id)}/reset")

    def delete_group(self, group_id: str) -> T:
        """Delete a group (its robots stay)."""
        return self._call("DELETE", f"/api/groups/{quote(group_id)}")

    def recordings(self) -> T:
        """Recordings and the recorder's status."""
        return self._call("GET", "/api/recordings")

    def fleet_nodes(self) -> T:
        """The nodes of this server's fleet (`--node`): name, alive, version, robots."""
        return self._call("GET", "/api/fleet/nodes")

    def fleet_robots(self) -> T:
        """Every robot of every node of the fleet, with its node and state; each one can be
        opened (REST or WebSocket) through this server whichever node owns it."""
        return self._call("GET", "/api/fleet/robots")

    def fleet_estop(self, reason: str | None = None) -> T:
        """E-stop every robot of every node; each node's acknowledgment and time. Raises
        `ArenaClientError` ESTOP_INCOMPLETE (503) naming any node that failed or did not answer."""
        return self._call("POST", "/api/fleet/estop", {"reason": reason} if reason else {})


def _unreachable(url: httpx.URL, error: Exception) -> ArenaClientError:
    return ArenaClientError("UNREACHABLE", f"cannot reach {url}: {error or type(error).__name__}")


def _answer(response: httpx.Response) -> Any:
    if response.status_code >= 400:
        try:
            error = response.json().get("error") or {}
            code, message = error.get("code", "HTTP_ERROR"), error.get("message", response.text)
        except ValueError:
            code, message = "HTTP_ERROR", response.text
        raise ArenaClientError(code, message, response.status_code)
    return response.json() if response.content else None


class Arena(_Endpoints[Any]):
    """Blocking REST client, for plain scripts. Errors raise `ArenaClientError`."""

    def __init__(self, base_url: str, api_key: str | None = None, timeout: float = 10.0) -> None:
        headers = {"Authorization": f"Bearer {api_key}"} if api_key else {}
        self.http = httpx.Client(base_url=base_url, headers=headers, timeout=timeout)

    def _call(self, method: str, path: str, body: Any = None) -> Any:
        try:
            response = self.http.request(method, path, json=body)
        except httpx.TransportError as error:
            raise _unreachable(self.http.base_url, error) from None
        return _answer(response)

    def close(self) -> None:
        """Close the HTTP connections."""
        self.http.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class AsyncArena(_Endpoints[Awaitable[Any]]):
    """The same REST client for trio code: every method is awaited."""

    def __init__(self, base_url: str, api_key: str | None = None, timeout: float = 10.0) -> None:
        headers = {"Authorization": f"Bearer {api_key}"} if api_key else {}
        self.http = httpx.AsyncClient(base_url=base_url, headers=headers, timeout=timeout)

    async def _request(self, method: str, path: str, body: Any) -> Any:
        try:
            response = await self.http.request(method, path, json=body)
        except httpx.TransportError as error:
            raise _unreachable(self.http.base_url, error) from None
        return _answer(response)

    def _call(self, method: str, path: str, body: Any = None) -> Awaitable[Any]:
        return self._request(method, path, body)

    async def aclose(self) -> None:
        """Close the HTTP connections."""
        await self.http.aclose()

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()
