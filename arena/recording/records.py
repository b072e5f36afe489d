"""What a recording holds: one JSON record type per topic kind, made from robot events.

Topics are `/robots/{robot_id}/{kind}`; every record carries `t`, the robot's trio time in
seconds (for exact relative timing in replay), while the MCAP log time is wall-clock ns.
The JSON Schemas of these structs are the MCAP schemas (encoding `jsonschema`).

A record is its event's fields (`robot/events.py` declares them, once), derived here at
import: `RECORDED` names each event's topic kind and its record, and says where a record
differs from its event. The formats are fixed by the files already written: `specs/schemas`
holds them, and a test compares.
"""

from __future__ import annotations

import enum
import operator
from collections.abc import Callable
from typing import Any, NamedTuple, get_args

import msgspec

from arena.protocol.messages import ClampInfo, JointValue
from arena.robot.events import (
    Audited,
    CameraFrame,
    CommandHandled,
    EpisodeChanged,
    FaultReported,
    InterventionChanged,
    JointStatesReceived,
    MotionStopped,
    Observed,
    PeerChanged,
    PolicyInferred,
    RobotEvent,
    StateChanged,
    TargetsSent,
)


class CommandRecord(msgspec.Struct, kw_only=True):
    """A command as received, with its source and how it was answered."""

    t: float
    source: str
    joints: list[JointValue]
    duration: float | None  # milliseconds
    label: str | None
    accepted: bool
    code: str | None
    message: str
    clamped: list[ClampInfo]


def _command_record(event: CommandHandled) -> CommandRecord:
    command, result = event.command, event.result
    return CommandRecord(
        t=event.time,
        source=event.source,
        joints=list(command.joints),
        duration=None if command.duration is None else command.duration * 1000.0,
        label=command.source,
        accepted=result.accepted,
        code=None if result.code is None else str(result.code),
        message=result.message,
        clamped=list(result.clamped),
    )


class Recorded(NamedTuple):
    """How one robot event is recorded: on which topic kind, and its record's name and
    description (its JSON Schema's `title` and `description`)."""

    kind: str
    event: type[Observed]
    name: str
    description: str


#: Every robot event and its record. Each record is derived from its event's fields
#: (`derive_record`) but a command's, `CommandRecord` above, which differs on purpose: it is
#: flat (the command's fields and its answer's beside the event's), its duration is in
#: milliseconds as on the wire, and the command's own `source` is its `label` (the event's
#: `source` says who sent it).
RECORDED = (
    Recorded("command", CommandHandled, "CommandRecord", str(CommandRecord.__doc__)),
    Recorded("targets", TargetsSent, "TargetsRecord", "Targets sent to every slave (degrees)."),
    Recorded(
        "joint_states",
        JointStatesReceived,
        "JointStatesRecord",
        "Real joint values from one slave (degrees).",
    ),
    Recorded(
        "state",
        StateChanged,
        "StateRecord",
        "A safety state transition and its cause (e-stops and resets with their reasons).",
    ),
    Recorded("fault", FaultReported, "FaultRecord", "A fault reported by a slave or a driver."),
    Recorded(
        "peer", PeerChanged, "PeerRecord", "A master or slave attached, detached, lost or refused."
    ),
    Recorded(
        "episode",
        EpisodeChanged,
        "EpisodeRecord",
        "A data-collection episode started, stopped, discarded or cut (its robot stopped while "
        "it ran: a server's shutdown, the robot deleted); `arena export` reads them.",
    ),
    Recorded(
        "audit",
        Audited,
        "AuditRecord",
        "Who did what: a caller's action on the robot (a token's sub or which API key).",
    ),
    Recorded(
        "policy",
        PolicyInferred,
        "PolicyRecord",
        "One inference of a policy master: its latency (seconds) and chunk size (specs/policy.md).",
    ),
    Recorded(
        "intervention",
        InterventionChanged,
        "InterventionRecord",
        "An intervention started or ended: the intervening master and the master it paused "
        "(a correction; `arena export` marks its frames).",
    ),
    Recorded(
        "stop",
        MotionStopped,
        "StopRecord",
        "A motion the collision guard stopped on its way after accepting it: who commanded "
        "it, why, what would have met, where the arm holds and where it was going.",
    ),
)

#: The event fields no record holds: the topic names the robot, `time` is the record's `t`
#: (its first field), and `wall_time` is the message's MCAP log time.
NOT_RECORDED = frozenset({"robot_id", "time", "wall_time"})

#: Makes a record of an event.
Maker = Callable[[Any], msgspec.Struct]


def derive_record(recorded: Recorded) -> tuple[type[msgspec.Struct], Maker]:
    """The record type of an event (`t`, then the event's fields in their order but those
    in `NOT_RECORDED`, an enum as a plain string) and how to make one: positional, through
    one attribute getter made here, so that a record costs what a hand-written one did."""
    fields: list[tuple[str, Any] | tuple[str, Any, Any]] = [("t", float)]
    for field in msgspec.structs.fields(recorded.event):
        if field.name in NOT_RECORDED:
            continue
        # A StrEnum member is a str, so it goes into the record as it is and encodes as its
        # value; readers get the plain string back.
        kind = field.type
        if isinstance(kind, type) and issubclass(kind, enum.StrEnum):
            kind = str
        fields.append((field.name, kind) if field.required else (field.name, kind, field.default))
    record = msgspec.defstruct(
        recorded.name, fields, module=__name__, namespace={"__doc__": recorded.description}
    )
    names = [field[0] for field in fields[1:]]
    if len(names) == 1:  # (an attrgetter of one name returns the value, not a tuple)
        one = operator.attrgetter(names[0])
        return record, lambda event: record(event.time, one(event))
    several = operator.attrgetter(*names)
    return record, lambda event: record(event.time, *several(event))


def _forms() -> dict[type, tuple[str, type[msgspec.Struct], Maker]]:
    """Event type -> (topic kind, record type, maker), for every robot event."""
    forms: dict[type, tuple[str, type[msgspec.Struct], Maker]] = {}
    for recorded in RECORDED:
        if recorded.event is CommandHandled:
            forms[CommandHandled] = (recorded.kind, CommandRecord, _command_record)
        else:
            forms[recorded.event] = (recorded.kind, *derive_record(recorded))
    missing = set(get_args(RobotEvent)) - set(forms)
    if missing:  # (else a new event would fail at its first recording)
        raise TypeError(f"robot events without a record: {sorted(t.__name__ for t in missing)}")
    return forms


_FORMS = _forms()
#: Topic kind -> record type.
RECORD_TYPES: dict[str, type[msgspec.Struct]] = {kind: t for kind, t, _ in _FORMS.values()}
#: Event type -> (its topic kind, what makes its record).
_MAKERS: dict[type, tuple[str, Maker]] = {e: (kind, make) for e, (kind, _, make) in _FORMS.items()}


def topic(robot_id: str, kind: str) -> str:
    """The MCAP topic of one kind of record of one robot."""
    return f"/robots/{robot_id}/{kind}"


#: Topic kinds that show a robot in Foxglove (`foxglove.py`), recorded beside the records.
VIEW_KINDS = ("tf", "scene", "log")


#: Topic kinds of cameras start so: a camera's topic is `/robots/{id}/cameras/{name}`.
CAMERA_PREFIX = "cameras/"


def camera_kind(name: str) -> str:
    """The topic kind of a camera."""
    return CAMERA_PREFIX + name


def camera_of_topic(name: str) -> tuple[str, str] | None:
    """(robot id, camera name) of a camera topic, or None."""
    parts = name.split("/")
    if len(parts) == 5 and parts[:2] == ["", "robots"] and parts[3] == "cameras" and parts[4]:
        return parts[2], parts[4]
    return None


def is_view_topic(name: str) -> bool:
    """True for a robot's Foxglove topic (`/robots/{id}/tf` and the like, and its cameras'
    images): kept undecoded when a file is read."""
    parts = name.split("/")
    in_view = len(parts) == 4 and parts[:2] == ["", "robots"] and parts[3] in VIEW_KINDS
    return in_view or camera_of_topic(name) is not None


def split_topic(name: str) -> tuple[str, str] | None:
    """(robot_id, kind) of a topic, or None if it is not one of ours."""
    parts = name.split("/")
    if len(parts) == 4 and parts[0] == "" and parts[1] == "robots" and parts[3] in RECORD_TYPES:
        return parts[2], parts[3]
    return None


def record_of(event: RobotEvent) -> tuple[str, msgspec.Struct]:
    """The (kind, record) for a robot event."""
    kind, make = _MAKERS[type(event)]
    return kind, make(event)


#: Observed type -> its topic kind (camera frames are "image"; their topics are per camera).
KIND_OF_EVENT: dict[type[Observed], str] = {CameraFrame: "image"}
KIND_OF_EVENT.update((recorded.event, recorded.kind) for recorded in RECORDED)


def schema_of(kind: str) -> dict[str, Any]:
    """The JSON Schema of a record kind."""
    return msgspec.json.schema(RECORD_TYPES[kind])
