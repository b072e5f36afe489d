"""Talking to real STS3215 servos through `scservo_sdk` (feetech-servo-sdk) and pyserial: the
Feetech family behind `arena.servo.interface` (`FEETECH`, its `FeetechBus`).

A `FeetechBus` is used from one thread only: the SDK's port is not thread-safe. Its port is the
SDK's with the traps fixed (`arena.servo.ports.PortFixes`: stale input dropped, reads that sleep
in `select()`, a timeout of wire time plus a margin), and

- one silent servo fails a whole `GroupSyncRead`: `sync_read` collects replies one by one, so
  every servo that did answer is kept and the silent one is named.

Both are done as Dynamixel's bus does them, in `arena.servo.sdk_bus.SdkBus`. Besides:

- byte order: `PacketHandler(0)` sets a process-wide global; `open()` sets it again.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import scservo_sdk as sdk

from arena.feetech import registers as reg
from arena.servo.interface import ServoFamily, SyncReadResult, Telemetry
from arena.servo.ports import PortFixes
from arena.servo.sdk_bus import SdkBus, decode_telemetry

#: Present_Load and Torque_Limit at full torque (tenths of a percent).
FULL_TORQUE = 1000
# USB ids of the serial adapters seen on SO-100 arms.
ADAPTERS: dict[tuple[int, int], str] = {(0x1A86, 0x7523): "CH340", (0x1A86, 0x55D3): "CH343"}


class ArenaPort(PortFixes, sdk.PortHandler):  # type: ignore[misc]
    """The SDK's port with the traps fixed (`PortFixes`). Public for `sim_pty`, whose paced
    port is this one waiting also for the simulator."""


class FeetechBus(SdkBus):
    """Servos on one serial port. Not thread-safe: one thread owns it."""

    sdk = sdk
    port_class = ArenaPort
    ID_AT, DATA_AT, MIN_FRAME = 2, 5, 6  # FF FF id length error data... checksum
    BROADCAST_ID = reg.BROADCAST_ID
    PRESENT_POSITION, GOAL_POSITION = reg.PRESENT_POSITION, reg.GOAL_POSITION
    TORQUE_ENABLE, HOMING_OFFSET = reg.TORQUE_ENABLE, reg.HOMING_OFFSET

    def _new_handler(self) -> Any:
        return sdk.PacketHandler(0)  # STS servos are little-endian (process-global): each open

    def _reply_error(self, packet: Sequence[int]) -> int:
        return packet[4]  # the status packet's error bits are the fault flags

    def write(self, servo_id: int, register: reg.Register, value: int) -> None:
        """Write one register and wait for the servo's answer (broadcast: no answer)."""
        data = list(register.encode(value))
        if servo_id == reg.BROADCAST_ID:
            result = self._call(
                self._handler.writeTxOnly,
                self._port,
                servo_id,
                register.address,
                register.size,
                data,
            )
        else:
            result, _ = self._call(
                self._handler.writeTxRx,
                self._port,
                servo_id,
                register.address,
                register.size,
                data,
            )
        self._check(result, servo_id, f"write {register.name}")

    # -- the family-neutral interface (`arena.servo.interface.ServoBus`) ----------------------

    @property
    def family(self) -> ServoFamily:
        """Feetech's."""
        return FEETECH

    def prepare(self, servo_ids: Sequence[int], *, limited: Sequence[int] = ()) -> None:
        """Nothing to do: an STS3215 follows position goals as it comes, and obeys its
        Torque_Limit in any mode."""

    def set_torque_limits(self, limits: Mapping[int, float]) -> None:
        """Torque_Limit (RAM, tenths of a percent; it starts from Max_Torque_Limit at power-on)
        of every servo named."""
        self.sync_write(
            reg.TORQUE_LIMIT,
            {sid: max(0, min(FULL_TORQUE, round(p * 10))) for sid, p in limits.items()},
        )

    def read_telemetry(self, servo_ids: Sequence[int]) -> tuple[Telemetry, SyncReadResult]:
        """Present_Position to Present_Temperature in one request, decoded."""
        result = self.sync_read(reg.TELEMETRY_START, reg.TELEMETRY_SIZE, servo_ids)
        telemetry = decode_telemetry(
            result,
            reg.TELEMETRY_START,
            reg.TELEMETRY_SIZE,
            position=reg.PRESENT_POSITION,
            temperature=reg.PRESENT_TEMPERATURE,
            load=reg.PRESENT_LOAD,
            voltage=reg.PRESENT_VOLTAGE,
            full_load=FULL_TORQUE,
        )
        return telemetry, result

    def set_speed(self, servo_ids: Sequence[int], steps_per_second: int) -> None:
        """Goal_Velocity (steps/s) of every servo named."""
        self.sync_write(reg.GOAL_VELOCITY, dict.fromkeys(servo_ids, steps_per_second))

    def write_homing(self, servo_id: int, value: int) -> None:
        """Homing_Offset into EEPROM: the lock opened for the write and closed after."""
        self.write(servo_id, reg.LOCK, 0)
        self.write(servo_id, reg.HOMING_OFFSET, value)
        self.write(servo_id, reg.LOCK, 1)


#: Feetech's STS servos (the so-arm100's and the SO-101's STS3215).
FEETECH = ServoFamily(
    name="feetech",
    models={"sts3215": reg.STS3215_MODEL},
    default_model="sts3215",
    default_baud=1_000_000,
    adapters=ADAPTERS,
    homing_sign=-1,  # present = actual - Homing_Offset
    homing_limit=reg.HOMING_OFFSET_LIMIT,
    wraps=True,
    open_bus=FeetechBus,
    port_class=ArenaPort,
    lerobot_folders={
        "so-101": {
            "robots": ("so_follower", "so101_follower"),
            "teleoperators": ("so_leader", "so101_leader"),
        },
        "so-arm100": {
            "robots": ("so_follower", "so100_follower"),
            "teleoperators": ("so_leader", "so100_leader"),
        },
        "*": {
            "robots": ("so_follower", "so101_follower", "so100_follower"),
            "teleoperators": ("so_leader", "so101_leader", "so100_leader"),
        },
    },
)
