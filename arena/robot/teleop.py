"""Teleoperation by velocity: the hand moves at the velocity a master last sent, inside a box,
and stops when the messages stop (a dead-man). See specs/cartesian.md.

A `VelocityDriver` integrates the velocity into a target pose every tick, solves the joints from
the last ones (a step of a few millimetres: one start, a few iterations) and sends them as a
command through every rule, as any command of the master.
"""

from __future__ import annotations

import math
from collections.abc import Awaitable, Callable, Mapping
from dataclasses import dataclass
from typing import Protocol

import trio

from arena.protocol.messages import JointValue
from arena.robot.cartesian import POSITION_TOLERANCE, Hand
from arena.robot.kinematics import Quaternion, Vector, axis_angle, quaternion_multiply
from arena.robot.motion import Command, CommandResult
from arena.robot.workspace import Workspace

#: Seconds after the last `ee_velocity` message at which the hand stops, unless set.
DEADMAN = 0.2
#: The longest dead-man time that may be set (seconds): longer is no dead-man.
MAX_DEADMAN = 2.0
#: Seconds between targets while the hand moves (50 Hz: half the default command rate).
TICK = 0.02
#: Iterations of the solve of one tick (a step of millimetres needs two or three).
TICK_ITERATIONS = 20


@dataclass(frozen=True, slots=True)
class TeleopSettings:
    """Where teleoperation may take the tool point (an axis-aligned box, metres in the base
    frame) and its dead-man time (seconds)."""

    low: Vector
    high: Vector
    deadman: float = DEADMAN


def default_settings(hand: Hand, workspace: Workspace) -> TeleopSettings:
    """A box around the arm's reach from its first joint, above the table (2 cm over the
    workspace's floor, if it has one)."""
    x, y, z = hand.shoulder
    reach = hand.reach
    bottom = z - reach if workspace.floor is None else max(z - reach, workspace.floor + 0.02)
    return TeleopSettings((x - reach, y - reach, bottom), (x + reach, y + reach, z + reach))


class _Settled(Protocol):
    teleop: TeleopSettings | None


def settings_of(robot: _Settled, hand: Hand, workspace: Workspace) -> TeleopSettings:
    """The robot's teleoperation settings: those set over REST, else the default."""
    return robot.teleop or default_settings(hand, workspace)


class VelocityDriver:
    """The hand of one master, moved by velocity.

    `goals` gives the joints' goals now (where the hand starts from when it starts moving),
    `send` sends a command as the master, `settings` gives the box and dead-man time, and
    `refused` hears of a refused command (the hand stops until the next message)."""

    def __init__(
        self,
        hand: Hand,
        goals: Callable[[], Mapping[str, float]],
        send: Callable[[Command], Awaitable[CommandResult]],
        settings: Callable[[], TeleopSettings],
        refused: Callable[[CommandResult], Awaitable[None]] | None = None,
    ) -> None:
        self.hand = hand
        self._goals = goals
        self._send = send
        self._settings = settings
        self._refused = refused
        self._linear: Vector = (0.0, 0.0, 0.0)
        self._angular: Vector | None = None
        self._gripper = 0.0
        self._heard = -math.inf
        self._wake = trio.Event()
        #: Commands sent, and ticks whose target could not be reached (held there).
        self.sent = 0
        self.held = 0

    def velocity(self, linear: Vector, angular: Vector | None, gripper: float | None) -> None:
        """A message: move at this velocity from now until the next one (or the dead-man)."""
        self._linear = linear
        self._angular = angular if angular is not None and any(angular) else None
        self._gripper = gripper or 0.0
        self._heard = trio.current_time()
        self._wake.set()

    async def run(self) -> None:
        """Move the hand while messages come; wait for them otherwise. Runs until cancelled."""
        while True:
            await self._wake.wait()
            self._wake = trio.Event()
            await self._move()

    async def _move(self) -> None:
        values = dict(self._goals())
        here = self.hand.pose(values)
        if here is None:
            return
        position, orientation = here.position, here.orientation
        gripper_joint = self.hand.gripper
        grip = values.get(gripper_joint.name) if gripper_joint is not None else None
        last = trio.current_time()
        while True:
            await trio.sleep(TICK)
            settings = self._settings()
            now = trio.current_time()
            until = min(now, self._heard + settings.deadman)
            dt = until - last
            last = now
            if dt <= 0:
                return  # the dead-man: no message for too long
            target = _step_in_box(position, self._linear, dt, settings)
            turn = None
            if self._angular is not None:
                turn = _turned(orientation, self._angular, dt)
            moved = target != position or turn is not None
            new_grip = grip
            if gripper_joint is not None and grip is not None and self._gripper:
                new_grip = gripper_joint.clamp(grip + self._gripper * dt)
            if not moved and new_grip == grip:
                continue
            joints = {name: values[name] for name in self.hand.joint_names}
            if moved:
                solution = self.hand.solve(
                    target, turn, values, starts=1, iterations=TICK_ITERATIONS
                )
                if solution.distance > POSITION_TOLERANCE:
                    self.held += 1  # out of reach from here: the hand waits at the edge
                    continue
                joints = solution.joints
            goals = [JointValue(name, value) for name, value in joints.items()]
            if gripper_joint is not None and new_grip is not None:
                goals.append(JointValue(gripper_joint.name, new_grip))
            result = await self._send(Command(tuple(goals), None, "ee_velocity"))
            self.sent += 1
            if not result.accepted:
                self._heard = -math.inf  # stopped until the next message
                if self._refused is not None:
                    await self._refused(result)
                return
            values.update(joints)
            reached = self.hand.pose(values)
            assert reached is not None
            position, orientation, grip = reached.position, reached.orientation, new_grip


def _step_in_box(position: Vector, velocity: Vector, dt: float, box: TeleopSettings) -> Vector:
    """`position` moved for `dt`, never out of the box (a hand outside it may only come back
    toward it, never farther out)."""
    moved = []
    for p, v, low, high in zip(position, velocity, box.low, box.high, strict=True):
        moved.append(min(max(p + v * dt, min(low, p)), max(high, p)))
    return moved[0], moved[1], moved[2]


def _turned(orientation: Quaternion, angular: Vector, dt: float) -> Quaternion:
    """`orientation` turned at `angular` rad/s (base frame) for `dt`."""
    speed = math.hypot(*angular)
    axis = (angular[0] / speed, angular[1] / speed, angular[2] / speed)
    return quaternion_multiply(axis_angle(axis, speed * dt), orientation)
