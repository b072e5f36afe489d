"""Talking to real STS3215 servos through `scservo_sdk` (feetech-servo-sdk) and pyserial: the
Feetech family behind `arena.servo.interface` (`FEETECH`, its `FeetechBus`).

A `FeetechBus` is used from one thread only: the SDK's port is not thread-safe. Its port is the
SDK's with the traps fixed (`arena.servo.ports.PortFixes`: stale input dropped, reads that sleep
in `select()`, a timeout of wire time plus a margin). Besides:

- one silent servo fails a whole `GroupSyncRead`: `sync_read` collects replies one by one, so
  every servo that did answer is kept and the silent one is named.
- byte order: `PacketHandler(0)` sets a process-wide global; `open()` sets it again.
"""

from __future__ import annotations

import termios
from collections.abc import Mapping, Sequence
from typing import Any

import scservo_sdk as sdk
import serial

from arena.feetech import registers as reg
from arena.protocol.errors import ArenaError, ErrorCode
from arena.servo.interface import BusError, ServoFamily, SyncReadResult, Telemetry
from arena.servo.ports import DEFAULT_TIMEOUT_MARGIN, PortFixes, port_error

# USB ids of the serial adapters seen on SO-100 arms.
ADAPTERS: dict[tuple[int, int], str] = {(0x1A86, 0x7523): "CH340", (0x1A86, 0x55D3): "CH343"}


class ArenaPort(PortFixes, sdk.PortHandler):  # type: ignore[misc]
    """The SDK's port with the traps fixed (`PortFixes`). Public for `sim_pty`, whose paced
    port is this one waiting also for the simulator."""


class FeetechBus:
    """Servos on one serial port. Not thread-safe: one thread owns it."""

    def __init__(
        self,
        port: str,
        baud: int = 1_000_000,
        *,
        timeout_margin: float = DEFAULT_TIMEOUT_MARGIN,
        port_handler: ArenaPort | None = None,
    ) -> None:
        self.port_name = port
        self.baud = baud
        self._port = port_handler or ArenaPort(port, timeout_margin)
        self._handler: Any = None

    # -- port -------------------------------------------------------------------------------

    def open(self) -> None:
        """Open the port; problems raise `BusError` with what to do about them."""
        self._handler = sdk.PacketHandler(0)  # STS servos are little-endian (process-global)
        self._port.baudrate = self.baud
        if self._port.getCFlagBaud(self.baud) <= 0:
            raise BusError(ErrorCode.INVALID_CONFIG, f"Baud rate {self.baud} is not supported.")
        try:
            self._port.setupPort(self.baud)
        except (serial.SerialException, OSError, termios.error) as exc:
            raise port_error(self.port_name, exc) from None

    def close(self) -> None:
        """Close the port (no error if it is gone already)."""
        if self._port.is_open:
            try:
                self._port.closePort()
            except (serial.SerialException, OSError, termios.error):
                self._port.is_open = False

    @property
    def is_open(self) -> bool:
        """Whether the port is open."""
        return bool(self._port.is_open)

    # -- transactions -----------------------------------------------------------------------

    def ping(self, servo_id: int) -> int:
        """The servo's model number; `ArenaError(SERVO_TIMEOUT)` if it does not answer."""
        model, result, _ = self._call(self._handler.ping, self._port, servo_id)
        self._check(result, servo_id, "ping")
        return int(model)

    def read(self, servo_id: int, register: reg.Register) -> int:
        """One register of one servo."""
        data, result, _ = self._call(
            self._handler.readTxRx, self._port, servo_id, register.address, register.size
        )
        self._check(result, servo_id, f"read {register.name}")
        return register.decode(bytes(data))

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

    def sync_write(self, register: reg.Register, values: Mapping[int, int]) -> None:
        """Write the same register of several servos in one packet (no answer)."""
        if not values:
            return
        params: list[int] = []
        for servo_id, value in values.items():
            params.append(servo_id)
            params.extend(register.encode(value))
        result = self._call(
            self._handler.syncWriteTxOnly,
            self._port,
            register.address,
            register.size,
            params,
            len(params),
        )
        self._check(result, reg.BROADCAST_ID, f"sync write {register.name}")

    def sync_read(self, address: int, length: int, servo_ids: Sequence[int]) -> SyncReadResult:
        """Read the same bytes of several servos in one request; see `SyncReadResult`."""
        ids = list(servo_ids)
        result = self._call(self._handler.syncReadTx, self._port, address, length, ids, len(ids))
        self._check(result, reg.BROADCAST_ID, "sync read")
        got = SyncReadResult()
        wanted = set(ids)
        while wanted:
            packet, outcome = self._call(self._handler.rxPacket, self._port)
            if outcome == sdk.COMM_SUCCESS:
                servo_id = packet[2]
                if servo_id in wanted:
                    wanted.discard(servo_id)
                    got.errors[servo_id] = packet[4]
                    got.data[servo_id] = bytes(packet[5 : 5 + length])
                continue
            if outcome == sdk.COMM_RX_CORRUPT and len(packet) >= 6 and packet[2] in wanted:
                wanted.discard(packet[2])  # a whole frame with a bad checksum: go on
                got.corrupt.append(packet[2])
                continue
            break  # timeout: whoever has not answered by now is missing
        got.missing = [sid for sid in ids if sid in wanted]
        self._port.is_using = False
        return got

    def sync_read_register(
        self, register: reg.Register, servo_ids: Sequence[int]
    ) -> tuple[dict[int, int], SyncReadResult]:
        """One register of several servos, decoded; and the raw result."""
        got = self.sync_read(register.address, register.size, servo_ids)
        return {sid: register.decode(data) for sid, data in got.data.items()}, got

    # -- the family-neutral interface (`arena.servo.interface.ServoBus`) ----------------------

    @property
    def family(self) -> ServoFamily:
        """Feetech's."""
        return FEETECH

    def prepare(self, servo_ids: Sequence[int]) -> None:
        """Nothing to do: an STS3215 follows position goals as it comes."""

    def read_positions(self, servo_ids: Sequence[int]) -> tuple[dict[int, int], SyncReadResult]:
        """Present positions of several servos in one request; and what came back."""
        return self.sync_read_register(reg.PRESENT_POSITION, servo_ids)

    def read_telemetry(self, servo_ids: Sequence[int]) -> tuple[Telemetry, SyncReadResult]:
        """Present_Position to Present_Temperature in one request, decoded."""
        result = self.sync_read(reg.TELEMETRY_START, reg.TELEMETRY_SIZE, servo_ids)

        def field_of(register: reg.Register, data: bytes) -> int:
            start = register.address - reg.TELEMETRY_START
            return register.decode(data[start : start + register.size])

        data = {sid: d for sid, d in result.data.items() if len(d) >= reg.TELEMETRY_SIZE}
        telemetry = Telemetry(
            positions={sid: field_of(reg.PRESENT_POSITION, d) for sid, d in data.items()},
            temperatures={sid: field_of(reg.PRESENT_TEMPERATURE, d) for sid, d in data.items()},
            loads={sid: abs(field_of(reg.PRESENT_LOAD, d)) for sid, d in data.items()},
            voltages={sid: field_of(reg.PRESENT_VOLTAGE, d) / 10 for sid, d in data.items()},
        )
        return telemetry, result

    def write_goals(self, goals: Mapping[int, int]) -> None:
        """Goal_Position of several servos in one packet."""
        self.sync_write(reg.GOAL_POSITION, goals)

    def set_torque(self, servo_ids: Sequence[int], *, on: bool) -> None:
        """Torque_Enable of every servo named."""
        self.sync_write(reg.TORQUE_ENABLE, dict.fromkeys(servo_ids, 1 if on else 0))

    def set_speed(self, servo_ids: Sequence[int], steps_per_second: int) -> None:
        """Goal_Velocity (steps/s) of every servo named."""
        self.sync_write(reg.GOAL_VELOCITY, dict.fromkeys(servo_ids, steps_per_second))

    def read_homings(self, servo_ids: Sequence[int]) -> dict[int, int]:
        """Each servo's Homing_Offset register."""
        return {sid: self.read(sid, reg.HOMING_OFFSET) for sid in servo_ids}

    def write_homing(self, servo_id: int, value: int) -> None:
        """Homing_Offset into EEPROM: the lock opened for the write and closed after."""
        self.write(servo_id, reg.LOCK, 0)
        self.write(servo_id, reg.HOMING_OFFSET, value)
        self.write(servo_id, reg.LOCK, 1)

    def _call(self, method: Any, *args: Any) -> Any:
        try:
            return method(*args)
        except (serial.SerialException, OSError, TypeError, termios.error) as exc:
            # TypeError: the SDK touches `ser` after it was closed under it.
            self._port.is_using = False
            raise BusError(
                ErrorCode.PORT_DISCONNECTED,
                f"The servo bus on {self.port_name} stopped working ({exc}); "
                "check the USB cable and the servo power supply.",
            ) from None

    def _check(self, result: int, servo_id: int, what: str) -> None:
        if result == sdk.COMM_SUCCESS:
            return
        if result == sdk.COMM_RX_TIMEOUT:
            raise ArenaError(ErrorCode.SERVO_TIMEOUT, f"Servo {servo_id} did not answer ({what}).")
        if result == sdk.COMM_RX_CORRUPT:
            raise ArenaError(
                ErrorCode.SERVO_CORRUPT, f"Servo {servo_id} sent a garbled answer ({what})."
            )
        raise BusError(
            ErrorCode.PORT_DISCONNECTED,
            f"{what} on {self.port_name} failed: {self._handler.getTxRxResult(result)}",
        )


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
