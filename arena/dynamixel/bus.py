"""Talking to real Dynamixel X-series servos (Protocol 2.0) through `dynamixel_sdk` and pyserial.

A `DynamixelBus` is used from one thread only. Its port is the SDK's with the same traps fixed
as Feetech's (`arena.servo.ports.PortFixes`), and a sync read collects replies one by one so
that one silent servo does not fail the others. Fault flags come from each servo's
Hardware_Error_Status, read with the telemetry.
"""

from __future__ import annotations

import inspect
import termios
from collections.abc import Mapping, Sequence
from typing import Any

import dynamixel_sdk as sdk
import serial

from arena.dynamixel import registers as reg
from arena.protocol.errors import ArenaError, ErrorCode
from arena.servo.interface import BusError, ServoFamily, SyncReadResult, Telemetry
from arena.servo.ports import DEFAULT_TIMEOUT_MARGIN, PortFixes, port_error

#: USB ids of the adapters Dynamixel arms come with: ROBOTIS's U2D2 (an FTDI FT232H).
ADAPTERS: dict[tuple[int, int], str] = {(0x0403, 0x6014): "U2D2"}
_STATUS_DATA = 9  # index of a status packet's first data byte (after the error byte)


class DynamixelPort(PortFixes, sdk.PortHandler):  # type: ignore[misc]
    """The SDK's port with the traps fixed (`PortFixes`)."""


class DynamixelBus:
    """Dynamixel servos on one serial port. Not thread-safe: one thread owns it."""

    def __init__(
        self,
        port: str,
        baud: int = 1_000_000,
        *,
        timeout_margin: float = DEFAULT_TIMEOUT_MARGIN,
        port_handler: DynamixelPort | None = None,
    ) -> None:
        self.port_name = port
        self.baud = baud
        self._port = port_handler or DynamixelPort(port, timeout_margin)
        self._handler: Any = None
        self._fast: tuple[bool, ...] = ()  # (fast_option,) where the SDK (3.8) takes it

    @property
    def family(self) -> ServoFamily:
        """Dynamixel's."""
        return DYNAMIXEL

    # -- port -------------------------------------------------------------------------------

    def open(self) -> None:
        """Open the port; problems raise `BusError` with what to do about them."""
        self._handler = sdk.PacketHandler(2.0)
        takes_fast = "fast_option" in inspect.signature(self._handler.rxPacket).parameters
        self._fast = (False,) if takes_fast else ()
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
        """Write one register and wait for the servo's answer; a refusal (an EEPROM register
        while torque is on) is an `INVALID_CONFIG` naming it."""
        data = list(register.encode(value))
        result, error = self._call(
            self._handler.writeTxRx,
            self._port,
            servo_id,
            register.address,
            register.size,
            data,
        )
        self._check(result, servo_id, f"write {register.name}")
        if error & 0x7F:
            raise ArenaError(
                ErrorCode.INVALID_CONFIG,
                f"Servo {servo_id} refused the write of {register.name} (error {error & 0x7F}"
                f"{': torque must be off' if register.eeprom else ''}).",
            )

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
        """Read the same bytes of several servos in one request, their replies one by one."""
        ids = list(servo_ids)
        result = self._call(
            self._handler.syncReadTx, self._port, address, length, ids, len(ids), *self._fast
        )
        self._check(result, reg.BROADCAST_ID, "sync read")
        got = SyncReadResult()
        wanted = set(ids)
        while wanted:
            packet, outcome = self._call(self._handler.rxPacket, self._port, *self._fast)
            if outcome == sdk.COMM_SUCCESS:
                servo_id = packet[4]
                if servo_id in wanted:
                    wanted.discard(servo_id)
                    got.errors[servo_id] = 0  # (flags come from Hardware_Error_Status)
                    got.data[servo_id] = bytes(packet[_STATUS_DATA : _STATUS_DATA + length])
                continue
            if outcome == sdk.COMM_RX_CORRUPT and len(packet) >= 11 and packet[4] in wanted:
                wanted.discard(packet[4])  # a whole frame with a bad CRC: go on
                got.corrupt.append(packet[4])
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

    def prepare(self, servo_ids: Sequence[int]) -> None:
        """Servos in a mode that ignores position goals (velocity, current, PWM) go to position
        mode, torque off for the change; the position modes LeRobot sets (extended position,
        current-based position for the Koch's gripper) are kept. Every servo must answer, and
        the modes are read back after a change: a servo left in another mode would take the
        coming torque-on with the velocity, PWM or current goal still in its RAM."""
        modes = self._operating_modes(servo_ids)
        changed = [sid for sid, mode in modes.items() if mode not in reg.POSITION_MODES]
        for servo_id in changed:
            self.write(servo_id, reg.TORQUE_ENABLE, 0)
            self.write(servo_id, reg.OPERATING_MODE, reg.OperatingMode.POSITION)
        if not changed:
            return
        stuck = {
            sid: mode
            for sid, mode in self._operating_modes(changed).items()
            if mode not in reg.POSITION_MODES
        }
        if stuck:
            raise ArenaError(
                ErrorCode.INVALID_CONFIG,
                f"Servo(s) {sorted(stuck)} stayed in operating mode(s) {stuck} rather than a "
                "position mode: torque stays off. Set their Operating_Mode to 3 (position).",
            )

    def _operating_modes(self, servo_ids: Sequence[int]) -> dict[int, int]:
        """Every servo's Operating_Mode; `SERVO_TIMEOUT` naming any that did not answer."""
        modes, got = self.sync_read_register(reg.OPERATING_MODE, servo_ids)
        if got.missing or got.corrupt:
            raise ArenaError(
                ErrorCode.SERVO_TIMEOUT,
                f"Servo(s) {sorted(got.missing + got.corrupt)} did not answer the read of their "
                "operating mode: torque stays off.",
            )
        return modes

    def read_positions(self, servo_ids: Sequence[int]) -> tuple[dict[int, int], SyncReadResult]:
        """Present positions of several servos in one request; and what came back."""
        return self.sync_read_register(reg.PRESENT_POSITION, servo_ids)

    def read_telemetry(self, servo_ids: Sequence[int]) -> tuple[Telemetry, SyncReadResult]:
        """Present_Current to Present_Temperature in one request, then Hardware_Error_Status
        (its bits become the result's fault flags)."""
        result = self.sync_read(reg.TELEMETRY_START, reg.TELEMETRY_SIZE, servo_ids)

        def field_of(register: reg.Register, data: bytes) -> int:
            start = register.address - reg.TELEMETRY_START
            return register.decode(data[start : start + register.size])

        data = {sid: d for sid, d in result.data.items() if len(d) >= reg.TELEMETRY_SIZE}
        telemetry = Telemetry(
            positions={sid: field_of(reg.PRESENT_POSITION, d) for sid, d in data.items()},
            temperatures={sid: field_of(reg.PRESENT_TEMPERATURE, d) for sid, d in data.items()},
            loads={sid: abs(field_of(reg.PRESENT_CURRENT, d)) for sid, d in data.items()},
            voltages={sid: field_of(reg.PRESENT_INPUT_VOLTAGE, d) / 10 for sid, d in data.items()},
        )
        hardware, _ = self.sync_read_register(reg.HARDWARE_ERROR_STATUS, list(data))
        for servo_id, bits in hardware.items():
            result.errors[servo_id] = reg.faults_of(bits)
        return telemetry, result

    def write_goals(self, goals: Mapping[int, int]) -> None:
        """Goal_Position of several servos in one packet."""
        self.sync_write(reg.GOAL_POSITION, goals)

    def set_torque(self, servo_ids: Sequence[int], *, on: bool) -> None:
        """Torque_Enable of every servo named."""
        self.sync_write(reg.TORQUE_ENABLE, dict.fromkeys(servo_ids, 1 if on else 0))

    def set_speed(self, servo_ids: Sequence[int], steps_per_second: int) -> None:
        """Profile_Velocity (0.229 rpm units) of every servo named."""
        units = max(1, round(steps_per_second * 60 / 4096 / reg.RPM_PER_UNIT))
        self.sync_write(reg.PROFILE_VELOCITY, dict.fromkeys(servo_ids, units))

    def read_homings(self, servo_ids: Sequence[int]) -> dict[int, int]:
        """Each servo's Homing_Offset register."""
        return {sid: self.read(sid, reg.HOMING_OFFSET) for sid in servo_ids}

    def write_homing(self, servo_id: int, value: int) -> None:
        """Homing_Offset into EEPROM (the servo refuses it with torque on)."""
        self.write(servo_id, reg.HOMING_OFFSET, value)

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


#: ROBOTIS's Dynamixel X series (the Koch arm's XL430-W250 and XL330-M288).
DYNAMIXEL = ServoFamily(
    name="dynamixel",
    models=reg.MODELS,
    default_model="xl430-w250",
    default_baud=1_000_000,
    adapters=ADAPTERS,
    homing_sign=1,  # present = actual + Homing_Offset
    homing_limit=reg.HOMING_OFFSET_LIMIT,
    wraps=False,
    open_bus=DynamixelBus,
    port_class=DynamixelPort,
    lerobot_folders={
        "*": {"robots": ("koch_follower",), "teleoperators": ("koch_leader",)},
    },
)
