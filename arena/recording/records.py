"""What a recording holds: one JSON record type per topic kind, made from robot events.

Topics are `/robots/{robot_id}/{kind}`; every record carries `t`, the robot's trio time in
seconds (for exact relative timing in replay), while the MCAP log time is wall-clock ns.
The JSON Schemas of these structs are the MCAP schemas (encoding `jsonschema`).
"""

from __future__ import annotations

from typing import Any

import msgspec

from arena.protocol.messages import ClampInfo, JointValue
from arena.robot.events import (
    CameraFrame,
    CommandHandled,
    EpisodeChanged,
    FaultReported,
    JointStatesReceived,
    PeerChanged,
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


class TargetsRecord(msgspec.Struct, kw_only=True):
    """Targets sent to every slave (degrees)."""

    t: float
    joints: dict[str, float]


class JointStatesRecord(msgspec.Struct, kw_only=True):
    """Real joint values from one slave (degrees)."""

    t: float
    slave_id: str
    joints: dict[str, float]


class StateRecord(msgspec.Struct, kw_only=True):
    """A safety state transition and its cause (e-stops and resets with their reasons)."""

    t: float
    mode: str
    owner: str | None
    estop_reason: str | None
    cause: str


class FaultRecord(msgspec.Struct, kw_only=True):
    """A fault reported by a slave or a driver."""

    t: float
    peer_id: str
    code: str
    message: str
    severity: str
    joint: str | None


class PeerRecord(msgspec.Struct, kw_only=True):
    """A master or slave attached, detached, lost or refused."""

    t: float
    role: str
    peer_id: str
    kind: str
    change: str
    reason: str
    autonomous: bool = False


class EpisodeRecord(msgspec.Struct, kw_only=True):
    """A data-collection episode started, stopped or discarded (`arena export` reads them)."""

    t: float
    change: str  # "start" | "stop" | "discard"
    index: int
    task: str
    started: float  # `t` of the episode's start


#: Topic kind -> record type.
RECORD_TYPES: dict[str, type[msgspec.Struct]] = {
    "command": CommandRecord,
    "targets": TargetsRecord,
    "joint_states": JointStatesRecord,
    "state": StateRecord,
    "fault": FaultRecord,
    "peer": PeerRecord,
    "episode": EpisodeRecord,
}


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
    # The most frequent first: every command makes one; targets follow most commands sent one
    # at a time, and few of a burst's.
    if isinstance(event, CommandHandled):
        command, result = event.command, event.result
        return "command", CommandRecord(
            t=event.time,
            source=event.source,
            joints=list(command.joints),
            duration=None if command.duration is None else command.duration * 1000.0,
            label=command.source,
            accepted=result.accepted,
            code=None if result.code is None else str(result.code),
            message=result.message,
            clamped=[ClampInfo(c.joint, c.requested, c.applied) for c in result.clamped],
        )
    if isinstance(event, TargetsSent):
        return "targets", TargetsRecord(t=event.time, joints=event.joints)
    if isinstance(event, JointStatesReceived):
        return "joint_states", JointStatesRecord(
            t=event.time, slave_id=event.slave_id, joints=event.joints
        )
    if isinstance(event, StateChanged):
        return "state", StateRecord(
            t=event.time,
            mode=str(event.mode),
            owner=event.owner,
            estop_reason=event.estop_reason,
            cause=event.cause,
        )
    if isinstance(event, FaultReported):
        return "fault", FaultRecord(
            t=event.time,
            peer_id=event.peer_id,
            code=event.code,
            message=event.message,
            severity=str(event.severity),
            joint=event.joint,
        )
    if isinstance(event, EpisodeChanged):
        return "episode", EpisodeRecord(
            t=event.time,
            change=event.change,
            index=event.index,
            task=event.task,
            started=event.started,
        )
    return "peer", PeerRecord(
        t=event.time,
        role=event.role,
        peer_id=event.peer_id,
        kind=event.kind,
        change=event.change,
        reason=event.reason,
        autonomous=event.autonomous,
    )


#: Topic kind -> the robot event it records (what `record_of` maps).
EVENT_TYPES: dict[str, type[RobotEvent]] = {
    "command": CommandHandled,
    "targets": TargetsSent,
    "joint_states": JointStatesReceived,
    "state": StateChanged,
    "fault": FaultReported,
    "peer": PeerChanged,
    "episode": EpisodeChanged,
}
#: Observed type -> its topic kind (camera frames are "image"; their topics are per camera).
KIND_OF_EVENT: dict[type[msgspec.Struct], str] = {
    event: kind for kind, event in {**EVENT_TYPES, "image": CameraFrame}.items()
}


def schema_of(kind: str) -> dict[str, Any]:
    """The JSON Schema of a record kind."""
    return msgspec.json.schema(RECORD_TYPES[kind])
