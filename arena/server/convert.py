"""Between wire messages (degrees, milliseconds, the seed's shapes) and the robot core's types."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import msgspec

from arena.drivers.sequences import Sequence, parse_sequence
from arena.protocol import messages as wire
from arena.robot.events import FaultReported, MotionStopped, NoticeKind, SlaveNotice, SlaveTarget
from arena.robot.handle import Robot
from arena.robot.motion import Command, CommandResult
from arena.robot.snapshot import MasterEnded, PeerSnapshot, RobotSnapshot
from arena.server.link_quality import LinkQuality


def command_from_wire(
    joints: list[wire.JointValue], duration_ms: float | None, metadata: dict[str, Any] | None = None
) -> Command:
    """A wire command (degrees, milliseconds) as a core `Command` (degrees, seconds)."""
    source = metadata.get("source") if metadata else None
    return Command(
        tuple(joints),  # the wire's joint values are the core's goals (immutable)
        None if duration_ms is None else duration_ms / 1000.0,
        str(source) if source is not None else None,
    )


def sequence_from_wire(data: wire.SequenceData) -> Sequence:
    """A wire sequence as a core `Sequence` (raises `ArenaError` when malformed)."""
    return parse_sequence(msgspec.to_builtins(data))


def ack(result: CommandResult) -> wire.AckMessage:
    """The acknowledgment of a command."""
    if not result.accepted:
        data = wire.AckData("refused", str(result.code), result.message)
    elif result.clamped:
        data = wire.AckData("clamped", None, result.message, list(result.clamped))
    else:  # (its message: a way out of a collision in the model, say)
        data = wire.AckData("accepted", None, result.message)
    return wire.AckMessage(timestamp=wire.now_iso(), data=data)


def joint_states(robot: Robot) -> wire.JointStatesOut:
    """Every joint's virtual and real value now, in the seed's `joint_states` shape."""
    return JointStatesView(robot).message()


class JointStatesView:
    """`joint_states` of one robot as it is now, without a full snapshot. WebSocket clients
    get one after almost every command: keep a view, and the parts that never change are
    built once."""

    def __init__(self, robot: Robot) -> None:
        self.robot = robot
        self._fixed = [
            (j.name, j.servo_id, wire.JointLimits(j.lower, j.upper, j.max_velocity))
            for j in robot.model.joints
        ]

    def message(self) -> wire.JointStatesOut:
        """The message, stamped now."""
        virtual, real = self.robot.joint_values()
        return wire.JointStatesOut(
            timestamp=wire.now_iso(),
            data=[
                wire.JointStateOut(
                    name, servo_id, "revolute", virtual[name], real.get(name), limits
                )
                for name, servo_id, limits in self._fixed
            ],
        )


def state(snapshot: RobotSnapshot) -> wire.StateMessage:
    """The robot's safety state, and what its master is."""
    master = snapshot.master
    info = (
        None if master is None else wire.MasterInfo(master.peer_id, master.kind, master.description)
    )
    return wire.StateMessage(
        timestamp=wire.now_iso(),
        data=wire.StateData(
            snapshot.robot_id,
            str(snapshot.mode),
            snapshot.owner,
            snapshot.estop_reason,
            info,
        ),
    )


#: A slave notice's wire message: the notice's own name (NoticeKind's value), but for a
#: shutdown, which the wire calls `stop` (specs/api.md).
_NOTICES: dict[
    NoticeKind, type[wire.EStopNotice | wire.ResetNotice | wire.HoldNotice | wire.StopNotice]
] = {
    NoticeKind.ESTOP: wire.EStopNotice,
    NoticeKind.RESET: wire.ResetNotice,
    NoticeKind.HOLD: wire.HoldNotice,
    NoticeKind.SHUTDOWN: wire.StopNotice,
}


def to_slave(message: SlaveTarget | SlaveNotice) -> msgspec.Struct:
    """What a WebSocket slave receives: `execute_command` or a notice."""
    if isinstance(message, SlaveTarget):
        joints = [wire.JointValue(name, value) for name, value in message.joints.items()]
        return wire.ExecuteCommandMessage(timestamp=wire.now_iso(), data=wire.ExecuteData(joints))
    return _NOTICES[message.kind](timestamp=wire.now_iso(), data=wire.NoticeData(message.reason))


def fault(event: FaultReported) -> wire.FaultMessage:
    """A fault, or its end, as viewers get it."""
    return wire.FaultMessage(
        timestamp=wire.now_iso(),
        data=wire.FaultData(
            event.robot_id,
            event.peer_id,
            event.code,
            event.message,
            str(event.severity),
            event.joint,
            event.cleared,
        ),
    )


def stop_fault(event: MotionStopped) -> wire.FaultMessage:
    """A motion the guard stopped on its way, as viewers get it: a warning of whoever
    commanded it (a master id, or `manual`: the dashboard's sliders, a REST caller)."""
    data = wire.FaultData(event.robot_id, event.source, event.code, event.message, "warning")
    return wire.FaultMessage(timestamp=wire.now_iso(), data=data)


def _peer(peer: PeerSnapshot) -> dict[str, Any]:
    return {
        "id": peer.peer_id,
        "type": peer.kind,
        "connected": peer.connected,
        "last_error": peer.last_error,
        "joining": peer.joining,
        "faults": [
            {
                "code": f.code,
                "message": f.message,
                "severity": f.severity,
                "joint": f.joint,
            }
            for f in peer.faults
        ],
    }


def _master(
    peer: PeerSnapshot | None, links: Mapping[str, LinkQuality] | None = None
) -> dict[str, Any] | None:
    """A master as a peer, with its `kind` and `description` as `TAKEN_OVER`'s `by` names
    them (`kind` is its `type`): a client shows what plays without having started it. A
    WebSocket master's `link` (round trip, jitter, stale commands) from `links`, by master id."""
    if peer is None:
        return None
    shown = _peer(peer) | {
        "kind": peer.kind,
        "description": peer.description,
        "paused": peer.paused,
    }
    if peer.figures is not None:
        shown["figures"] = peer.figures
    link = (links or {}).get(peer.peer_id)
    if link is not None:
        shown["link"] = link.as_dict()
    return shown


def robot_summary(
    robot: Robot, tenant: str = "default", links: Mapping[str, LinkQuality] | None = None
) -> dict[str, Any]:
    """A robot as the REST API shows it (`tenant`: whose it is; `links`: its WebSocket
    master's, if it has one)."""
    snapshot = robot.snapshot()
    return {
        "id": snapshot.robot_id,
        "name": snapshot.name,
        "tenant": tenant,
        "robot_type": snapshot.robot_type,
        "state": str(snapshot.mode),
        "owner": snapshot.owner,
        "estop_reason": snapshot.estop_reason,
        "master": _master(snapshot.master, links),
        "paused_master": _master(snapshot.paused_master, links),
        "last_master": _ended(robot.last_master),
        "last_stop": _stopped(robot.last_stop),
        "corrections": {
            "total": robot.intervention_count,
            "episode": robot.episodes.running_corrections(),
        },
        "slaves": [_peer(s) for s in snapshot.slaves],
        "joints": msgspec.to_builtins(joint_states(robot).data),
    }


def _ended(master: MasterEnded | None) -> dict[str, Any] | None:
    """The last master that left, as the details show it."""
    if master is None:
        return None
    return {
        "id": master.peer_id,
        "type": master.kind,
        "description": master.description,
        "ended": master.change,
        "reason": master.reason,
        "error": master.error,
        "at": round(master.at, 3),
    }


def _stopped(stop: MotionStopped | None) -> dict[str, Any] | None:
    """The last motion the collision guard stopped on its way, as the details show it."""
    if stop is None:
        return None
    return {
        "source": stop.source,
        "code": stop.code,
        "message": stop.message,
        "blocked": list(stop.blocked),
        "joints": {name: round(value, 4) for name, value in stop.joints.items()},
        "goals": {name: round(value, 4) for name, value in stop.goals.items()},
        "at": round(stop.wall_time, 3),
    }


def robot_status(robot: Robot, links: Mapping[str, LinkQuality] | None = None) -> dict[str, Any]:
    """Connection status: who is attached, and the safety state."""
    snapshot = robot.snapshot()
    return {
        "id": snapshot.robot_id,
        "state": str(snapshot.mode),
        "has_master": snapshot.master is not None,
        "master": _master(snapshot.master, links),
        "paused_master": _master(snapshot.paused_master, links),
        "slave_count": len(snapshot.slaves),
        "slaves": [_peer(s) for s in snapshot.slaves],
        "estop_reason": snapshot.estop_reason,
    }
