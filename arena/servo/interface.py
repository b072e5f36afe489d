"""What every servo family gives the rest of Arena: one bus interface, one description.

A family (Feetech's STS servos, Dynamixel's X series) is a `ServoFamily`: its name, its model
numbers, its default baud rate, the USB adapters it comes with, how its Homing_Offset register
acts, and how to open its `ServoBus`. The bus worker, the drivers and the calibration speak only
this interface; `arena.feetech` and `arena.dynamixel` each implement it. The robot core knows a
robot type's `[bus] family` only as a name.
"""

from __future__ import annotations

import enum
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

from arena.protocol.errors import ArenaError

#: Steps in one turn of every servo Arena drives (STS3215, Dynamixel X series).
STEPS_PER_TURN = 4096
CENTER_STEP = 2048
MAX_STEP = STEPS_PER_TURN - 1


class BusError(ArenaError):
    """The bus itself failed (port gone, unreadable): the driver closes it and reconnects."""


class FaultBit(enum.IntFlag):
    """A servo's fault flags, whatever its family reports them as (the bus translates)."""

    VOLTAGE = 1
    ANGLE = 2
    OVERHEAT = 4
    OVERCURRENT = 8
    OVERLOAD = 32


@dataclass
class SyncReadResult:
    """What a sync read got back: data and fault flags per servo that answered, and the rest."""

    data: dict[int, bytes] = field(default_factory=dict)
    errors: dict[int, int] = field(default_factory=dict)  # FaultBit flags by servo id
    missing: list[int] = field(default_factory=list)
    corrupt: list[int] = field(default_factory=list)


@dataclass(frozen=True, slots=True)
class Telemetry:
    """A telemetry read, decoded: present positions (raw steps), temperatures (C), loads
    (the family's own unit, magnitude only), voltages (V), by servo id; and the loads as
    percents of each servo's full torque (`load_percent`: the unit torque limits are in)."""

    positions: dict[int, int]
    temperatures: dict[int, int]
    loads: dict[int, int]
    voltages: dict[int, float]
    load_percent: dict[int, float] = field(default_factory=dict)


class ServoBus(Protocol):
    """Servos on one serial port, used from one thread only (the SDKs' ports are not
    thread-safe). Raw steps are the servo's own Present/Goal_Position units."""

    port_name: str

    @property
    def family(self) -> ServoFamily:
        """The family of servos on this bus."""

    def open(self) -> None:
        """Open the port; problems raise `BusError` with what to do about them."""

    def close(self) -> None:
        """Close the port (no error if it is gone already)."""

    @property
    def is_open(self) -> bool:
        """Whether the port is open."""

    def ping(self, servo_id: int) -> int:
        """The servo's model number; `ArenaError(SERVO_TIMEOUT)` if it does not answer."""

    def prepare(self, servo_ids: Sequence[int], *, limited: Sequence[int] = ()) -> None:
        """Whatever the family needs before its servos follow position goals (run at connect,
        before the hold: Dynamixel's operating mode, say). `limited`: the servos that will be
        given a torque limit (`set_torque_limits`), where the family needs a mode for it
        (Dynamixel's current-based position control). Never moves a servo."""

    def set_torque_limits(self, limits: Mapping[int, float]) -> None:
        """The most torque each servo named may give, in percent of its full torque; an
        `ArenaError(INVALID_CONFIG)` for a servo that cannot be limited."""

    def read_positions(self, servo_ids: Sequence[int]) -> tuple[dict[int, int], SyncReadResult]:
        """Present positions of several servos in one request; and what came back."""

    def read_telemetry(self, servo_ids: Sequence[int]) -> tuple[Telemetry, SyncReadResult]:
        """Positions, load, voltage and temperature of several servos; and what came back."""

    def write_goals(self, goals: Mapping[int, int]) -> None:
        """Goal positions (raw steps by servo id) in one packet."""

    def set_torque(self, servo_ids: Sequence[int], *, on: bool) -> None:
        """Torque on or off for every servo named."""

    def set_speed(self, servo_ids: Sequence[int], steps_per_second: int) -> None:
        """The fastest the servos may move toward a goal."""

    def read_homings(self, servo_ids: Sequence[int]) -> dict[int, int]:
        """Each servo's Homing_Offset register."""

    def write_homing(self, servo_id: int, value: int) -> None:
        """Store a Homing_Offset in one servo (EEPROM; torque must be off)."""


@dataclass(frozen=True)
class ServoFamily:
    """A family of servos and what Arena needs to know of it (see the module docstring).

    `homing_sign`: how the servo applies its Homing_Offset register, `present = actual +
    homing_sign * homing` (Feetech -1, Dynamixel +1). `wraps`: whether present positions stay
    within one turn (Feetech) or count turns (Dynamixel, signed 32 bits): LeRobot's arithmetic
    follows the servo. `lerobot_folders`: the folder names LeRobot files its calibrations under,
    by robot type and then by `robots`/`teleoperators`, newest first.
    """

    name: str
    models: Mapping[str, int]  # model name -> model number
    default_model: str
    default_baud: int
    adapters: Mapping[tuple[int, int], str]  # USB (vendor, product) -> adapter name
    homing_sign: int
    homing_limit: int
    wraps: bool
    open_bus: Callable[..., ServoBus]  # (port, baud, *, timeout_margin=..., port_handler=...)
    port_class: type[Any]  # the SDK port handler the bus uses (sim_pty paces a subclass)
    lerobot_folders: Mapping[str, Mapping[str, tuple[str, ...]]] = field(default_factory=dict)

    def model_number(self, model: str) -> int:
        """The model number a servo of this model answers a ping with."""
        return self.models[model]
