"""What a robot tells the world: events for observers and notices for its masters and slaves.

Observers (the server, dashboards, the recorder) receive `RobotEvent`s; masters receive
`MasterNotice`s; slaves receive targets (`SlaveTarget`) and `SlaveNotice`s. `time` is trio time,
`wall_time` is Unix time (for timestamps on the wire and in recordings).

Each event's fields are declared here and nowhere else. Its record in a recording is derived
from them (`recording/records.py`: every field but `robot_id`, `time` and `wall_time`; a
command's record is the one deliberate exception, named there), and its form in Foxglove is
one entry of a table (`recording/foxglove.py`: the tree a pose moves, or a log line); both
modules check at import that every `RobotEvent` has its form. A field added here is
recorded: `specs/schemas/record-*.json` then changes, and `tests/test_schemas.py` says so.

Every type here holds only immutable values (strings, numbers, enums, tuples and dicts of
them, other such structs), so none can be part of a reference cycle: they are left out of the
garbage collector (`gc=False`). A burst keeps thousands of events alive until the recorder's
next batch, and each young-generation collection walked all of them (4-9 ms a pass).
"""

from __future__ import annotations

import enum
from typing import TypeAlias

import msgspec

from arena.protocol.errors import ErrorCode, Severity
from arena.robot.motion import Command, CommandResult
from arena.robot.safety import Mode


class SlaveTarget(msgspec.Struct, frozen=True, gc=False):
    """Where every joint should be now (wire degrees), with the speed cap per joint (deg/s).

    `more_follow`: the command behind it came in a master's burst, with more of its commands
    in hand, so a newer target follows at once; a slave's writer may leave this one to be
    replaced (slaves get the newest target) rather than write it now."""

    joints: dict[str, float]
    time: float
    more_follow: bool = False


class NoticeKind(enum.StrEnum):
    """Non-target messages to a slave."""

    ESTOP = "estop"  # stop at once (the slave's e-stop policy: hold or torque off)
    RESET = "reset"  # the e-stop is over; wait for the next target
    HOLD = "hold"  # keep the current position (the master left)
    SHUTDOWN = "shutdown"  # the robot is going away or the slave was detached


class SlaveNotice(msgspec.Struct, frozen=True, gc=False):
    """A control notice to a slave."""

    kind: NoticeKind
    reason: str = ""


class TakenBy(msgspec.Struct, frozen=True, gc=False):
    """The master that took a robot over: its id, kind and what it is in words."""

    master_id: str
    kind: str
    description: str


class MasterNotice(msgspec.Struct, frozen=True, gc=False):
    """Something a master should know: it was detached (`by`: who took over), or the robot
    changed state."""

    kind: str  # "detached" | "state" | "paused" | "resumed" | "stopped" (by the guard)
    code: ErrorCode | None = None
    message: str = ""
    mode: Mode | None = None
    by: TakenBy | None = None
    blocked: tuple[str, str] | None = None  # "stopped": the two things that would have met


class Observed(msgspec.Struct, frozen=True, gc=False, tag_field="event", tag=True):
    """What observers receive: robot events and camera frames. Each is tagged with its class
    name, so that a list of them packs and unpacks in one call (the recorder's hand-off)."""


class StateChanged(Observed, frozen=True, gc=False):
    """The safety state changed (mode, owner or e-stop reason)."""

    robot_id: str
    mode: Mode
    owner: str | None
    estop_reason: str | None
    cause: str
    time: float
    wall_time: float


class CommandHandled(Observed, frozen=True, gc=False):
    """A command arrived (from `source`: a master id or 'manual') and how it was answered."""

    robot_id: str
    source: str
    command: Command
    result: CommandResult
    time: float
    wall_time: float


class TargetsSent(Observed, frozen=True, gc=False):
    """Targets sent to every slave."""

    robot_id: str
    joints: dict[str, float]
    time: float
    wall_time: float


class JointStatesReceived(Observed, frozen=True, gc=False):
    """Real joint values reported by a slave."""

    robot_id: str
    slave_id: str
    joints: dict[str, float]
    time: float
    wall_time: float


class FaultReported(Observed, frozen=True, gc=False):
    """A fault of a peer (a master or a slave), a camera or a driver, or with `cleared` the
    end of one a peer had: its source said it is over (`message` says how), the robot was
    reset, or the peer left."""

    robot_id: str
    peer_id: str
    code: str
    message: str
    severity: Severity
    joint: str | None
    time: float
    wall_time: float
    cleared: bool = False


class PeerChanged(Observed, frozen=True, gc=False):
    """A master or slave attached, detached or was lost."""

    robot_id: str
    role: str  # "master" | "slave"
    peer_id: str
    kind: str  # driver kind, e.g. "mock-slave"
    # "attached" | "detached" | "released" (a master's own `release`) | "lost" | "refused" |
    # "disconnected" | "reconnected", and for a slave that measures "adopted" | "joining" |
    # "joined" (specs/robot-model.md), and for a master "paused" | "resumed"
    change: str
    reason: str
    time: float
    wall_time: float
    autonomous: bool = False  # a master that plays a program (sequence, replay)
    code: str | None = None  # why a master was "refused" (MASTER_ACTIVE, ...), as it was told


class EpisodeChanged(Observed, frozen=True, gc=False):
    """A data-collection episode started, stopped, was discarded, or was cut: its robot stopped
    while it ran (`episodes.py`)."""

    robot_id: str
    change: str  # "start" | "stop" | "discard" | "cut"
    index: int  # the episode's number on this robot since the server started
    task: str
    started: float  # trio time the episode started
    time: float
    wall_time: float


class Audited(Observed, frozen=True, gc=False):
    """Who did something to the robot: `user` (a token's `sub`, or which API key: never the
    key or the token), the `action` (a REST route, or a WebSocket's connect, e-stop or reset)
    and its `detail` (the HTTP status, or the peer id it acts as)."""

    robot_id: str
    user: str
    action: str
    detail: str
    time: float
    wall_time: float


class InterventionChanged(Observed, frozen=True, gc=False):
    """An intervention `started` or `ended`: `master` is the intervening master, `paused` the
    master it paused (which waits, and drives again once handed back)."""

    robot_id: str
    change: str  # "started" | "ended"
    master: str
    paused: str
    time: float
    wall_time: float


class PolicyInferred(Observed, frozen=True, gc=False):
    """One inference of a policy master (`arena/policy`): `policy` its identity, `timestep`
    the control step its observation was taken at, `chunk_size` the actions the chunk held
    and `kept` those not already due, `latency` seconds from the observation sent to the chunk
    back (`inference`: the worker's own part of it), `frame_age` seconds from the capture of
    the oldest camera frame the observation carried to its sending (None: no camera)."""

    robot_id: str
    policy: str
    timestep: int
    chunk_size: int
    kept: int
    latency: float
    inference: float
    frame_age: float | None
    time: float
    wall_time: float


class MotionStopped(Observed, frozen=True, gc=False):
    """The collision guard stopped a motion on its way, after its command was accepted (a
    target on the way the joints really take would have met something): `source` commanded
    it (a master id, or 'manual'), `code` and `message` say why, `blocked` names the two
    things, `joints` where the arm holds and `goals` where it was going."""

    robot_id: str
    source: str
    code: str
    message: str
    blocked: tuple[str, str]
    joints: dict[str, float]
    goals: dict[str, float]
    time: float
    wall_time: float


RobotEvent: TypeAlias = (
    StateChanged
    | CommandHandled
    | TargetsSent
    | JointStatesReceived
    | FaultReported
    | PeerChanged
    | EpisodeChanged
    | Audited
    | PolicyInferred
    | InterventionChanged
    | MotionStopped
)


class CameraFrame(Observed, frozen=True, gc=False):
    """One JPEG frame of a robot's camera (`arena/sensors`), stamped at capture on the same
    clocks as the robot's events. Frames travel apart from `RobotEvent`s: they are large, and
    whoever wants them subscribes to the camera."""

    robot_id: str
    camera: str
    seq: int  # frames captured by this camera before this one
    time: float
    wall_time: float
    width: int
    height: int
    jpeg: bytes
