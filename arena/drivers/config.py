"""The drivers' own settings, in their own words: the server builds them from the validated
REST bodies (`server/drivers.py`), so a driver never depends on a body's shape or field names.
(`MockSlaveConfig` and `PhysicsSettings` live beside their drivers.)"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Literal

#: What servos do on an e-stop: `hold` (torque kept, goal = present) or `torque-off`.
EStopPolicy = Literal["hold", "torque-off"]


@dataclass(frozen=True, slots=True)
class UsbSlaveConfig:
    """An arm on a servo bus. `port` None: the adapter is found by its USB id;
    `rate`: control loop Hz; `join_speed`: deg/s at which the arm is brought to the robot's
    pose when it joins (None: the robot type's); `torque_limit`: percent of full torque by
    joint name, over the robot type's; `stall_time`: seconds of pushing before a stall."""

    port: str | None = None
    baud_rate: int | None = None  # None: the robot type's
    rate: float = 250.0
    estop: EStopPolicy = "hold"
    join_speed: float | None = None
    torque_limit: Mapping[str, float] = field(default_factory=dict)
    stall_time: float = 1.0


@dataclass(frozen=True, slots=True)
class UsbMasterConfig:
    """A leader arm on a servo bus. `rate`: Hz at which it is read; `deadband`:
    degrees a joint must move before a new command goes out; `actuated`: its servos take
    torque, so that it is first driven to the follower's pose (then goes limp)."""

    port: str | None = None
    baud_rate: int | None = None  # None: the robot type's
    rate: float = 250.0
    deadband: float = 0.5
    actuated: bool = False


@dataclass(frozen=True, slots=True)
class RemoteLinkConfig:
    """A link to a robot on another Arena server: its URL, the robot's id there (None: the
    same as here), the API key, seconds between heartbeats, the first and longest wait
    between reconnection attempts, and whether to displace a master there or here."""

    url: str
    robot_id: str | None = None
    api_key: str | None = None
    heartbeat: float = 30.0
    reconnect_initial: float = 0.5
    reconnect_max: float = 30.0
    takeover: bool = False
