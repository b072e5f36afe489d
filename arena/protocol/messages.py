"""The wire messages, as typed structs: decode and validate at the edge, encode on the way out.

The shapes follow the LeRobot Arena contract (`type`, `timestamp`, `data`). Unknown fields are
refused (UNKNOWN_FIELD, naming the field and the allowed ones: a misspelled field must not be
dropped without a word); missing or mistyped fields are errors. Joint
values are degrees, durations and sequence timestamps are milliseconds, speeds are deg/s.

`decode_master`, `decode_slave` return a message or raise `ArenaError` with one of
INVALID_JSON, UNKNOWN_MESSAGE_TYPE, UNKNOWN_FIELD, INVALID_MESSAGE, MESSAGE_TOO_LARGE. No I/O
here.
"""

from __future__ import annotations

import datetime
import time
from typing import Annotated, Any, Literal, TypeAlias

import msgspec

from arena.protocol.errors import ArenaError, ErrorCode, Severity
from arena.protocol.validation import refusal

#: Largest accepted WebSocket frame or request body, in bytes.
MAX_MESSAGE_BYTES = 64 * 1024


class _Msg(msgspec.Struct, tag_field="type", omit_defaults=True, kw_only=True):
    """Base of every message: the `type` tag and an optional ISO timestamp."""

    timestamp: str | None = None


# --- shared pieces ----------------------------------------------------------------------------


# Immutable: the robot core takes a command's joints as they were decoded (its `JointGoal`).
class JointValue(
    msgspec.Struct, omit_defaults=True, frozen=True, gc=False, forbid_unknown_fields=True
):
    """A joint and its value in degrees; `speed` caps its velocity (deg/s)."""

    name: str
    value: float
    speed: float | None = None


class CommandData(msgspec.Struct, omit_defaults=True, forbid_unknown_fields=True):
    """The body of a command."""

    joints: list[JointValue]
    timestamp: float | None = None  # client's milliseconds since the epoch
    duration: float | None = None  # ms: reach the targets smoothly over this time
    metadata: dict[str, Any] | None = None


class SequenceStep(msgspec.Struct, omit_defaults=True, forbid_unknown_fields=True):
    """One command of a sequence, `timestamp` ms after the start."""

    joints: list[JointValue]
    timestamp: float = 0.0
    duration: float | None = None


class SequenceData(msgspec.Struct, omit_defaults=True, forbid_unknown_fields=True):
    """A movement sequence."""

    commands: list[SequenceStep]
    id: str = "custom"
    name: str | None = None
    total_duration: float | None = None
    loop: bool = False


class ReasonData(msgspec.Struct, omit_defaults=True, forbid_unknown_fields=True):
    """Why something happened."""

    reason: str | None = None


# --- master -> server -------------------------------------------------------------------------


class CommandMessage(_Msg, tag="command", forbid_unknown_fields=True):
    """Move joints."""

    data: CommandData


class SequenceMessage(_Msg, tag="sequence", forbid_unknown_fields=True):
    """Play a sequence of commands with its timing."""

    data: SequenceData


class HeartbeatMessage(_Msg, tag="heartbeat", forbid_unknown_fields=True):
    """I am still here."""


class EStopMessage(_Msg, tag="estop", forbid_unknown_fields=True):
    """Emergency stop."""

    data: ReasonData | None = None


class ResetMessage(_Msg, tag="reset", forbid_unknown_fields=True):
    """Leave the e-stop."""


class ReleaseData(msgspec.Struct, omit_defaults=True, forbid_unknown_fields=True):
    """How a master lets go: `hold` stops the arm where it is now; without it the commands
    already accepted complete."""

    hold: bool = False


class ReleaseMessage(_Msg, tag="release", forbid_unknown_fields=True):
    """I am done: hand the robot back (no e-stop). The moves already accepted complete, unless
    `data.hold` asks the arm to stop where it is. Answered `released`, then the server closes
    the socket (1000)."""

    data: ReleaseData | None = None


#: Seconds (a latency, an age): finite, not negative, under a day.
Seconds = Annotated[float, msgspec.Meta(ge=0, le=86_400)]
#: A count of actions or steps.
Count = Annotated[int, msgspec.Meta(ge=0, le=2**31)]


class PolicyData(msgspec.Struct, omit_defaults=True, forbid_unknown_fields=True):
    """A master that runs a policy elsewhere (`arena policy --url`) says so once: its control
    rate and watchdog periods, so the server keeps its watchdog and its record as it does for
    a policy it runs itself."""

    fps: Annotated[float, msgspec.Meta(gt=0, le=1000)]
    stall_periods: Annotated[int, msgspec.Meta(ge=1, le=1000)] = 2


class PolicyMessage(_Msg, tag="policy", forbid_unknown_fields=True):
    """Declare this master a policy (`PolicyData`)."""

    data: PolicyData


class InferenceData(msgspec.Struct, omit_defaults=True, forbid_unknown_fields=True):
    """One inference of a policy master that runs elsewhere, as `events.PolicyInferred`
    records it (seconds; `frame_age` None: no camera)."""

    timestep: Count
    chunk_size: Count
    kept: Count
    latency: Seconds
    inference: Seconds
    frame_age: Seconds | None = None


class InferenceMessage(_Msg, tag="inference", forbid_unknown_fields=True):
    """Record one inference (`InferenceData`); only after `policy`."""

    data: InferenceData


#: A coordinate (metres) of a hand's target: no arm Arena drives reaches 10 m.
Metres = Annotated[float, msgspec.Meta(ge=-10, le=10)]
#: A component of a velocity: m/s, rad/s, or the gripper's unit per second.
Rate = Annotated[float, msgspec.Meta(ge=-1000, le=1000)]


class PoseData(msgspec.Struct, omit_defaults=True, forbid_unknown_fields=True):
    """Where the hand should go (specs/cartesian.md): its tool point in metres in the robot's
    base frame, optionally its orientation (a quaternion x, y, z, w; left out: any), the
    gripper's value (degrees or percent, as its joint) and the move's duration (ms)."""

    position: Annotated[list[Metres], msgspec.Meta(min_length=3, max_length=3)]
    orientation: Annotated[list[Rate], msgspec.Meta(min_length=4, max_length=4)] | None = None
    gripper: float | None = None
    duration: Annotated[float, msgspec.Meta(ge=0, le=3_600_000)] | None = None


class PoseMessage(_Msg, tag="pose", forbid_unknown_fields=True):
    """Move the hand to a pose (`PoseData`); acknowledged as a command is."""

    data: PoseData


class EeVelocityData(msgspec.Struct, omit_defaults=True, forbid_unknown_fields=True):
    """Move the hand at this velocity until the next message, or until messages stop for the
    robot's dead-man time: `linear` m/s and `angular` rad/s in the base frame, `gripper` in
    its joint's unit per second."""

    linear: Annotated[list[Rate], msgspec.Meta(min_length=3, max_length=3)]
    angular: Annotated[list[Rate], msgspec.Meta(min_length=3, max_length=3)] | None = None
    gripper: Rate | None = None


class EeVelocityMessage(_Msg, tag="ee_velocity", forbid_unknown_fields=True):
    """Drive the hand by velocity (`EeVelocityData`): teleoperation without a leader arm."""

    data: EeVelocityData


#: A joint's name in a move's goal (a robot type's names are short).
GoalJoint = Annotated[str, msgspec.Meta(min_length=1, max_length=64)]


class MoveData(msgspec.Struct, omit_defaults=True, forbid_unknown_fields=True):
    """A goal, `joints` (by name) or `pose`, reached straight (one command) or, with `plan`,
    along a path found within `budget` ms at `speed` (0-1) of the limits (specs/cartesian.md)."""

    joints: Annotated[dict[GoalJoint, float], msgspec.Meta(max_length=32)] | None = None
    pose: PoseData | None = None
    plan: bool = False
    budget: Annotated[float, msgspec.Meta(ge=10, le=10_000)] | None = None
    speed: Annotated[float, msgspec.Meta(ge=0.01, le=1)] | None = None
    duration: Annotated[float, msgspec.Meta(ge=0, le=3_600_000)] | None = None


class MoveMessage(_Msg, tag="move", forbid_unknown_fields=True):
    """Move to a goal (`MoveData`), straight or along a path played as this master's commands."""

    data: MoveData


MasterMessage: TypeAlias = (
    CommandMessage
    | SequenceMessage
    | HeartbeatMessage
    | EStopMessage
    | ResetMessage
    | ReleaseMessage
    | PolicyMessage
    | InferenceMessage
    | PoseMessage
    | EeVelocityMessage
    | MoveMessage
)


# --- slave -> server --------------------------------------------------------------------------


class StatusData(msgspec.Struct, omit_defaults=True, forbid_unknown_fields=True):
    """A slave's connection status."""

    isConnected: bool = True
    lastConnected: str | None = None
    error: str | None = None


class StatusUpdateMessage(_Msg, tag="status_update", forbid_unknown_fields=True):
    """A slave reports its status."""

    data: StatusData


class JointStateEntry(msgspec.Struct, omit_defaults=True, forbid_unknown_fields=True):
    """A joint's measured value: `real_value`, or `value` from simpler slaves."""

    name: str
    real_value: float | None = None
    value: float | None = None
    virtual_value: float | None = None
    servo_id: int | None = None
    type: str | None = None
    limits: dict[str, Any] | None = None


class JointStatesMessage(_Msg, tag="joint_states", forbid_unknown_fields=True):
    """Measured joint values."""

    data: list[JointStateEntry]


class ErrorData(msgspec.Struct, omit_defaults=True, forbid_unknown_fields=True):
    """A fault: code, sentence, joint, severity."""

    code: str
    message: str = ""
    joint: str | None = None
    severity: Severity = Severity.ERROR


class ErrorMessage(_Msg, tag="error", forbid_unknown_fields=True):
    """A fault report (from a slave) or an error answer (from the server)."""

    data: ErrorData


SlaveMessage: TypeAlias = StatusUpdateMessage | JointStatesMessage | ErrorMessage | HeartbeatMessage


# --- server -> clients ------------------------------------------------------------------------


# Immutable: the robot core reports its clamps in this type (its `Clamp`), so an answer, its
# acknowledgment and its record hold the same values.
class ClampInfo(msgspec.Struct, frozen=True, gc=False):
    """A value that was clamped to the limits."""

    joint: str
    requested: float
    applied: float


class AckData(msgspec.Struct):
    """The answer to a command: accepted, clamped (with what) or refused (with a code)."""

    status: Literal["accepted", "clamped", "refused"]
    code: str | None = None
    message: str = ""
    clamped: list[ClampInfo] = msgspec.field(default_factory=list)


class AckMessage(_Msg, tag="ack"):
    """Acknowledgment of one command or sequence."""

    data: AckData | None = None


class GroupAckData(msgspec.Struct):
    """The answer to a group master's command: each member's ack, and the group's `status`:
    `refused` if every member refused, `partial` if some did, else `clamped` if any member
    clamped, else `accepted`."""

    status: Literal["accepted", "clamped", "partial", "refused"]
    members: dict[str, AckData]

    @classmethod
    def of(cls, members: dict[str, AckData]) -> GroupAckData:
        """The group's answer made of its members' answers."""
        statuses = {answer.status for answer in members.values()}
        if "refused" in statuses:
            return cls("refused" if statuses == {"refused"} else "partial", members)
        return cls("clamped" if "clamped" in statuses else "accepted", members)


class GroupAckMessage(_Msg, tag="ack"):
    """Acknowledgment of a group master's command, one ack per member."""

    data: GroupAckData


class JointLimits(msgspec.Struct):
    """A joint's limits in degrees and deg/s."""

    lower: float
    upper: float
    velocity: float


class JointStateOut(msgspec.Struct):
    """A joint as the server reports it."""

    name: str
    servo_id: int
    type: str
    virtual_value: float
    real_value: float | None
    limits: JointLimits


class JointStatesOut(_Msg, tag="joint_states"):
    """Every joint's commanded and measured value."""

    data: list[JointStateOut] = msgspec.field(default_factory=list)


class MasterInfo(msgspec.Struct):
    """A robot's master: its label (`id`, the state's `owner`), its kind (`websocket`,
    `mock-sequence`, `replay`, ...) and what it is in words (`sequence 'gentle-wave'`,
    `replay of 'x.mcap'`, `WebSocket client`), as `TakenBy` names one."""

    id: str
    kind: str
    description: str


class StateData(msgspec.Struct):
    """A robot's safety state, and its master (null when it has none)."""

    robot_id: str
    mode: str
    owner: str | None
    estop_reason: str | None
    master: MasterInfo | None


class StateMessage(_Msg, tag="state"):
    """The robot's safety state changed (or, on connect, what it is)."""

    data: StateData | None = None


class FaultData(msgspec.Struct):
    """A fault of one of the robot's peers (a master or a slave) or of a camera, or with
    `cleared` its end (`message` says how: its source said so, a reset, the peer left)."""

    robot_id: str
    peer_id: str
    code: str
    message: str
    severity: str
    joint: str | None = None
    cleared: bool = False


class FaultMessage(_Msg, tag="fault"):
    """A fault as it happens, or its end (sent to viewers)."""

    data: FaultData


class ExecuteData(msgspec.Struct):
    """Targets for a slave."""

    joints: list[JointValue]


class ExecuteCommandMessage(_Msg, tag="execute_command"):
    """Move to these targets now."""

    data: ExecuteData | None = None


class NoticeData(msgspec.Struct):
    """Why a notice was sent."""

    reason: str = ""


class EStopNotice(_Msg, tag="estop"):
    """Stop at once (sent to slaves)."""

    data: NoticeData | None = None


class ResetNotice(_Msg, tag="reset"):
    """The e-stop is over; wait for the next target (sent to slaves)."""

    data: NoticeData | None = None


class HoldNotice(_Msg, tag="hold"):
    """Hold the current position (sent to slaves)."""

    data: NoticeData | None = None


class StopNotice(_Msg, tag="stop"):
    """The slave was detached or the robot is going away (sent to slaves)."""

    data: NoticeData | None = None


class TakenBy(msgspec.Struct, omit_defaults=True):
    """The master that took a robot over: its label (`id`), its kind (`websocket`,
    `mock-sequence`, `replay`, `remote-server`, `usb-master`, ...) and what it is in words
    (`sequence 'gentle-wave'`, `replay of 'x.mcap'`)."""

    id: str
    kind: str
    description: str = ""


class DetachedData(msgspec.Struct, omit_defaults=True):
    """Why a master lost the robot; `by`: who took it over (with TAKEN_OVER)."""

    code: str
    message: str
    by: TakenBy | None = None


class DetachedMessage(_Msg, tag="detached"):
    """This master no longer owns the robot."""

    data: DetachedData | None = None


class PauseNotice(_Msg, tag="pause"):
    """To a master: the robot paused it (`POST .../master/pause`, an intervention): send
    nothing until `resume` (what it sends meanwhile is refused MASTER_PAUSED)."""


class ResumeNotice(_Msg, tag="resume"):
    """To a paused master: it may command again."""


class ReleasedData(msgspec.Struct, omit_defaults=True):
    """A master's release done: the robot's mode now (`idle`, or `estopped` if it was
    e-stopped). To a group master: the group's id, `mode` `estopped` if any member is, and
    each member's mode in `members`."""

    robot_id: str
    mode: str
    members: dict[str, str] | None = None


class ReleasedMessage(_Msg, tag="released"):
    """The answer to `release`: the master no longer holds the robot; the socket closes."""

    data: ReleasedData


class MemberLeftData(msgspec.Struct):
    """Which member of a group left, and why."""

    robot_id: str
    reason: str


class MemberLeftMessage(_Msg, tag="member_left"):
    """To a group master: a member is gone (deleted); the group goes on with the rest."""

    data: MemberLeftData


class MissedData(msgspec.Struct):
    """How many messages of each kind a peer that stopped reading did not get. Joint states
    and states count those superseded by a newer one, which follows this message."""

    ack: int = 0
    joint_states: int = 0
    state: int = 0
    error: int = 0
    heartbeat: int = 0
    fault: int = 0


class MissedMessage(_Msg, tag="missed"):
    """Sent once a peer that stopped reading reads again, before the newest states."""

    data: MissedData


# --- codec ------------------------------------------------------------------------------------

_master_decoder = msgspec.json.Decoder(MasterMessage)
_slave_decoder = msgspec.json.Decoder(SlaveMessage)
_encoder = msgspec.json.Encoder()


_second_cache: tuple[int, str] = (-1, "")
_millisecond_cache: tuple[int, str] = (-1, "")


def now_iso() -> str:
    """The current UTC time as ISO 8601 to the millisecond, the wire's `timestamp` format."""
    global _second_cache, _millisecond_cache
    milliseconds = time.time_ns() // 1_000_000
    if _millisecond_cache[0] == milliseconds:  # the messages one command causes share it
        return _millisecond_cache[1]
    second, millisecond = divmod(milliseconds, 1000)
    if _second_cache[0] != second:  # formatting a date costs ~1 us; most calls share a second
        moment = datetime.datetime.fromtimestamp(second, datetime.UTC)
        _second_cache = (second, moment.strftime("%Y-%m-%dT%H:%M:%S"))
    _millisecond_cache = (milliseconds, f"{_second_cache[1]}.{millisecond:03d}Z")
    return _millisecond_cache[1]


def _decode(decoder: msgspec.json.Decoder[Any], raw: str | bytes) -> Any:
    if len(raw) > MAX_MESSAGE_BYTES:
        raise ArenaError(
            ErrorCode.MESSAGE_TOO_LARGE,
            f"Message of {len(raw)} bytes is over the {MAX_MESSAGE_BYTES}-byte limit.",
        )
    try:
        return decoder.decode(raw)
    except msgspec.ValidationError as exc:
        raise refusal(
            decoder.type, raw, exc, what="message", code=ErrorCode.INVALID_MESSAGE
        ) from None
    except msgspec.DecodeError as exc:
        raise ArenaError(ErrorCode.INVALID_JSON, f"Not valid JSON: {exc}") from None
    except RecursionError:  # msgspec's own depth guard
        raise ArenaError(ErrorCode.INVALID_JSON, "The message is nested too deeply.") from None


def decode_master(raw: str | bytes) -> MasterMessage:
    """Decode and validate a message from a master."""
    message: MasterMessage = _decode(_master_decoder, raw)
    return message


def decode_slave(raw: str | bytes) -> SlaveMessage:
    """Decode and validate a message from a slave."""
    message: SlaveMessage = _decode(_slave_decoder, raw)
    return message


def encode(message: msgspec.Struct) -> str:
    """Encode an outgoing message as JSON text."""
    return _encoder.encode(message).decode()


def error_message(code: ErrorCode | str, message: str) -> str:
    """An `error` message as JSON text."""
    return encode(
        ErrorMessage(timestamp=now_iso(), data=ErrorData(code=str(code), message=message))
    )
