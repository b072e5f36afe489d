"""Commands, pure: what a master or an operator asks of a robot's joints, validated and
clamped against the robot's model (`resolve_command`), and the answer it gets. The limiter that
turns the goals into motion is `arena.robot.motion`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import msgspec

from arena.protocol.errors import ArenaError, ErrorCode
from arena.protocol.messages import ClampInfo, JointValue
from arena.robot.model import RobotModel

#: One joint's requested value in wire degrees, with an optional speed cap in deg/s: the
#: wire's own type, so a command off the wire (or out of a recording) keeps its joints as
#: they were decoded.
JointGoal = JointValue


class Command(msgspec.Struct, frozen=True, gc=False):
    """A request to move some joints; `duration` (seconds) asks for a smooth move over that time."""

    joints: tuple[JointGoal, ...]
    duration: float | None = None
    source: str | None = None  # free-form label (the wire's metadata.source)
    #: When the values were true, on the robot's clock, if the master knows it (a leader
    #: arm: its bus read, before the command arrived by the bus's and the loop's delays):
    #: a stream's velocity and line are taken from it (`MotionLimiter.set_goals`).
    stamp: float | None = None

    @classmethod
    def of(cls, values: Mapping[str, float], duration: float | None = None) -> Command:
        """Shorthand: `Command.of({"Rotation": 45})`."""
        return cls(tuple(JointGoal(n, v) for n, v in values.items()), duration)


#: A requested value that was outside the limits and what was applied instead: the wire's
#: own type, so an acknowledgment and a record carry a command's clamps as they are.
Clamp = ClampInfo


class CommandResult(msgspec.Struct, frozen=True, gc=False):
    """The answer to a command: accepted (maybe clamped) or refused with a code."""

    accepted: bool
    code: ErrorCode | None = None
    message: str = ""
    clamped: tuple[Clamp, ...] = ()

    @classmethod
    def refused(cls, code: ErrorCode, message: str) -> CommandResult:
        """A refusal."""
        return cls(False, code, message)


class ResolvedGoal(msgspec.Struct, frozen=True, gc=False):
    """A validated goal: protocol joint name, value inside the limits, effective speed."""

    name: str
    value: float
    speed: float


def resolve_command(model: RobotModel, command: Command) -> tuple[list[ResolvedGoal], list[Clamp]]:
    """Validate a command against the model.

    Unknown joints, non-finite values, bad speeds or durations raise `ArenaError`; values outside
    the limits are clamped and listed. Names come back as protocol names (aliases resolved).
    """
    if not command.joints:
        raise ArenaError(ErrorCode.EMPTY_COMMAND, "The command names no joints.")
    if command.duration is not None and not (
        math.isfinite(command.duration) and command.duration >= 0
    ):
        raise ArenaError(ErrorCode.INVALID_VALUE, "duration must be a finite number >= 0.")
    goals: list[ResolvedGoal] = []
    clamps: list[Clamp] = []
    seen: set[str] = set()
    for goal in command.joints:
        spec = model.joint(goal.name)
        if spec is None:
            known = ", ".join(model.joint_names)
            raise ArenaError(
                ErrorCode.UNKNOWN_JOINT, f"Unknown joint {goal.name!r}; this robot has {known}."
            )
        if spec.name in seen:
            raise ArenaError(ErrorCode.INVALID_VALUE, f"Joint {spec.name!r} is named twice.")
        seen.add(spec.name)
        requested = goal.value
        if not _is_finite_number(requested):
            raise ArenaError(
                ErrorCode.INVALID_VALUE,
                f"Joint {spec.name!r}: value must be a finite number of degrees.",
            )
        speed = spec.max_velocity
        if goal.speed is not None:
            if not _is_finite_number(goal.speed) or goal.speed <= 0:
                raise ArenaError(
                    ErrorCode.INVALID_VALUE,
                    f"Joint {spec.name!r}: speed must be a positive number (deg/s).",
                )
            speed = min(speed, float(goal.speed))
        requested = float(requested)
        value = spec.clamp(requested)
        if value != requested:
            clamps.append(Clamp(spec.name, requested, value))
        goals.append(ResolvedGoal(spec.name, value, speed))
    return goals, clamps


def _is_finite_number(value: object) -> bool:
    if type(value) is float:  # what the wire decodes to: one check, per command
        return math.isfinite(value)
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
