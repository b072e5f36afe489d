"""The WebSocket endpoints: masters, slaves and read-only state viewers.

They run on Arena's own WebSocket transport (`listener`, `ws_transport`), not Quart's. Each
connection runs its tasks in one nursery and ends in one of three ways: the client goes away
(for a master or slave that is a loss, and the robot's loss policy applies), the robot ends the
link (detached, deleted), or the server shuts down (closed with 1001 at once).
"""

from __future__ import annotations

import collections
import contextlib
import itertools
import logging
import math
import time
from collections.abc import Awaitable, Callable
from functools import partial
from typing import Any, NamedTuple, TypeVar

import msgspec
import trio

from arena.drivers.sequence_master import SequenceMaster
from arena.protocol import messages as wire
from arena.protocol.errors import ArenaError, ErrorCode
from arena.protocol.ws_frames import UpgradeRequest, WebSocketClosed
from arena.robot.actor import Robot
from arena.robot.events import (
    JointStatesReceived,
    MasterNotice,
    NoticeKind,
    RobotEvent,
    SlaveNotice,
    SlaveTarget,
    StateChanged,
    TargetsSent,
)
from arena.robot.links import DETACHED_LINK, MasterLink, SlaveLink
from arena.robot.mailbox import EventQueue
from arena.robot.manager import estop_together
from arena.robot.motion import CommandResult
from arena.server import convert
from arena.server.auth import check_token
from arena.server.base import ArenaApp
from arena.server.listener import WebSocketHandler
from arena.server.ws_transport import WebSocket

T = TypeVar("T")
log = logging.getLogger(__name__)
_ids = itertools.count(1)

#: Close codes: 1000 normal, 1001 going away, 4000 + an HTTP-like status for refusals.
CLOSE_NORMAL, CLOSE_GOING_AWAY = 1000, 1001
_CLOSE_FOR = {
    ErrorCode.UNAUTHORIZED: 4401,
    ErrorCode.FORBIDDEN: 4403,
    ErrorCode.UNKNOWN_ROBOT: 4404,
    ErrorCode.MASTER_ACTIVE: 4409,
    ErrorCode.ESTOPPED: 4423,
    ErrorCode.TAKEN_OVER: 4409,
    ErrorCode.MASTER_LOST: 4408,
    ErrorCode.NODE_LOST: 4503,
}


def router(app: ArenaApp) -> Callable[[UpgradeRequest], WebSocketHandler | None]:
    """The WebSocket endpoints by path (None for any other path)."""

    def route(request: UpgradeRequest) -> WebSocketHandler | None:
        """The handler for the path; raises `ArenaError` for a foreign page or host name."""
        parts = request.path.split("/")
        if len(parts) == 4 and parts[1] == "ws" and parts[2] in _PEER_ENDPOINTS and parts[3]:
            role = parts[2]
        elif len(parts) == 5 and parts[1:3] == ["ws", "robots"] and parts[4] == "state":
            role = "viewer"
        else:
            return None
        handler, robot_id = _ENDPOINTS[role], parts[3]
        host = request.headers.get("host")
        app.origin_policy.check_host(host)
        app.origin_policy.check_origin(request.headers.get("origin"), host, request.scheme)
        try:
            node = _remote_node(app, robot_id)
        except ArenaError as error:  # its node is gone (NODE_LOST): the client is told so
            return partial(_refused, app, role, error)
        if node is not None:  # another node of the fleet owns it: carried there
            from arena.server.fleet_api import proxy

            return lambda ws: proxy(Connection(app, ws, role), robot_id, node)
        return lambda ws: handler(Connection(app, ws, role), robot_id)

    return route


async def _refused(app: ArenaApp, role: str, error: ArenaError, ws: WebSocket) -> None:
    """A connection refused before it reaches a robot (its key checked first): the error,
    then the close."""
    connection = Connection(app, ws, role)
    if await authorized(connection):
        await connection.refuse(error)


def _remote_node(app: ArenaApp, robot_id: str) -> str | None:
    """The other node of the fleet that owns `robot_id`, if it is not here (`owner_of`:
    NODE_LOST if its node is gone)."""
    fleet = app.fleet
    if fleet is None or robot_id in {robot.robot_id for robot in app.manager.robots()}:
        return None
    node = fleet.owner_of(robot_id)
    return None if node == fleet.name else node


class Encoded(NamedTuple):
    """A message encoded already, with its kind: `ack`, `error`, `heartbeat`, `state` or
    `joint_states`, the last two optionally `:<robot id>` (a group master hears from several)."""

    kind: str
    text: str


Outgoing = msgspec.Struct | Encoded

_accepted_ack = ("", Encoded("ack", ""))  # (timestamp, the plain acceptance encoded)


def _ack(result: CommandResult) -> Outgoing:
    """The ack of a command; a plain acceptance is encoded once per millisecond (the
    timestamp's resolution), since a burst of commands gets many in one."""
    global _accepted_ack
    if not result.accepted or result.clamped:
        return convert.ack(result)
    stamp = wire.now_iso()
    if stamp != _accepted_ack[0]:
        message = wire.AckMessage(timestamp=stamp, data=wire.AckData("accepted"))
        _accepted_ack = (stamp, Encoded("ack", wire.encode(message)))
    return _accepted_ack[1]


#: Kinds of which a peer that is behind gets only the newest, once it reads again.
_LATEST_KINDS = frozenset({"state", "joint_states"})
#: Kinds that a peer that is behind misses (counted in the `missed` message).
_DROPPED_KINDS = frozenset({"ack", "error", "heartbeat"})
_KIND_OF: dict[type, str] = {
    wire.StateMessage: "state",
    wire.JointStatesOut: "joint_states",
    wire.AckMessage: "ack",
    wire.ErrorMessage: "error",
    wire.HeartbeatMessage: "heartbeat",
}


def _switch(args: dict[str, str], name: str) -> bool:
    """A query parameter that is on unless it says off."""
    return args.get(name, "").lower() not in ("0", "false", "no", "off")


class Connection:
    """One accepted WebSocket: send helpers, refusals, and the shutdown race.

    `send` never waits, so a reader answering its peer never stalls on that peer. Once the
    peer has let the transport's `high_water` bytes pile up, states and joint states keep
    only the newest of each, and acks, errors and heartbeats are dropped and counted; when
    the peer has read what was queued, it gets one `missed` message with the counts, then the
    newest states. Messages that must not be dropped (a slave's targets) go through
    `send_in_turn`, which waits for room in the writer task that sends them.
    """

    def __init__(self, app: ArenaApp, ws: WebSocket, role: str) -> None:
        self.app = app
        self.ws = ws
        self.role = role  # master, slave or viewer
        self.args = ws.request.args
        #: Query parameters `acks=false`, `joint_states=false`: a fire-and-forget master
        #: hears only refusals; a viewer may watch state changes alone.
        self.wants_acks = _switch(self.args, "acks")
        self.wants_joint_states = _switch(self.args, "joint_states")
        self.closed = False
        self._ended = trio.Event()
        self._held: dict[str, str] = {}  # the newest text of each latest-only kind
        self._missed: collections.Counter[str] = collections.Counter()
        self._behind = trio.Event()  # set while something is held or missed

    async def send(self, *messages: Outgoing, whole: bool = False) -> None:
        """Send messages in one write (a struct is encoded as JSON); never waits. `whole`:
        they answer every frame the reader took together (see `WebSocket.offer`)."""
        if self._held or self._missed:
            self._catch_up()
        texts = [m.text if isinstance(m, Encoded) else wire.encode(m) for m in messages]
        if not (self._held or self._missed) and self.ws.offer(*texts, whole=whole):
            self._note_closed()
            return
        for message, text in zip(messages, texts, strict=True):
            kind = message.kind if isinstance(message, Encoded) else _KIND_OF.get(type(message))
            self._keep(kind, text)

    async def send_in_turn(self, message: msgspec.Struct) -> None:
        """Send a message that must not be dropped, first waiting while the peer is behind."""
        await self.ws.send(wire.encode(message))
        self._note_closed()

    def _keep(self, kind: str | None, text: str) -> None:
        """A message for a peer that is behind: keep the newest of its kind, or count it."""
        base = kind.partition(":")[0] if kind else ""
        if base in _LATEST_KINDS:
            assert kind is not None
            missed = self._held.pop(kind, None) is not None  # superseded by this one
            self._held[kind] = text
        elif base in _DROPPED_KINDS:
            missed = True
        else:  # rare and small (a detach notice): queued whatever the backlog
            self.ws.send_nowait(text)
            return
        if missed:
            self._missed[base] += 1
            self.app.metrics.dropped[base] += 1
        self._behind.set()

    def _catch_up(self) -> None:
        """If the peer has room again: the `missed` counts, then the newest states."""
        if self.ws.backlogged or not (self._held or self._missed):
            return
        texts = []
        if self._missed:
            missed = wire.MissedData(**{k: self._missed[k] for k in self._missed})
            texts.append(wire.encode(wire.MissedMessage(timestamp=wire.now_iso(), data=missed)))
        texts.extend(self._held.values())
        self._held.clear()
        self._missed.clear()
        self._behind = trio.Event()
        self.ws.offer(*texts)
        self._note_closed()

    async def _catch_up_when_read(self) -> None:
        while not self.ws.close_sent:
            await self._behind.wait()
            await self.ws.wait_drained()
            self._catch_up()

    def _note_closed(self) -> None:
        if self.ws.close_sent:  # the transport closed (protocol error, or the peer is gone)
            self._ended.set()

    @property
    def queued_bytes(self) -> int:
        """Bytes waiting for the peer to read."""
        return self.ws.queued_bytes

    def send_now(self, message: msgspec.Struct) -> bool:
        """Write a message at once if the socket is idle; False (nothing sent) if it is not."""
        if not self.ws.send_now(wire.encode(message)):
            return False
        self._note_closed()
        return True

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
        await self.close(_CLOSE_FOR.get(error.code, 4400), error.message)

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
            nursery.start_soon(self._catch_up_when_read)
            nursery.start_soon(main)


async def authorized(connection: Connection) -> bool:
    """Check the key; a refusal is sent and the answer is False. A connection carried from
    another node of the fleet was checked there (`trusted`)."""
    if getattr(connection.ws, "trusted", False):
        return True
    try:
        check_token(
            connection.app,
            connection.ws.request.headers.get("authorization"),
            connection.args.get("token"),
            mutating=connection.role != "viewer",
        )
    except ArenaError as error:
        await connection.refuse(error)
        return False
    return True


async def _accept(connection: Connection, robot_id: str) -> Robot | None:
    """Check the key and find the robot; a refusal is sent and the answer is None."""
    if not await authorized(connection):
        return None
    try:
        return connection.app.manager.get(robot_id)
    except ArenaError as error:
        await connection.refuse(error)
        return None


_BINARY_REFUSAL = "Send JSON text frames, not binary frames."


def _flag(value: str | None) -> bool:
    return value is not None and value.lower() in ("1", "true", "yes", "on")


async def _receive_text(connection: Connection) -> str | None:
    """The next text frame; binary frames are answered with an error and skipped."""
    while True:
        try:
            frame = await connection.ws.receive()
        except WebSocketClosed:
            return None
        connection.app.metrics.messages[connection.role] += 1
        if isinstance(frame, str):
            return frame
        await connection.send_error(ErrorCode.BINARY_NOT_SUPPORTED, _BINARY_REFUSAL)


async def _heartbeats(connection: Connection) -> None:
    interval = connection.app.arena_config.heartbeat_interval
    while True:
        await trio.sleep(interval)
        await connection.send(wire.HeartbeatMessage(timestamp=wire.now_iso()))


#: The events a `_RobotEventForwarder` makes messages of (its queue takes no others).
_FORWARDED = (StateChanged, JointStatesReceived, TargetsSent)


class _RobotEventForwarder:
    """State changes at once; joint states once per `joint_states_interval` on average.

    Joint states are paced by a token bucket of two intervals: at most one per interval on
    average and two at once, so that a client commanding at that rate gets one with every
    acknowledgment despite jitter (a late command followed by one on time) without a separate
    write. `name_robot` adds the robot's id to them (a group master hears from several).

    Besides its own task (`run`), the connection's reader can take what is ready right after
    answering a command (`handling_command`, `take_due`), so that the acknowledgment and the
    joint states it caused leave in one write, and the task is not woken for them.

    The task sends pending joint states one interval after the bucket would allow them, so a
    command that comes before then carries them. Sending them as soon as allowed locks a
    client that commands at the interval's own rate, after any stall that made two of its
    commands arrive together, into a phase where every joint state leaves in a write of its
    own a few milliseconds before the command that could have carried it. The bucket never
    refills at that rate, so the phase lasts as long as the client.
    """

    def __init__(
        self,
        connection: Connection,
        robot: Robot,
        events: EventQueue[RobotEvent],
        name_robot: bool = False,
        on_robot_gone: Callable[[str], Awaitable[None]] | None = None,
    ) -> None:
        self.connection = connection
        self.robot = robot
        self.events = events
        self.name_robot = name_robot
        self.on_robot_gone = on_robot_gone
        self.interval = connection.app.arena_config.joint_states_interval
        self.pending = False  # joint values changed since the last joint_states sent
        self.next_send = -math.inf
        self.joint_states = convert.JointStatesView(robot)
        self._waiting: trio.CancelScope | None = None  # the task's wait, while it waits

    async def run(self) -> None:
        """Forward until the robot is gone."""
        while True:
            batch: list[RobotEvent] = []
            with trio.CancelScope(deadline=self._deadline()) as self._waiting:
                try:
                    batch = [await self.events.get(), *self.events.drain()]
                except trio.EndOfChannel:  # the robot is gone
                    if self.on_robot_gone is not None:
                        await self.on_robot_gone(self.robot.robot_id)
                    else:
                        await self.connection.close(CLOSE_NORMAL, "robot deleted")
                    return
            self._waiting = None
            for message in self._messages(batch):
                await self.connection.send(message)

    def handling_command(self) -> contextlib.AbstractContextManager[None]:
        """Around a command whose events the reader will `take_due` itself."""
        return self.events.holding_wakes()

    def take_due(self) -> list[Outgoing]:
        """What is ready to go now, taken from the queue (the task then finds it empty)."""
        if not (self.events or self.pending):  # most commands of a burst: nothing new to say
            return []
        messages = self._messages(self.events.drain())
        if self._waiting is not None:  # joint states held back: the task sends them when due
            deadline = self._deadline()
            if deadline != self._waiting.deadline:  # (setting it costs even when unchanged)
                self._waiting.deadline = deadline
        return messages

    def _deadline(self) -> float:
        return self.next_send + self.interval if self.pending else math.inf

    def _messages(self, batch: list[RobotEvent]) -> list[Outgoing]:
        out: list[Outgoing] = []
        changed = moved = False
        for event in batch:  # (a loop: two `any` generators cost more, per command)
            kind = type(event)
            changed = changed or kind is StateChanged
            moved = moved or kind is TargetsSent or kind is JointStatesReceived
        if changed:
            state = convert.state(self.robot.snapshot())
            if self.name_robot:  # the newest of each member's is kept for a peer behind
                out.append(Encoded(f"state:{self.robot.robot_id}", wire.encode(state)))
            else:
                out.append(state)
        self.pending = self.pending or (moved and self.connection.wants_joint_states)
        now = trio.current_time()
        if self.pending and now >= self.next_send:
            states = self.joint_states.message()
            if self.name_robot:
                named = msgspec.to_builtins(states) | {"robot_id": self.robot.robot_id}
                text = msgspec.json.encode(named).decode()
                out.append(Encoded(f"joint_states:{self.robot.robot_id}", text))
            else:
                out.append(states)
            self.pending = False
            # The time the bucket holds a token again (it holds at most two).
            self.next_send = max(self.next_send + self.interval, now)
        return out


async def _forward_robot_events(
    connection: Connection, robot: Robot, events: EventQueue[RobotEvent]
) -> None:
    await _RobotEventForwarder(connection, robot, events).run()


# --- masters ----------------------------------------------------------------------------------


async def master_socket(connection: Connection, robot_id: str) -> None:
    """A master: commands in, acknowledgments, joint states and state changes out."""
    if robot_id in connection.app.groups:
        await _group_master_socket(connection, robot_id)
        return
    robot = await _accept(connection, robot_id)
    if robot is None:
        return
    app = connection.app
    try:
        link = await robot.connect_master(
            connection.args.get("id") or f"ws-master-{next(_ids)}",
            kind="websocket",
            takeover=_flag(connection.args.get("takeover")),
            heartbeat_timeout=app.arena_config.heartbeat_timeout,
            description="WebSocket client",
        )
    except ArenaError as error:
        await connection.refuse(error)
        return
    app.metrics.connections["master"] += 1
    try:
        await connection.send(convert.state(robot.snapshot()))
        with robot.subscribe(maxlen=256, kinds=_FORWARDED) as events:
            player = _SequencePlayer()
            forwarder = _RobotEventForwarder(connection, robot, events)
            if connection.wants_joint_states:
                await connection.send(forwarder.joint_states.message())

            async def body(nursery: trio.Nursery) -> None:
                nursery.start_soon(forwarder.run)
                nursery.start_soon(_forward_master_notices, connection, link, player)
                nursery.start_soon(_heartbeats, connection)
                await _master_reader(connection, robot, link, forwarder, player, nursery)

            await connection.run(body)
    finally:
        try:
            await _release_master(app, link)
        finally:  # counted closed once the robot has heard (tests wait on it)
            app.metrics.connections["master"] -= 1


class _GroupMembers:
    """A group master's links to the members still there. A member that is deleted leaves
    the group master's hands (it is told in a `member_left` message); the rest stay claimed,
    and its e-stop still stops every one of them. When none is left, the socket closes."""

    def __init__(self, connection: Connection, links: dict[str, MasterLink], group_id: str) -> None:
        self.connection = connection
        self.links = links
        self.group_id = group_id

    async def leave(self, robot_id: str, reason: str = "robot deleted") -> None:
        """`robot_id` is gone: forget it and say so (once)."""
        if self.links.pop(robot_id, None) is None:
            return
        await self.connection.send(
            wire.MemberLeftMessage(
                timestamp=wire.now_iso(), data=wire.MemberLeftData(robot_id, reason)
            )
        )
        if not self.links:
            await self.connection.close(CLOSE_NORMAL, "every member of the group is gone")


async def _group_master_socket(connection: Connection, group_id: str) -> None:
    """A master of a group: it claims every member; each command goes to each member, and
    the ack tells how each answered. Members keep their own safety state."""
    if not await authorized(connection):
        return
    app = connection.app
    links: dict[str, MasterLink] = {}
    try:
        group = app.groups.get(group_id)
        robots = [app.manager.get(robot_id) for robot_id in group.members]
        master_id = connection.args.get("id") or f"ws-group-master-{next(_ids)}"
        for robot in robots:
            links[robot.robot_id] = await robot.connect_master(
                master_id,
                kind="websocket-group",
                takeover=_flag(connection.args.get("takeover")),
                heartbeat_timeout=app.arena_config.heartbeat_timeout,
                description=f"master of the group {group_id!r}",
            )
    except ArenaError as error:
        with trio.CancelScope(shield=True):
            for link in links.values():
                await link.detach("the group could not be claimed whole")
        await connection.refuse(error)
        return
    app.metrics.connections["master"] += 1
    members = _GroupMembers(connection, dict(links), group_id)
    try:
        with contextlib.ExitStack() as stack:
            queues = [
                stack.enter_context(robot.subscribe(maxlen=256, kinds=_FORWARDED))
                for robot in robots
            ]
            for robot in robots:
                await connection.send(convert.state(robot.snapshot()))

            async def body(nursery: trio.Nursery) -> None:
                for robot, queue in zip(robots, queues, strict=True):
                    forwarder = _RobotEventForwarder(
                        connection, robot, queue, name_robot=True, on_robot_gone=members.leave
                    )
                    nursery.start_soon(forwarder.run)
                nursery.start_soon(_heartbeats, connection)
                await _read_loop(
                    connection, wire.decode_master, partial(_handle_group_message, members)
                )

            await connection.run(body)
    finally:
        app.metrics.connections["master"] -= 1
        for link in links.values():
            await _release_master(app, link)


async def _handle_group_message(members: _GroupMembers, message: wire.MasterMessage) -> None:
    connection = members.connection
    for link in members.links.values():
        link.alive()
    if isinstance(message, wire.CommandMessage):
        data = message.data
        command = convert.command_from_wire(data.joints, data.duration, data.metadata)
        answers: dict[str, Any] = {}
        gone: list[str] = []

        async def one(robot_id: str, link: MasterLink) -> None:
            try:
                result = await link.command(command)
            except ArenaError as error:
                if error.code is not ErrorCode.ROBOT_STOPPED:
                    raise
                gone.append(robot_id)  # deleted just now: it leaves the group's answer
                return
            answers[robot_id] = msgspec.to_builtins(convert.ack(result).data)

        async with trio.open_nursery() as nursery:
            for robot_id, link in list(members.links.items()):
                nursery.start_soon(one, robot_id, link)
        for robot_id in gone:
            await members.leave(robot_id)
        if not answers:
            return
        statuses = {answer["status"] for answer in answers.values()}
        if "refused" in statuses:
            status = "refused" if statuses == {"refused"} else "partial"
        else:
            status = "clamped" if "clamped" in statuses else "accepted"
        ack = {
            "type": "ack",
            "timestamp": wire.now_iso(),
            "data": {"status": status, "members": answers},
        }
        if connection.wants_acks or status != "accepted":
            await connection.send(Encoded("ack", msgspec.json.encode(ack).decode()))
    elif isinstance(message, wire.EStopMessage):
        reason = (message.data.reason if message.data else None) or "e-stop from group master"
        await estop_together([link.robot for link in members.links.values()], reason)
    elif isinstance(message, wire.ResetMessage):
        for link in list(members.links.values()):
            if str(link.robot.snapshot().mode) == "estopped":
                with contextlib.suppress(ArenaError):  # deleted meanwhile: its forwarder tells
                    await link.robot.reset()
    elif isinstance(message, wire.HeartbeatMessage):
        await connection.send(wire.HeartbeatMessage(timestamp=wire.now_iso()))
    elif isinstance(message, wire.ReleaseMessage):
        modes: dict[str, str] = {}
        for robot_id, link in list(members.links.items()):
            with contextlib.suppress(ArenaError):  # deleted meanwhile: nothing to release
                await link.release()
                modes[robot_id] = str(link.robot.snapshot().mode)
        mode = "estopped" if "estopped" in modes.values() else "idle"
        await _send_released(connection, wire.ReleasedData(members.group_id, mode, modes))
    else:
        await connection.send_error(
            ErrorCode.INVALID_MESSAGE,
            "A group master sends commands, e-stops, resets, heartbeats, release.",
        )


async def _release_master(app: ArenaApp, link: MasterLink) -> None:
    """The socket of a master is gone: a shutdown detaches it, anything else loses it (the
    robot's loss policy applies) unless the robot let it go first."""
    with trio.CancelScope(shield=True):
        if app.shutting_down.is_set():
            await link.detach("server shutting down")
        elif not link.detached.is_set():
            await link.lost("connection closed")


class _SequencePlayer:
    """The sequence a WebSocket master asked for, played under that master's ownership;
    `releasing`: the master said `release` (its link ends without a word from the robot)."""

    def __init__(self) -> None:
        self.scope: trio.CancelScope | None = None
        self.releasing = False

    def stop(self) -> None:
        if self.scope is not None:
            self.scope.cancel()
            self.scope = None

    async def play(self, link: MasterLink, master: SequenceMaster) -> None:
        with trio.CancelScope() as scope:
            self.scope = scope
            await master.run(link)


async def _forward_master_notices(
    connection: Connection, link: MasterLink, player: _SequencePlayer
) -> None:
    async for notice in link.notices:
        if notice.kind == "detached":
            await _send_detached(connection, notice)
            return
    if player.releasing:
        return  # the reader answers the release and closes
    # The robot closed the link (deleted, or detached without a word).
    await connection.close(CLOSE_NORMAL, "robot link closed")


async def _send_detached(connection: Connection, notice: MasterNotice) -> None:
    code = notice.code or ErrorCode.MASTER_LOST
    by = notice.by
    taken_by = None if by is None else wire.TakenBy(by.master_id, by.kind, by.description)
    await connection.send(  # queued even to a peer that is behind: it is the last word
        wire.DetachedMessage(
            timestamp=wire.now_iso(), data=wire.DetachedData(str(code), notice.message, taken_by)
        )
    )
    await connection.close(_CLOSE_FOR.get(code, CLOSE_NORMAL), notice.message)


async def _send_released(connection: Connection, data: wire.ReleasedData) -> None:
    """Answer a `release` (queued even to a peer that is behind) and close normally."""
    await connection.send(wire.ReleasedMessage(timestamp=wire.now_iso(), data=data))
    await connection.close(CLOSE_NORMAL, "released")


async def _read_loop(
    connection: Connection, decode: Callable[[str], T], handle: Callable[[T], Awaitable[None]]
) -> None:
    """Decode and handle frames until the client leaves; errors are answered, not fatal."""
    while True:
        raw = await _receive_text(connection)
        if raw is None:
            return
        started = time.perf_counter()
        try:
            await handle(decode(raw))
        except ArenaError as error:
            if not await _answer_error(connection, error):
                return
        connection.app.metrics.observe_latency(time.perf_counter() - started)


async def _answer_error(connection: Connection, error: ArenaError) -> bool:
    """Answer a message's error with an `error` message; False (and the socket closed) when
    it is that the robot is gone."""
    if error.code is ErrorCode.ROBOT_STOPPED:
        await connection.close(CLOSE_NORMAL, "robot deleted")
        return False
    await connection.send_error(error.code, error.message)
    return True


def _in_hand(connection: Connection, first: str) -> tuple[list[str | bytes], bool]:
    """`first` and the frames in hand after it (the rest of a burst, up to the transport's
    fairness bound); True when the peer's close came among them."""
    frames: list[str | bytes] = [first]
    closed = False
    if connection.ws.holds_more():  # (one at a time, nothing is)
        try:
            while (frame := connection.ws.next_in_hand()) is not None:
                frames.append(frame)
        except WebSocketClosed:
            closed = True
        connection.app.metrics.messages[connection.role] += len(frames) - 1
    return frames, closed


async def _master_reader(
    connection: Connection,
    robot: Robot,
    link: MasterLink,
    forwarder: _RobotEventForwarder,
    player: _SequencePlayer,
    nursery: trio.Nursery,
) -> None:
    """A master's messages until it leaves; errors are answered, not fatal.

    The frames of a burst that are in hand together are taken at once, and each run of
    commands among them is decided in one pass (`_decide_commands`). Every command is still
    decided, recorded and acknowledged on its own and in order; what a run shares is the
    forwarder's hold and one write of the answers.
    """
    handle = partial(_handle_master_message, connection, robot, link, player, nursery)
    while True:
        raw = await _receive_text(connection)
        if raw is None:
            return
        started = time.perf_counter()
        frames, closed = _in_hand(connection, raw)
        run: list[wire.CommandData] = []
        for frame in frames:
            message: wire.MasterMessage | ArenaError
            if isinstance(frame, bytes):
                message = ArenaError(ErrorCode.BINARY_NOT_SUPPORTED, _BINARY_REFUSAL)
            else:
                try:
                    message = wire.decode_master(frame)
                except ArenaError as error:
                    message = error
            if isinstance(message, wire.CommandMessage):
                run.append(message.data)
                continue
            if run and not await _decide_commands(connection, link, forwarder, run, True):
                return
            run = []
            if isinstance(message, ArenaError):
                await connection.send_error(message.code, message.message)
                continue
            try:
                await handle(message)
            except ArenaError as error:
                if not await _answer_error(connection, error):
                    return
        if run and not await _decide_commands(
            connection, link, forwarder, run, connection.ws.holds_more()
        ):
            return
        connection.app.metrics.observe_latency(time.perf_counter() - started, len(frames))
        if closed:
            return


async def _decide_commands(
    connection: Connection,
    link: MasterLink,
    forwarder: _RobotEventForwarder,
    run: list[wire.CommandData],
    burst_goes_on: bool,
) -> bool:
    """Decide commands in order and send their answers in one write; False (and the socket
    closed) if the robot is gone. `burst_goes_on`: more frames follow the last of them."""
    out: list[Outgoing] = []
    stopped = False
    commands = [convert.command_from_wire(d.joints, d.duration, d.metadata) for d in run]
    wants_acks = connection.wants_acks
    with forwarder.handling_command():
        # Each command counts as a heartbeat (the robot notes the time of each).
        index, last = 0, len(commands) - 1
        while index <= last:
            rest = commands[index:] if index else commands
            results = link.command_run_now(rest, burst_goes_on=burst_goes_on)
            if results is not None:
                out.extend(
                    [_ack(result) for result in results if wants_acks or not result.accepted]
                )
                break
            # The actor is busy (most often a motion tick is due): this command goes through
            # its inbox, after which the actor is idle again for the rest.
            try:
                in_burst = burst_goes_on or index < last
                result = await link.command(commands[index], in_burst=in_burst)
            except ArenaError as error:
                if error.code is ErrorCode.ROBOT_STOPPED:
                    stopped = True
                    break
                out.append(connection.error(error.code, error.message))
            else:
                if wants_acks or not result.accepted:
                    out.append(_ack(result))
            index += 1
        # The joint states the commands caused ride along: one write instead of two.
        out.extend(forwarder.take_due())
    if out:
        await connection.send(*out, whole=True)
    if stopped:
        await connection.close(CLOSE_NORMAL, "robot deleted")
    return not stopped


async def _handle_master_message(
    connection: Connection,
    robot: Robot,
    link: MasterLink,
    player: _SequencePlayer,
    nursery: trio.Nursery,
    message: wire.MasterMessage,
) -> None:
    """Any message of a master but a command (those go to `_decide_commands`)."""
    link.alive()
    if isinstance(message, wire.SequenceMessage):
        sequence = convert.sequence_from_wire(message.data)
        sequence.check_against(robot.model)
        player.stop()
        nursery.start_soon(player.play, link, SequenceMaster([sequence], loop=sequence.loop))
        await connection.send(
            wire.AckMessage(timestamp=wire.now_iso(), data=wire.AckData("accepted"))
        )
    elif isinstance(message, wire.EStopMessage):
        player.stop()
        reason = (message.data.reason if message.data else None) or "e-stop from master"
        await robot.estop(reason)
    elif isinstance(message, wire.ResetMessage):
        await robot.reset()
    elif isinstance(message, wire.HeartbeatMessage):
        await connection.send(wire.HeartbeatMessage(timestamp=wire.now_iso()))
    elif isinstance(message, wire.ReleaseMessage):
        if link.detached.is_set():  # taken over or stopped meanwhile: its notice says why
            raise ArenaError(ErrorCode.NOT_OWNER, DETACHED_LINK.message)
        player.stop()
        player.releasing = True
        await link.release()
        snapshot = robot.snapshot()
        await _send_released(connection, wire.ReleasedData(robot.robot_id, str(snapshot.mode)))


# --- slaves -----------------------------------------------------------------------------------


async def slave_socket(connection: Connection, robot_id: str) -> None:
    """A slave: `execute_command` and notices out; joint states, status and errors in."""
    robot = await _accept(connection, robot_id)
    if robot is None:
        return
    app = connection.app
    try:
        link = await robot.connect_slave(
            connection.args.get("id") or f"ws-slave-{next(_ids)}",
            kind="websocket",
            heartbeat_timeout=app.arena_config.heartbeat_timeout,
        )
    except ArenaError as error:
        await connection.refuse(error)
        return
    app.metrics.connections["slave"] += 1
    ended_by_robot = trio.Event()
    try:

        async def body(nursery: trio.Nursery) -> None:
            nursery.start_soon(_slave_writer, connection, link, ended_by_robot)
            nursery.start_soon(_heartbeats, connection)
            await _read_loop(
                connection, wire.decode_slave, partial(_handle_slave_message, connection, link)
            )

        await connection.run(body)
    finally:
        app.metrics.connections["slave"] -= 1
        if not ended_by_robot.is_set():
            with trio.CancelScope(shield=True):
                if app.shutting_down.is_set():
                    await link.detach("server shutting down")
                else:
                    await link.lost("connection closed")


async def _slave_writer(connection: Connection, link: SlaveLink, ended: trio.Event) -> None:
    def deliver_now(message: SlaveTarget | SlaveNotice) -> bool:
        # The robot writes to an idle socket itself; the end (shutdown) stays with this task,
        # and so do targets in the middle of a master's burst (the newest replaces them).
        if isinstance(message, SlaveNotice):
            if message.kind is NoticeKind.SHUTDOWN:
                return False
        elif message.more_follow:
            return False
        return connection.send_now(convert.to_slave(message))

    link.mailbox.deliver_now = deliver_now
    try:
        async for message in link.messages():
            await connection.send_in_turn(convert.to_slave(message))
    finally:
        link.mailbox.deliver_now = None
    ended.set()
    await connection.close(CLOSE_NORMAL, "detached from the robot")


async def _handle_slave_message(
    connection: Connection, link: SlaveLink, message: wire.SlaveMessage
) -> None:
    if isinstance(message, wire.JointStatesMessage):
        values: dict[str, float] = {}
        for entry in message.data:
            value = entry.real_value if entry.real_value is not None else entry.value
            if value is not None:
                values[entry.name] = value
        unknown = [n for n in values if link.robot.model.joint(n) is None]
        if unknown:
            await connection.send_error(
                ErrorCode.UNKNOWN_JOINT, f"Unknown joints ignored: {', '.join(unknown)}."
            )
        await link.report_joint_states(values)
    elif isinstance(message, wire.ErrorMessage):
        data = message.data
        await link.report_fault(data.code, data.message, data.severity, data.joint)
    elif isinstance(message, wire.StatusUpdateMessage):
        link.alive()
        if not message.data.isConnected or message.data.error:
            await link.report_fault(ErrorCode.SLAVE_STATUS, message.data.error or "disconnected")
    else:
        link.alive()


# --- viewers ----------------------------------------------------------------------------------


async def state_socket(connection: Connection, robot_id: str) -> None:
    """Read-only: the robot's state and joint states as they change. Any number may watch."""
    robot = await _accept(connection, robot_id)
    if robot is None:
        return
    app = connection.app
    app.metrics.connections["viewer"] += 1
    try:
        with robot.subscribe(maxlen=256, kinds=_FORWARDED) as events:
            await connection.send(convert.state(robot.snapshot()))
            if connection.wants_joint_states:
                await connection.send(convert.joint_states(robot))

            async def body(nursery: trio.Nursery) -> None:
                nursery.start_soon(_heartbeats, connection)
                nursery.start_soon(_forward_robot_events, connection, robot, events)
                await _viewer_reader(connection)

            await connection.run(body)
    finally:
        app.metrics.connections["viewer"] -= 1


async def _viewer_reader(connection: Connection) -> Any:
    while True:
        raw = await _receive_text(connection)
        if raw is None:
            return
        try:
            message = msgspec.json.decode(raw)
        except msgspec.DecodeError:
            message = None
        if not (isinstance(message, dict) and message.get("type") == "heartbeat"):
            await connection.send_error(
                ErrorCode.FORBIDDEN, "This stream is read-only; it takes only heartbeats."
            )


_ENDPOINTS: dict[str, Callable[[Connection, str], Awaitable[None]]] = {
    "master": master_socket,
    "slave": slave_socket,
    "viewer": state_socket,
}
_PEER_ENDPOINTS = ("master", "slave")


async def serve_role(connection: Connection, robot_id: str) -> None:
    """Serve a connection of its role (master, slave or viewer) for a robot of this node."""
    await _ENDPOINTS[connection.role](connection, robot_id)
