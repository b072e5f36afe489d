"""URLs and the messages a client sends, made with the protocol's own structs
(`arena.protocol.messages`) and encoded by its encoder, so that the client cannot drift from
the wire format the server decodes.

What is not a finite number raises `ValueError` here, before anything is sent: the protocol's
encoder would write NaN as `null`, which the server would take as "no value".
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any
from urllib.parse import quote

import msgspec

from arena.protocol.errors import Severity
from arena.protocol.messages import (
    CommandData,
    CommandMessage,
    ErrorData,
    ErrorMessage,
    EStopMessage,
    HeartbeatMessage,
    InferenceData,
    InferenceMessage,
    JointStateEntry,
    JointStatesMessage,
    JointValue,
    PolicyData,
    PolicyMessage,
    PoseData,
    PoseMessage,
    ReasonData,
    ReleaseData,
    ReleaseMessage,
    ResetMessage,
    now_iso,
)

__all__ = [
    "command",
    "command_message",
    "error",
    "estop",
    "finite_joints",
    "heartbeat",
    "inference",
    "joint_states",
    "joint_states_message",
    "now_iso",
    "policy",
    "pose",
    "release",
    "reset",
    "ws_url",
]

#: The fields of a command's `data` besides its joints (`MasterSession.command(**data)`).
COMMAND_FIELDS = frozenset(CommandData.__struct_fields__) - {"joints"}


def ws_url(base: str, path: str, **query: str) -> str:
    """`http(s)://host:port` or `ws(s)://...` plus `path` -> the WebSocket URL."""
    base = base.rstrip("/")
    if base.startswith("http"):
        base = "ws" + base[len("http") :]
    params = "&".join(f"{k}={quote(v)}" for k, v in query.items() if v)
    return f"{base}{path}" + (f"?{params}" if params else "")


def _finite(value: Any) -> bool:
    return not isinstance(value, bool) and isinstance(value, int | float) and math.isfinite(value)


def finite_joints(joints: Mapping[str, Any]) -> dict[str, float]:
    """`joints` as {name: float}; `ValueError` naming the joint whose value is not a finite
    number (NaN, infinity, None, a string, a bool): such a command never leaves the client."""
    checked: dict[str, float] = {}
    for name, value in joints.items():
        if not _finite(value):
            raise ValueError(f"joint {name!r}: {value!r} is not a finite number of degrees")
        checked[name] = float(value)
    return checked


def _check_numbers(value: Any, where: str) -> None:
    """`ValueError` for a NaN or an infinity anywhere in `value` (JSON has neither)."""
    if isinstance(value, float) and not math.isfinite(value):
        raise ValueError(f"{where}: {value!r} is not a finite number")
    if isinstance(value, Mapping):
        for key, item in value.items():
            _check_numbers(item, f"{where}.{key}")
    elif isinstance(value, list | tuple):
        for index, item in enumerate(value):
            _check_numbers(item, f"{where}[{index}]")


def command(joints: Mapping[str, float], **data: Any) -> CommandMessage:
    """A master's `command`: `joints` in degrees, and any of `timestamp` (the client's
    milliseconds since the epoch), `duration` (ms) and `metadata`. `ValueError` for a value
    that is not a finite number or a field the protocol does not have."""
    unknown = sorted(set(data) - COMMAND_FIELDS)
    if unknown:
        raise ValueError(f"a command has no field {unknown}; it has {sorted(COMMAND_FIELDS)}")
    _check_numbers(data, "command")
    entries = [JointValue(name, value) for name, value in finite_joints(joints).items()]
    return CommandMessage(timestamp=now_iso(), data=CommandData(joints=entries, **data))


def pose(
    position: Sequence[float],
    orientation: Sequence[float] | None = None,
    gripper: float | None = None,
    duration: float | None = None,
) -> PoseMessage:
    """A master's `pose`: the hand's tool point (metres, base frame), its orientation (x, y,
    z, w) if wanted, the gripper, the duration (ms). `ValueError` for what is not finite."""
    given = [*position, *(orientation or ()), gripper, duration]
    _check_numbers([v for v in given if v is not None], "pose")
    data = PoseData(
        [float(v) for v in position],
        None if orientation is None else [float(v) for v in orientation],
        None if gripper is None else float(gripper),
        None if duration is None else float(duration),
    )
    return PoseMessage(timestamp=now_iso(), data=data)


def joint_states(joints: Mapping[str, float]) -> JointStatesMessage:
    """A slave's `joint_states` report: real values in degrees (`ValueError` if not finite)."""
    entries = [
        JointStateEntry(name, value=value, real_value=value)
        for name, value in finite_joints(joints).items()
    ]
    return JointStatesMessage(timestamp=now_iso(), data=entries)


def heartbeat() -> HeartbeatMessage:
    """A `heartbeat`: the peer is still there."""
    return HeartbeatMessage(timestamp=now_iso())


def estop(reason: str) -> EStopMessage:
    """A master's `estop`."""
    return EStopMessage(timestamp=now_iso(), data=ReasonData(reason=reason))


def reset() -> ResetMessage:
    """A master's `reset` (of the robot's e-stop)."""
    return ResetMessage(timestamp=now_iso())


def release(hold: bool = False) -> ReleaseMessage:
    """A master's `release`: hand the robot back (`hold`: the arm stops where it is, rather
    than completing the commands accepted)."""
    data = ReleaseData(hold=True) if hold else None
    return ReleaseMessage(timestamp=now_iso(), data=data)


def policy(fps: float, stall_periods: int) -> PolicyMessage:
    """A master's `policy`: it runs a policy at `fps`, watched over `stall_periods` periods."""
    return PolicyMessage(timestamp=now_iso(), data=PolicyData(fps, stall_periods))


def inference(
    timestep: int,
    chunk_size: int,
    kept: int,
    latency: float,
    seconds: float,
    frame_age: float | None,
) -> InferenceMessage:
    """A policy master's `inference` record (`seconds`: the worker's own part of `latency`)."""
    data = InferenceData(timestep, chunk_size, kept, latency, seconds, frame_age)
    return InferenceMessage(timestamp=now_iso(), data=data)


def error(code: str, message: str, severity: Severity = Severity.ERROR) -> ErrorMessage:
    """A slave's `error` report (`critical` e-stops the robot)."""
    return ErrorMessage(
        timestamp=now_iso(), data=ErrorData(code=code, message=message, severity=severity)
    )


def command_message(joints: Mapping[str, float], **data: Any) -> dict[str, Any]:
    """`command(...)` as a dict (the message as JSON would show it)."""
    built: dict[str, Any] = msgspec.to_builtins(command(joints, **data))
    return built


def joint_states_message(joints: Mapping[str, float]) -> dict[str, Any]:
    """`joint_states(...)` as a dict (the message as JSON would show it)."""
    built: dict[str, Any] = msgspec.to_builtins(joint_states(joints))
    return built
