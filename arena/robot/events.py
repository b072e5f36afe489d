"""What a robot tells the world: events for observers and notices for its masters and slaves.

Observers (the server, dashboards, the recorder) receive `RobotEvent`s; masters receive
`MasterNotice`s; slaves receive targets (`SlaveTarget`) and `SlaveNotice`s. `time` is trio time,
`wall_time` is Unix time (for timestamps on the wire and in recordings).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import TypeAlias

from arena.protocol.errors import ErrorCode, Severity
from arena.robot.motion import Command, CommandResult
from arena.robot.safety import Mode


@dataclass(frozen=True, slots=True)
class SlaveTarget:
    """Where every joint should be now (wire degrees), with the speed cap per joint (deg/s)."""

    joints: dict[str, float]
    time: float


class NoticeKind(enum.StrEnum):
    """Non-target messages to a slave."""

    ESTOP = "estop"  # stop at once (the slave's e-stop policy: hold or torque off)
    RESET = "reset"  # the e-stop is over; wait for the next target
    HOLD = "hold"  # keep the current position (the master left)
    SHUTDOWN = "shutdown"  # the robot is going away or the slave was detached


@dataclass(frozen=True, slots=True)
class SlaveNotice:
    """A control notice to a slave."""

    kind: NoticeKind
    reason: str = ""


@dataclass(frozen=True, slots=True)
class MasterNotice:
    """Something a master should know: it was detached, or the robot changed state."""

    kind: str  # "detached" | "state"
    code: ErrorCode | None = None
    message: str = ""
    mode: Mode | None = None


@dataclass(frozen=True, slots=True)
class StateChanged:
    """The safety state changed (mode, owner or e-stop reason)."""

    robot_id: str
    mode: Mode
    owner: str | None
    estop_reason: str | None
    cause: str
    time: float
    wall_time: float


@dataclass(frozen=True, slots=True)
class CommandHandled:
    """A command arrived (from `source`: a master id or 'manual') and how it was answered."""

    robot_id: str
    source: str
    command: Command
    result: CommandResult
    time: float
    wall_time: float


@dataclass(frozen=True, slots=True)
class TargetsSent:
    """Targets sent to every slave."""

    robot_id: str
    joints: dict[str, float]
    time: float
    wall_time: float


@dataclass(frozen=True, slots=True)
class JointStatesReceived:
    """Real joint values reported by a slave."""

    robot_id: str
    slave_id: str
    joints: dict[str, float]
    time: float
    wall_time: float


@dataclass(frozen=True, slots=True)
class FaultReported:
    """A fault reported by a slave or a driver."""

    robot_id: str
    peer_id: str
    code: str
    message: str
    severity: Severity
    joint: str | None
    time: float
    wall_time: float


@dataclass(frozen=True, slots=True)
class PeerChanged:
    """A master or slave attached, detached or was lost."""

    robot_id: str
    role: str  # "master" | "slave"
    peer_id: str
    kind: str  # driver kind, e.g. "mock-slave"
    change: str  # "attached" | "detached" | "lost" | "refused" | "disconnected" | "reconnected"
    reason: str
    time: float
    wall_time: float
    autonomous: bool = False  # a master that plays a program (sequence, replay)


RobotEvent: TypeAlias = (
    StateChanged | CommandHandled | TargetsSent | JointStatesReceived | FaultReported | PeerChanged
)
