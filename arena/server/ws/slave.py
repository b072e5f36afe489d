"""The slave endpoint, `/ws/slave/{robot id}`: `execute_command` and notices out; joint
states, status and errors in."""

from __future__ import annotations

from functools import partial

import trio

from arena.protocol import messages as wire
from arena.protocol.errors import ArenaError, ErrorCode
from arena.robot.events import NoticeKind, SlaveNotice, SlaveTarget
from arena.robot.links import SlaveLink
from arena.server import convert
from arena.server.ws.connection import CLOSE_NORMAL, Connection, peer_ids


async def serve(connection: Connection, robot_id: str) -> None:
    """A slave: `execute_command` and notices out; joint states, status and errors in."""
    robot = await connection.accept(robot_id)
    if robot is None:
        return
    app = connection.app
    try:
        link = await robot.connect_slave(
            connection.args.get("id") or f"ws-slave-{next(peer_ids)}",
            kind="websocket",
            heartbeat_timeout=app.arena_config.heartbeat_timeout,
        )
    except ArenaError as error:
        await connection.refuse(error)
        return
    connection.count_open([robot_id])
    robot.audit(connection.principal.audit_name(), "connect slave", link.slave_id)
    ended_by_robot = trio.Event()
    try:

        async def body(nursery: trio.Nursery) -> None:
            nursery.start_soon(slave_writer, connection, link, ended_by_robot)
            nursery.start_soon(connection.heartbeats)
            await connection.read_loop(
                wire.decode_slave, partial(_handle_slave_message, connection, link)
            )

        await connection.run(body)
    finally:
        connection.count_closed()
        if not ended_by_robot.is_set():
            with trio.CancelScope(shield=True):
                if app.shutting_down.is_set():
                    await link.detach("server shutting down")
                else:
                    await link.lost("connection closed")


async def slave_writer(connection: Connection, link: SlaveLink, ended: trio.Event) -> None:
    """Send the robot's targets and notices to the slave, newest target first; `ended` is
    set when the robot ends the link."""

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
        else:  # connected without an error: a status fault it had is over
            await link.clear_fault(ErrorCode.SLAVE_STATUS, message="connected again")
    else:
        link.alive()
