"""A master's `ee_velocity` messages: the hand driven by velocity (`arena.robot.teleop`)."""

from __future__ import annotations

import trio

from arena.protocol import messages as wire
from arena.protocol.errors import ArenaError, ErrorCode
from arena.robot.handle import Robot
from arena.robot.links import MasterLink
from arena.robot.motion import CommandResult
from arena.robot.teleop import VelocityDriver, settings_of
from arena.server import convert
from arena.server.hand_api import hand_of
from arena.server.ws.connection import Connection


class HandDrive:
    """One master's velocity driver, started with its first `ee_velocity` message and ended
    with the connection."""

    def __init__(self, connection: Connection, robot: Robot, link: MasterLink) -> None:
        self._connection = connection
        self._robot = robot
        self._link = link
        self._driver: VelocityDriver | None = None

    def velocity(self, data: wire.EeVelocityData, nursery: trio.Nursery) -> None:
        """Move the hand at this velocity (INVALID_VALUE for a gripper velocity of a hand
        without a gripper; INVALID_CONFIG for a robot type with no hand)."""
        robot = self._robot
        hand = hand_of(robot)
        if data.gripper and hand.gripper is None:
            raise ArenaError(
                ErrorCode.INVALID_VALUE,
                f"Robot type {robot.model.robot_type!r} names no gripper joint: "
                "leave `gripper` out.",
            )
        if self._driver is None:
            self._driver = VelocityDriver(
                hand,
                lambda: {joint.name: joint.goal for joint in robot.snapshot().joints},
                self._link.command,
                lambda: settings_of(robot, hand, robot.workspace),
                self._refused,
            )
            nursery.start_soon(self._driver.run)
        linear = (data.linear[0], data.linear[1], data.linear[2])
        angular = None
        if data.angular is not None:
            angular = (data.angular[0], data.angular[1], data.angular[2])
        self._driver.velocity(linear, angular, data.gripper)

    async def _refused(self, result: CommandResult) -> None:
        await self._connection.send(convert.ack(result))
