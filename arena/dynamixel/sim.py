"""A simulated Dynamixel X-series bus (Protocol 2.0), without I/O: servos with control tables
and a motion model, as `dynamixel_sdk` and LeRobot's `DynamixelMotorsBus` see real ones.

`SimBus.handle(packet, now)` takes one instruction packet and returns the status packets the
servos answer with, in order. As on the real servos: `present = actual + Homing_Offset` (many
turns, signed 32 bits); a write to EEPROM (below address 64) while torque is on, or to a
read-only register, is refused with an access error and changes nothing; torque going on holds the
servo where it is (goal = present); in position mode a goal is held within
Min/Max_Position_Limit. `arena.servo.sim_pty` puts a `SimBus` on a pty.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

from arena.dynamixel import registers as reg
from arena.dynamixel.bus import DYNAMIXEL
from arena.dynamixel.packets import (
    ALERT,
    Corrupt,
    Instruction,
    Packet,
    PacketParser,
    StatusError,
    encode_status,
)
from arena.servo.interface import CENTER_STEP, MAX_STEP, STEPS_PER_TURN
from arena.servo.sim_pty import (
    AMBIENT_C,
    COOLING_PER_S,
    HEATING_C_PER_S,
    OVERLOAD_AFTER_S,
    Obstacle,
    Reply,
    ServoFaults,
    SimServoBase,
    register_at,
)

MAX_SPEED = 4000.0  # steps/s at Profile_Velocity 0 (about 58 rpm, the XL430-W250 at 12 V)
#: Present_Load (tenths of a percent) at full torque, of servos that read no current (XL430).
FULL_LOAD = 1000
#: Per model: supply voltage (V), Velocity_Limit, Temperature_Limit, Current_Limit (mA, 0: the
#: model reads no current, its address 126 is Present_Load). A current-sensing servo's full
#: torque is at its shipped Current_Limit.
MODEL_DEFAULTS: dict[int, tuple[float, int, int, int]] = {
    reg.MODELS["xl430-w250"]: (12.0, 265, 72, 0),
    reg.MODELS["xl330-m288"]: (5.0, 445, 70, 1750),
    reg.MODELS["xl330-m077"]: (5.0, 1023, 70, 1750),
}


def _steps_per_second(profile_velocity: int) -> float:
    return profile_velocity * reg.RPM_PER_UNIT / 60 * STEPS_PER_TURN


@dataclass
class SimServo(SimServoBase):
    """One servo: a control table, where its horn physically is, and what it is doing."""

    servo_id: int
    model: int = reg.MODELS["xl430-w250"]
    actual: float = CENTER_STEP  # physical position in steps, before drive mode and homing
    faults: ServoFaults = field(default_factory=ServoFaults)
    memory: bytearray = field(default_factory=lambda: bytearray(reg.MEMORY_SIZE))
    temperature: float = AMBIENT_C
    heating: float = HEATING_C_PER_S
    cooling: float = COOLING_PER_S
    overload_after: float = OVERLOAD_AFTER_S
    obstacle: Obstacle | None = None
    hand: float | None = None
    load: float = 0.0
    stall_time: float = 0.0
    overloaded: bool = False  # the overload error, until torque is written on again
    velocity: float = 0.0  # steps/s, in the servo's frame
    pending: tuple[int, bytes] | None = None  # REG_WRITE waiting for ACTION
    last_update: float | None = None
    torque_enables: int = 0  # times torque went on (tests: "before any torque")

    def __post_init__(self) -> None:
        volts, velocity_limit, temperature_limit, current_limit = MODEL_DEFAULTS.get(
            self.model, (12.0, 265, 72, 0)
        )
        self.voltage = volts
        self.full_current = current_limit  # mA at full torque (0: reads Present_Load)
        defaults = {
            reg.MODEL_NUMBER: self.model,
            reg.FIRMWARE_VERSION: 52,
            reg.ID: self.servo_id,
            reg.BAUD_RATE: reg.BAUD_RATES[1_000_000],
            reg.RETURN_DELAY_TIME: 250,  # 500 us, as they ship (LeRobot writes 0)
            reg.OPERATING_MODE: reg.OperatingMode.POSITION,
            reg.PROTOCOL_TYPE: 2,
            reg.TEMPERATURE_LIMIT: temperature_limit,
            reg.MAX_VOLTAGE_LIMIT: 140 if volts > 6 else 70,
            reg.MIN_VOLTAGE_LIMIT: 60 if volts > 6 else 35,
            reg.CURRENT_LIMIT: current_limit,
            reg.GOAL_CURRENT: current_limit,  # as at power-up: the limit
            reg.VELOCITY_LIMIT: velocity_limit,
            reg.MAX_POSITION_LIMIT: MAX_STEP,
            reg.MIN_POSITION_LIMIT: 0,
            reg.STATUS_RETURN_LEVEL: 2,
            reg.POSITION_P_GAIN: 800,
        }
        for register, value in defaults.items():
            self.poke(register, value)
        self.poke(reg.GOAL_POSITION, self.present)
        self._refresh()

    # -- the control table --------------------------------------------------------------------

    def write(self, address: int, data: bytes) -> int:
        """A bus write, checked whole first: the status error number (0: written)."""
        torque = self.peek(reg.TORQUE_ENABLE) != 0
        for offset in range(len(data)):
            register = _REGISTER_AT.get(address + offset)
            if register is None:
                continue
            if not register.writable or (register.eeprom and torque):
                return StatusError.ACCESS
        for offset, byte in enumerate(data):
            if address + offset in _REGISTER_AT:
                self.memory[address + offset] = byte
        if not torque and self.peek(reg.TORQUE_ENABLE):
            self.poke(reg.GOAL_POSITION, self.present)  # torque on holds where it is
            self.torque_enables += 1
            self.overloaded = False
            self.stall_time = 0.0
        return StatusError.NONE

    # -- physics ------------------------------------------------------------------------------

    @property
    def _reversed(self) -> bool:
        return bool(self.peek(reg.DRIVE_MODE) & 1)

    @property
    def _position(self) -> float:
        """Where the horn is in the servo's frame (drive mode and homing applied)."""
        turned = MAX_STEP - self.actual if self._reversed else self.actual
        return turned + self.peek(reg.HOMING_OFFSET)

    @property
    def present(self) -> int:
        """Present position as the servo reports it (steps, signed, many turns)."""
        return round(self._position)

    def move_by_hand(self, present: float) -> None:
        """Someone moves the horn (torque off) so that it reads `present`."""
        turned = present - self.peek(reg.HOMING_OFFSET)
        self.actual = MAX_STEP - turned if self._reversed else turned
        self.velocity = 0.0
        self._refresh()

    @property
    def present_position(self) -> float:
        """Where the horn is in present steps (unrounded)."""
        return self._position

    def load_cap(self) -> float:
        """A current-sensing servo gives at most its Current_Limit, and in current-based
        position mode at most its Goal_Current; one that reads no current, full torque."""
        if not self.full_current:
            return 1.0
        cap = self.peek(reg.CURRENT_LIMIT)
        if self.peek(reg.OPERATING_MODE) == reg.OperatingMode.CURRENT_POSITION:
            cap = min(cap, abs(self.peek(reg.GOAL_CURRENT)))
        return max(0.0, min(1.0, cap / self.full_current))

    def _step(self, dt: float) -> None:
        mode = self.peek(reg.OPERATING_MODE)
        torque = self.peek(reg.TORQUE_ENABLE) != 0
        goal = float(self.peek(reg.GOAL_POSITION))
        if mode == reg.OperatingMode.POSITION:
            low, high = self.peek(reg.MIN_POSITION_LIMIT), self.peek(reg.MAX_POSITION_LIMIT)
            goal = max(low, min(high, goal))
        error = goal - self._position
        wants_to_move = torque and mode in reg.POSITION_MODES and abs(error) > 0.5
        self.velocity = 0.0
        self.load = 0.0
        if wants_to_move and (self.faults.stalled or self.pushing(error)):
            self.load = self.push_load(error)
        elif wants_to_move and self.load_cap() > 0:
            self._move(error, dt)
        self._protect(dt)
        self.heat(dt)

    def _move(self, error: float, dt: float) -> None:
        profile = self.peek(reg.PROFILE_VELOCITY)
        speed = _steps_per_second(profile) if profile else MAX_SPEED
        velocity = math.copysign(min(speed, abs(error) / dt), error)
        moved = self.move_toward(error, velocity * dt, velocity, MAX_SPEED)
        self.actual += -moved if self._reversed else moved

    def _protect(self, dt: float) -> None:
        # Tripped, it sets the overload error and drops torque (the X series' Shutdown).
        if self.overload_tripped(dt):
            self.overloaded = True
            self.poke(reg.TORQUE_ENABLE, 0)

    def _refresh(self) -> None:
        self.poke(reg.PRESENT_POSITION, self.present)
        rpm_units = round(self.velocity * 60 / STEPS_PER_TURN / reg.RPM_PER_UNIT)
        self.poke(reg.PRESENT_VELOCITY, rpm_units)
        # Present_Current (mA), or Present_Load (tenths of a percent) where no current is read.
        self.poke(reg.PRESENT_CURRENT, round(self.load * (self.full_current or FULL_LOAD)))
        self.poke(reg.PRESENT_INPUT_VOLTAGE, round(self.voltage * 10))
        self.poke(reg.PRESENT_TEMPERATURE, max(0, min(255, round(self.temperature))))
        self.poke(reg.MOVING, 1 if self.velocity else 0)
        hardware = 0
        for bit, fault in reg.FAULTS.items():
            if self.faults.error_bits & fault:
                hardware |= bit
        if self.overloaded:
            hardware |= reg.HardwareError.OVERLOAD
        if self.temperature >= self.peek(reg.TEMPERATURE_LIMIT):
            hardware |= reg.HardwareError.OVERHEATING
        self.poke(reg.HARDWARE_ERROR_STATUS, hardware)


class SimBus:
    """Dynamixel servos on one bus, answering Protocol 2.0 instruction packets. `models`: the
    model number of each servo by id (the Koch follower's by default)."""

    family = DYNAMIXEL

    def __init__(self, models: Mapping[int, int] | None = None) -> None:
        if models is None:
            xl430, xl330 = reg.MODELS["xl430-w250"], reg.MODELS["xl330-m288"]
            models = {1: xl430, 2: xl430, 3: xl330, 4: xl330, 5: xl330, 6: xl330}
        self.servos = {sid: SimServo(sid, model) for sid, model in models.items()}
        self.corrupt_requests = 0
        self.handled = 0

    def servo(self, servo_id: int) -> SimServo:
        """The servo with that id."""
        return self.servos[servo_id]

    def parser(self) -> PacketParser:
        """A parser for the packets sent to this bus."""
        return PacketParser()

    def advance(self, now: float) -> None:
        """Run every servo's model up to `now`."""
        for servo in self.servos.values():
            servo.advance(now)

    def handle(self, packet: Packet | Corrupt, now: float) -> list[Reply]:
        """Carry out one instruction; the replies, in the order the servos send them. A frame
        with a bad CRC is counted and gets no answer."""
        if isinstance(packet, Corrupt):
            self.corrupt_requests += 1
            return []
        self.handled += 1
        self.advance(now)
        params = packet.params
        code = packet.instruction
        if code == Instruction.SYNC_WRITE:
            self._sync_write(params)
            return []
        if code == Instruction.SYNC_READ:
            if len(params) < 4:
                return []
            address, length = _word(params, 0), _word(params, 2)
            return [
                self._status(servo, 0, servo.read(address, length))
                for sid in params[4:]
                if (servo := self.servos.get(sid)) is not None
            ]
        if packet.servo_id == reg.BROADCAST_ID:
            if code == Instruction.PING:  # every servo answers, lowest id first
                return [self._status(s, 0, self._ping(s)) for _, s in sorted(self.servos.items())]
            for servo in self.servos.values():
                self._execute(servo, code, params)
            return []
        servo = self.servos.get(packet.servo_id)
        if servo is None:
            return []
        error, data = self._execute(servo, code, params)
        return [self._status(servo, error, data)]

    def _execute(self, servo: SimServo, code: int, params: bytes) -> tuple[int, bytes]:
        if code == Instruction.PING:
            return 0, self._ping(servo)
        if code == Instruction.READ and len(params) >= 4:
            return 0, servo.read(_word(params, 0), _word(params, 2))
        if code == Instruction.WRITE and len(params) >= 2:
            return servo.write(_word(params, 0), params[2:]), b""
        if code == Instruction.REG_WRITE and len(params) >= 2:
            servo.pending = (_word(params, 0), params[2:])
            return 0, b""
        if code == Instruction.ACTION and servo.pending is not None:
            error = servo.write(*servo.pending)
            servo.pending = None
            return error, b""
        if code in (Instruction.REBOOT, Instruction.ACTION):
            return 0, b""
        return StatusError.INSTRUCTION, b""

    @staticmethod
    def _ping(servo: SimServo) -> bytes:
        return reg.MODEL_NUMBER.encode(servo.model) + bytes((servo.peek(reg.FIRMWARE_VERSION),))

    def _sync_write(self, params: bytes) -> None:
        if len(params) < 4:
            return
        address, length = _word(params, 0), _word(params, 2)
        body = params[4:]
        for start in range(0, len(body) - length, length + 1):
            servo = self.servos.get(body[start])
            if servo is not None:
                servo.write(address, body[start + 1 : start + 1 + length])

    def _status(self, servo: SimServo, error: int, data: bytes) -> Reply:
        faults = servo.faults
        if faults.silent:
            return Reply(b"", 0.0)
        if faults.drop > 0:
            faults.drop -= 1
            return Reply(b"", 0.0)
        if servo.peek(reg.HARDWARE_ERROR_STATUS):
            error |= ALERT
        frame = encode_status(servo.servo_id, error, data)
        if faults.corrupt:
            frame = frame[:-1] + bytes(((frame[-1] + 1) & 0xFF,))
        delay = faults.late + servo.peek(reg.RETURN_DELAY_TIME) * 2e-6
        return Reply(frame, delay, late=faults.late > 0)


def _word(data: bytes, at: int) -> int:
    return int.from_bytes(data[at : at + 2], "little")


_REGISTER_AT = register_at(reg.REGISTERS)
