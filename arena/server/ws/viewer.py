"""The viewer endpoint, `/ws/robots/{robot id}/state`: read-only, the robot's state, joint
states and faults as they change. Any number may watch."""

from __future__ import annotations

import msgspec
import trio

from arena.protocol.errors import ErrorCode
from arena.server import convert
from arena.server.ws.connection import Connection
from arena.server.ws.forwarder import FORWARDED_TO_VIEWERS, QUEUE_LENGTH, RobotEventForwarder


async def serve(connection: Connection, robot_id: str) -> None:
    """Read-only: the robot's state, joint states and faults as they change. Any number may
    watch."""
    robot = await connection.accept(robot_id)
    if robot is None:
        return
    connection.count_open([robot_id])
    try:
        with robot.subscribe(maxlen=QUEUE_LENGTH, kinds=FORWARDED_TO_VIEWERS) as events:
            await connection.send(convert.state(robot.snapshot()))
            if connection.wants_joint_states:
                await connection.send(convert.joint_states(robot))

            async def body(nursery: trio.Nursery) -> None:
                nursery.start_soon(connection.heartbeats)
                nursery.start_soon(RobotEventForwarder(connection, robot, events).run)
                await _viewer_reader(connection)

            await connection.run(body)
    finally:
        connection.count_closed()


async def _viewer_reader(connection: Connection) -> None:
    while True:
        raw = await connection.receive_text()
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
