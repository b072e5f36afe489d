"""Talking to real Dynamixel X-series servos (Protocol 2.0) through `dynamixel_sdk` and pyserial.

A `DynamixelBus` is used from one thread only. What it does as Feetech's bus does (the port,
its traps fixed, a sync read collecting replies one by one) is `arena.servo.sdk_bus.SdkBus`.
Fault flags come from each servo's Hardware_Error_Status, read with the telemetry.
"""

from __future__ import annotations

import inspect
from collections.abc import Mapping, Sequence
from typing import Any

import dynamixel_sdk as sdk

from arena.dynamixel import registers as reg
from arena.protocol.errors import ArenaError, ErrorCode
from arena.servo.interface import ServoFamily, SyncReadResult, Telemetry
from arena.servo.ports import PortFixes
from arena.servo.sdk_bus import SdkBus, decode_telemetry

#: USB ids of the adapters Dynamixel arms come with: ROBOTIS's U2D2 (an FTDI FT232H).
ADAPTERS: dict[tuple[int, int], str] = {(0x0403, 0x6014): "U2D2"}
#: Present_Load at full torque (tenths of a percent), for models that read no current.
FULL_LOAD = 1000
_STATUS_DATA = 9  # index of a status packet's first data byte (after the error byte)


class DynamixelPort(PortFixes, sdk.PortHandler):  # type: ignore[misc]
    """The SDK's port with the traps fixed (`PortFixes`)."""


class DynamixelBus(SdkBus):
    """Dynamixel servos on one serial port. Not thread-safe: one thread owns it."""

    sdk = sdk
    port_class = DynamixelPort
    ID_AT, DATA_AT, MIN_FRAME = 4, _STATUS_DATA, 11  # FF FF FD 00 id len len 55 error data.. crc
    BROADCAST_ID = reg.BROADCAST_ID
    PRESENT_POSITION, GOAL_POSITION = reg.PRESENT_POSITION, reg.GOAL_POSITION
    TORQUE_ENABLE, HOMING_OFFSET = reg.TORQUE_ENABLE, reg.HOMING_OFFSET
    _fast: tuple[bool, ...] = ()  # (fast_option,) where the SDK (3.8) takes it
    #: Set by `prepare`: each servo's load at full torque, and those in current-based
    #: position mode (whose Goal_Current is their torque limit).
    _full_loads: dict[int, int] = {}  # noqa: RUF012 (replaced, never changed in place)
    _current_based: set[int] = set()  # noqa: RUF012

    def _new_handler(self) -> Any:
        handler = sdk.PacketHandler(2.0)
        takes_fast = "fast_option" in inspect.signature(handler.rxPacket).parameters
        self._fast = (False,) if takes_fast else ()
        return handler

    def _rx_args(self) -> tuple[Any, ...]:
        return self._fast

    @property
    def family(self) -> ServoFamily:
        """Dynamixel's."""
        return DYNAMIXEL

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

    # -- the family-neutral interface (`arena.servo.interface.ServoBus`) ----------------------

    def prepare(self, servo_ids: Sequence[int], *, limited: Sequence[int] = ()) -> None:
        """Servos in a mode that ignores position goals (velocity, current, PWM) go to position
        mode, torque off for the change; the position modes LeRobot sets (extended position,
        current-based position for the Koch's gripper) are kept. The `limited` servos go to
        current-based position mode (their torque limit is a Goal_Current, which only the
        current-based modes obey); a model that reads no current (the XL430) cannot be
        limited so and is refused. Every servo must answer, and the modes are read back after
        a change: a servo left in another mode would take the coming torque-on with the
        velocity, PWM or current goal still in its RAM."""
        self._read_full_loads(servo_ids, limited)
        modes = self._operating_modes(servo_ids)
        current = reg.OperatingMode.CURRENT_POSITION
        wanted = {
            sid: current if sid in limited else (mode if mode in reg.POSITION_MODES else None)
            for sid, mode in modes.items()
        }
        changed = {
            sid: reg.OperatingMode.POSITION if mode is None else mode
            for sid, mode in wanted.items()
        }
        changed = {sid: mode for sid, mode in changed.items() if mode != modes[sid]}
        for servo_id, mode in changed.items():
            self.write(servo_id, reg.TORQUE_ENABLE, 0)
            self.write(servo_id, reg.OPERATING_MODE, mode)
        self._current_based = {sid for sid in modes if changed.get(sid, modes[sid]) == current}
        if not changed:
            return
        stuck = {
            sid: mode
            for sid, mode in self._operating_modes(list(changed)).items()
            if mode != changed[sid]
        }
        if stuck:
            raise ArenaError(
                ErrorCode.INVALID_CONFIG,
                f"Servo(s) {sorted(stuck)} stayed in operating mode(s) {stuck} rather than "
                f"{ {sid: int(changed[sid]) for sid in sorted(stuck)} }: torque stays off. Set "
                "their Operating_Mode (3: position; 5: current-based position).",
            )

    def _read_full_loads(self, servo_ids: Sequence[int], limited: Sequence[int]) -> None:
        """Each servo's load at full torque: its Current_Limit (mA) where it reads current,
        1000 (Present_Load's tenths of a percent) where it does not; those asked to be
        limited must read current."""
        models, got = self.sync_read_register(reg.MODEL_NUMBER, servo_ids)
        limits, got_limits = self.sync_read_register(reg.CURRENT_LIMIT, servo_ids)
        silent = sorted(set(got.missing + got.corrupt + got_limits.missing + got_limits.corrupt))
        if silent:
            raise ArenaError(
                ErrorCode.SERVO_TIMEOUT,
                f"Servo(s) {silent} did not answer the read of their model and current limit: "
                "torque stays off.",
            )
        sensing = {sid for sid, model in models.items() if model in reg.CURRENT_SENSING}
        blind = sorted(sid for sid in limited if sid not in sensing)
        if blind:
            names = {v: k.upper() for k, v in reg.MODELS.items()}
            which = ", ".join(
                f"servo {sid} ({names.get(models[sid], models[sid])})" for sid in blind
            )
            raise ArenaError(
                ErrorCode.INVALID_CONFIG,
                f"A torque limit on {which}: this model reads no current, and Arena limits a "
                "Dynamixel's torque with current-based position control. Limit only joints "
                "of current-sensing models (XL330, XM430, XM540).",
            )
        self._full_loads = {
            sid: (limits[sid] if sid in sensing else FULL_LOAD) for sid in servo_ids
        }

    def set_torque_limits(self, limits: Mapping[int, float]) -> None:
        """Goal_Current, as a share of each servo's Current_Limit, of the servos in
        current-based position mode; then a limit under 100 % on any other is refused (it
        would not be obeyed; the others are written), a full one needs nothing."""
        unlimited = sorted(
            sid for sid, p in limits.items() if p < 100 and sid not in self._current_based
        )
        goals = {
            sid: max(0, min(full, round(full * p / 100)))
            for sid, p in limits.items()
            if sid in self._current_based and (full := self._full_loads.get(sid, 0)) > 0
        }
        self.sync_write(reg.GOAL_CURRENT, goals)
        if unlimited:
            raise ArenaError(
                ErrorCode.INVALID_CONFIG,
                f"Servo(s) {unlimited} cannot have their torque lowered: not in current-based "
                "position mode (attach the arm with a torqueLimit for their joints).",
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

    def read_telemetry(self, servo_ids: Sequence[int]) -> tuple[Telemetry, SyncReadResult]:
        """Present_Current to Present_Temperature in one request, then Hardware_Error_Status
        (its bits become the result's fault flags)."""
        result = self.sync_read(reg.TELEMETRY_START, reg.TELEMETRY_SIZE, servo_ids)
        telemetry = decode_telemetry(
            result,
            reg.TELEMETRY_START,
            reg.TELEMETRY_SIZE,
            position=reg.PRESENT_POSITION,
            temperature=reg.PRESENT_TEMPERATURE,
            load=reg.PRESENT_CURRENT,
            voltage=reg.PRESENT_INPUT_VOLTAGE,
            full_load=self._full_loads or FULL_LOAD,
        )
        hardware, _ = self.sync_read_register(reg.HARDWARE_ERROR_STATUS, list(telemetry.positions))
        for servo_id, bits in hardware.items():
            result.errors[servo_id] = reg.faults_of(bits)
        return telemetry, result

    def set_speed(self, servo_ids: Sequence[int], steps_per_second: int) -> None:
        """Profile_Velocity (0.229 rpm units) of every servo named."""
        units = max(1, round(steps_per_second * 60 / 4096 / reg.RPM_PER_UNIT))
        self.sync_write(reg.PROFILE_VELOCITY, dict.fromkeys(servo_ids, units))

    def write_homing(self, servo_id: int, value: int) -> None:
        """Homing_Offset into EEPROM (the servo refuses it with torque on)."""
        self.write(servo_id, reg.HOMING_OFFSET, value)


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
