"""The ROS 2 messages Arena speaks, in CDR, through rosbags' codec and its Jazzy type store.

Joint values here are the URDF's: radians (metres for a prismatic joint), by URDF joint name.
The service `std_srvs/srv/Trigger` is not in rosbags' store; it is added with its request,
response and event types so that its type hash (REP 2016) is the one ROS computes.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from rosbags.interfaces import Nodetype
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

from arena.robot.kinematics import Pose

JOINT_STATE = "sensor_msgs/msg/JointState"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
STRING = "std_msgs/msg/String"
FLOAT64_ARRAY = "std_msgs/msg/Float64MultiArray"
TRAJECTORY = "trajectory_msgs/msg/JointTrajectory"
TRIGGER = "std_srvs/srv/Trigger"
#: Points of one trajectory Arena plays (a longer one is refused).
MAX_POINTS = 10_000


@functools.cache
def store() -> Typestore:
    """rosbags' ROS 2 Jazzy types, with std_srvs/srv/Trigger."""
    types = get_typestore(Stores.ROS2_JAZZY)
    name, base, seq, array = Nodetype.NAME, Nodetype.BASE, Nodetype.SEQUENCE, Nodetype.ARRAY
    request, response, event = f"{TRIGGER}_Request", f"{TRIGGER}_Response", f"{TRIGGER}_Event"
    fields: dict[str, Any] = {
        request: ([], []),
        response: ([], [("success", (base, ("bool", 0))), ("message", (base, ("string", 0)))]),
        event: (
            [],
            [
                ("info", (name, "service_msgs/msg/ServiceEventInfo")),
                ("request", (seq, ((name, request), 1))),
                ("response", (seq, ((name, response), 1))),
            ],
        ),
        TRIGGER: (
            [],
            [
                ("request_message", (name, request)),
                ("response_message", (name, response)),
                ("event_message", (name, event)),
            ],
        ),
    }
    types.register({k: v for k, v in fields.items() if k != TRIGGER})
    # The service's own description exists only to be hashed; ServiceEventInfo's `char[16]`
    # is `uint8[16]` in ROS's type description (rosbags hashes it as `char`).
    types.fielddefs[TRIGGER] = fields[TRIGGER]
    consts, info = types.fielddefs["service_msgs/msg/ServiceEventInfo"]
    hashed: list[Any] = [
        (n, (array, ((base, ("uint8", 0)), 16))) if n == "client_gid" else (n, d) for n, d in info
    ]
    types.fielddefs["service_msgs/msg/ServiceEventInfo"] = (consts, hashed)
    return types


@functools.cache
def type_hash(ros_type: str) -> str:
    """The type's REP 2016 hash (`RIHS01_...`), as rmw_zenoh puts it in key expressions."""
    return store().hash_rihs01(ros_type)


def _stamp(ns: int) -> Any:
    time = store().types["builtin_interfaces/msg/Time"]
    return time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def _header(ns: int, frame: str = "") -> Any:
    return store().types["std_msgs/msg/Header"](stamp=_stamp(ns), frame_id=frame)


def joint_state(ns: int, names: Sequence[str], positions: Sequence[float]) -> bytes:
    """A `sensor_msgs/msg/JointState` stamped `ns` (ns since the epoch)."""
    types = store()
    message = types.types[JOINT_STATE](
        header=_header(ns),
        name=list(names),
        position=np.array(positions, dtype=np.float64),
        velocity=np.array([], dtype=np.float64),
        effort=np.array([], dtype=np.float64),
    )
    return bytes(types.serialize_cdr(message, JOINT_STATE))


def transforms(ns: int, frames: Sequence[tuple[str, str, Pose]]) -> bytes:
    """A `tf2_msgs/msg/TFMessage`: (parent frame, child frame, pose of child in parent)."""
    types = store().types
    vector, quaternion = types["geometry_msgs/msg/Vector3"], types["geometry_msgs/msg/Quaternion"]
    transform, stamped = (
        types["geometry_msgs/msg/Transform"],
        types["geometry_msgs/msg/TransformStamped"],
    )
    items = []
    for parent, child, ((qx, qy, qz, qw), (x, y, z)) in frames:
        items.append(
            stamped(
                header=_header(ns, parent),
                child_frame_id=child,
                transform=transform(
                    translation=vector(x=x, y=y, z=z),
                    rotation=quaternion(x=qx, y=qy, z=qz, w=qw),
                ),
            )
        )
    return bytes(store().serialize_cdr(types[TF_MESSAGE](transforms=items), TF_MESSAGE))


def string(text: str) -> bytes:
    """A `std_msgs/msg/String`."""
    return bytes(store().serialize_cdr(store().types[STRING](data=text), STRING))


def trigger_response(success: bool, message: str) -> bytes:
    """A `std_srvs/srv/Trigger` response."""
    kind = f"{TRIGGER}_Response"
    return bytes(store().serialize_cdr(store().types[kind](success=success, message=message), kind))


@dataclass(frozen=True, slots=True)
class TrajectoryPoint:
    """One point of a trajectory: URDF values by joint, and when it is due (s from the start)."""

    at: float
    positions: dict[str, float]


def read_trajectory(data: bytes) -> list[TrajectoryPoint]:
    """The points of a `trajectory_msgs/msg/JointTrajectory`, in time order; ValueError says
    what is wrong with it."""
    message = _decode(data, TRAJECTORY)
    names = list(message.joint_names)
    if not names:
        raise ValueError("the trajectory names no joints")
    if len(set(names)) != len(names):
        raise ValueError("the trajectory names a joint twice")
    if not message.points:
        raise ValueError("the trajectory has no points")
    if len(message.points) > MAX_POINTS:
        raise ValueError(f"the trajectory has more than {MAX_POINTS} points")
    points, last = [], -1.0
    for k, point in enumerate(message.points):
        if len(point.positions) != len(names):
            raise ValueError(
                f"point {k} has {len(point.positions)} positions for {len(names)} joints"
            )
        at = point.time_from_start.sec + point.time_from_start.nanosec / 1e9
        if at < last:
            raise ValueError(f"point {k} comes before the point ahead of it")
        last = at
        values = [float(v) for v in point.positions]
        if not all(np.isfinite(values)):
            raise ValueError(f"point {k} has a position that is not a number")
        points.append(TrajectoryPoint(at, dict(zip(names, values, strict=True))))
    return points


def read_positions(data: bytes) -> list[float]:
    """The values of a `std_msgs/msg/Float64MultiArray`; ValueError when not finite."""
    values = [float(v) for v in _decode(data, FLOAT64_ARRAY).data]
    if not all(np.isfinite(values)):
        raise ValueError("a position is not a number")
    return values


def _decode(data: bytes, ros_type: str) -> Any:
    try:
        return store().deserialize_cdr(data, ros_type)
    except Exception as exc:  # rosbags raises what its parser meets: all mean "not this type"
        raise ValueError(f"not a {ros_type} in CDR ({type(exc).__name__})") from None


def trajectory(ns: int, names: Sequence[str], positions: Sequence[float], at: float) -> bytes:
    """A `trajectory_msgs/msg/JointTrajectory` of one point due `at` seconds from its start."""
    types = store().types
    empty = np.array([], dtype=np.float64)
    whole = int(at)
    point = types["trajectory_msgs/msg/JointTrajectoryPoint"](
        positions=np.array(positions, dtype=np.float64),
        velocities=empty,
        accelerations=empty,
        effort=empty,
        time_from_start=types["builtin_interfaces/msg/Duration"](
            sec=whole, nanosec=round((at - whole) * 1e9)
        ),
    )
    message = types[TRAJECTORY](header=_header(ns), joint_names=list(names), points=[point])
    return bytes(store().serialize_cdr(message, TRAJECTORY))
