"""The group master endpoint, `/ws/master/{group id}`: one master claims every member of a
group; each command goes to each member, and the ack tells how each answered. Members keep
their own safety state."""

from __future__ import annotations

import contextlib
from functools import partial

import trio

from arena.protocol import messages as wire
from arena.protocol.errors import ArenaError, ErrorCode
from arena.robot.groups import Group
from arena.robot.handle import Robot
from arena.robot.links import MasterLink
from arena.robot.manager import estop_together
from arena.robot.safety import Mode
from arena.server import convert
from arena.server.link_quality import LinkQuality
from arena.server.ws.connection import CLOSE_NORMAL, Connection, flag, peer_ids
from arena.server.ws.forwarder import FORWARDED, QUEUE_LENGTH, RobotEventForwarder
from arena.server.ws.master import release_master, send_released, stale_refusal


class GroupMembers:
    """A group master's links to the members still there. A member that is deleted leaves
    the group master's hands (it is told in a `member_left` message); the rest stay claimed,
    and its e-stop still stops every one of them. When none is left, the socket closes."""

    def __init__(
        self,
        connection: Connection,
        links: dict[str, MasterLink],
        group_id: str,
        robots: list[Robot],
        master_id: str,
    ) -> None:
        self.connection = connection
        self.links = links
        #: Its link's clock estimate, for stale commands (None: not checked).
        self.quality: LinkQuality | None = None
        self.group_id = group_id
        self.robots = {robot.robot_id: robot for robot in robots}
        self.master_id = master_id

    def audit(self, action: str, robot_ids: list[str]) -> None:
        """Record on each robot of `robot_ids` that the group master's user did `action`."""
        for robot_id in robot_ids:
            self.robots[robot_id].audit(
                self.connection.principal.audit_name(), action, self.master_id
            )

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


async def serve(connection: Connection, group: Group) -> None:
    """A master of `group` (which the caller sees) until it leaves or every member is gone."""
    if not await connection.authorized():
        return
    app = connection.app
    group_id = group.group_id
    links: dict[str, MasterLink] = {}
    try:
        robots = [app.manager.get(robot_id) for robot_id in group.members]
        master_id = connection.args.get("id") or f"ws-group-master-{next(peer_ids)}"
        for robot in robots:
            links[robot.robot_id] = await robot.connect_master(
                master_id,
                kind="websocket-group",
                takeover=flag(connection.args.get("takeover")),
                heartbeat_timeout=app.arena_config.heartbeat_timeout,
                description=f"master of the group {group_id!r}",
            )
    except ArenaError as error:
        with trio.CancelScope(shield=True):
            for link in links.values():
                await link.detach("the group could not be claimed whole")
        await connection.refuse(error)
        return
    for robot in robots:  # (claimed whole: a group refused in part is not recorded)
        robot.audit(connection.principal.audit_name(), "connect group master", master_id)
    connection.count_open(group.members)
    members = GroupMembers(connection, dict(links), group_id, robots, master_id)
    config = app.arena_config
    # (A group's socket is not pinged: its clock estimate rests on the stamps alone.)
    members.quality = LinkQuality(master_id, config.command_max_age, config.link_ping_interval)
    try:
        with contextlib.ExitStack() as stack:
            queues = [
                stack.enter_context(robot.subscribe(maxlen=QUEUE_LENGTH, kinds=FORWARDED))
                for robot in robots
            ]
            for robot in robots:
                await connection.send(convert.state(robot.snapshot()))

            async def body(nursery: trio.Nursery) -> None:
                for robot, queue in zip(robots, queues, strict=True):
                    forwarder = RobotEventForwarder(
                        connection, robot, queue, name_robot=True, on_robot_gone=members.leave
                    )
                    nursery.start_soon(forwarder.run)
                nursery.start_soon(connection.heartbeats)
                await connection.read_loop(wire.decode_master, partial(_handle, members))

            await connection.run(body)
    finally:
        connection.count_closed()
        for link in links.values():
            await release_master(app, link)


async def _command(members: GroupMembers, data: wire.CommandData) -> None:
    """Each member decides the command at once; the ack says how each answered."""
    command = convert.command_from_wire(data.joints, data.duration, data.metadata)
    answers: dict[str, wire.AckData] = {}
    gone: list[str] = []

    async def one(robot_id: str, link: MasterLink) -> None:
        try:
            result = await link.command(command)
        except ArenaError as error:
            if error.code is not ErrorCode.ROBOT_STOPPED:
                raise
            gone.append(robot_id)  # deleted just now: it leaves the group's answer
            return
        answer = convert.ack(result).data
        assert answer is not None  # (an ack of a command always says how it went)
        answers[robot_id] = answer

    async with trio.open_nursery() as nursery:
        for robot_id, link in list(members.links.items()):
            nursery.start_soon(one, robot_id, link)
    for robot_id in gone:
        await members.leave(robot_id)
    if not answers:
        return
    ack = wire.GroupAckData.of(answers)
    if members.connection.wants_acks or ack.status != "accepted":
        await members.connection.send(wire.GroupAckMessage(timestamp=wire.now_iso(), data=ack))


async def _handle(members: GroupMembers, message: wire.MasterMessage) -> None:
    connection = members.connection
    for link in members.links.values():
        link.alive()
    if isinstance(message, wire.CommandMessage):
        quality = members.quality
        if quality is not None and not quality.admit(message.data.timestamp):
            for robot_id in members.links:
                connection.app.metrics.stale_commands[robot_id] += 1
            refusal = stale_refusal(quality)
            await connection.send_error(ErrorCode.STALE_COMMAND, refusal.message)
            return
        await _command(members, message.data)
    elif isinstance(message, wire.EStopMessage):
        reason = (message.data.reason if message.data else None) or "e-stop from group master"
        await estop_together([link.robot for link in members.links.values()], reason)
        members.audit("estop over WebSocket", list(members.links))
    elif isinstance(message, wire.ResetMessage):
        reset = []
        for robot_id, link in list(members.links.items()):
            if link.robot.snapshot().mode is Mode.ESTOPPED:
                with contextlib.suppress(ArenaError):  # deleted meanwhile: its forwarder tells
                    await link.robot.reset()
                    reset.append(robot_id)
        members.audit("reset over WebSocket", reset)
    elif isinstance(message, wire.HeartbeatMessage):
        await connection.send(wire.HeartbeatMessage(timestamp=wire.now_iso()))
    elif isinstance(message, wire.ReleaseMessage):
        hold = message.data is not None and message.data.hold
        modes: dict[str, Mode] = {}
        released = []
        for robot_id, link in list(members.links.items()):
            with contextlib.suppress(ArenaError):  # deleted meanwhile: nothing to release
                await link.release(hold=hold)
                modes[robot_id] = link.robot.snapshot().mode
                released.append(robot_id)
        members.audit("release over WebSocket", released)
        mode = Mode.ESTOPPED if Mode.ESTOPPED in modes.values() else Mode.IDLE
        data = wire.ReleasedData(
            members.group_id, str(mode), {robot_id: str(m) for robot_id, m in modes.items()}
        )
        await send_released(connection, data)
    else:
        await connection.send_error(
            ErrorCode.INVALID_MESSAGE,
            "A group master sends commands, e-stops, resets, heartbeats, release.",
        )
