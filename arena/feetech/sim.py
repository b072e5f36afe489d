"""A simulated STS3215 bus, without I/O: servos with register files and a motion model.

`SimBus.handle(packet, now)` takes one instruction packet and returns the status packets the
servos would answer with, in order. Time is passed in (seconds, any monotonic origin), so the
motion model is deterministic under test. `arena.servo.sim_pty` puts a `SimBus` on a pty.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from arena.feetech import registers as reg
from arena.feetech.bus import FEETECH
from arena.feetech.packets import Corrupt, Instruction, Packet, PacketParser, encode
from arena.feetech.registers import ErrorBit
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

MAX_SPEED = 3400.0  # steps/s at Goal_Velocity 0 (about 300 deg/s, the STS3215 at 12 V)
ACCELERATION_UNIT = 100.0  # steps/s^2 per unit of the Acceleration register
#: Present_Load and Torque_Limit at full torque (tenths of a percent).
FULL_LOAD = 1000
#: Present_Current at full torque (6.5 mA units: the STS3215's 2.7 A stall current at 12 V).
STALL_CURRENT = 415


@dataclass
class SimServo(SimServoBase):
    """One servo: a register file, where it physically is, and what it is doing."""

    servo_id: int
    actual: float = reg.CENTER_STEP  # physical position in steps (before Homing_Offset)
    voltage: float = 12.0
    temperature: float = AMBIENT_C
    heating: float = HEATING_C_PER_S
    cooling: float = COOLING_PER_S
    overload_after: float = OVERLOAD_AFTER_S
    obstacle: Obstacle | None = None
    hand: float | None = None
    load: float = 0.0
    faults: ServoFaults = field(default_factory=ServoFaults)
    memory: bytearray = field(default_factory=lambda: bytearray(reg.MEMORY_SIZE))
    velocity: float = 0.0
    stall_time: float = 0.0
    pending: tuple[int, bytes] | None = None  # REG_WRITE waiting for ACTION
    last_update: float | None = None

    def __post_init__(self) -> None:
        defaults = {
            reg.MODEL_NUMBER: reg.STS3215_MODEL,
            reg.ID: self.servo_id,
            reg.MIN_POSITION_LIMIT: 0,
            reg.MAX_POSITION_LIMIT: reg.MAX_STEP,
            reg.MAX_TEMPERATURE: 70,
            reg.MAX_TORQUE: FULL_LOAD,
            reg.TORQUE_LIMIT: FULL_LOAD,
            reg.LOCK: 1,
        }
        for register, value in defaults.items():
            self.poke(register, value)
        self.poke(reg.GOAL_POSITION, self.present)
        self._refresh()

    # -- registers ----------------------------------------------------------------------------

    def write(self, address: int, data: bytes) -> None:
        """A bus write: read-only bytes are kept; EEPROM bytes only change while unlocked."""
        locked = self.peek(reg.LOCK) != 0
        for offset, byte in enumerate(data):
            register = _REGISTER_AT.get(address + offset)
            if register is None or address + offset >= reg.MEMORY_SIZE:
                continue
            if not register.writable or (register.eeprom and locked):
                continue
            self.memory[address + offset] = byte
        if self.peek(reg.TORQUE_ENABLE) == 0:
            self.stall_time = 0.0

    # -- physics ------------------------------------------------------------------------------

    @property
    def homing(self) -> int:
        """The Homing_Offset register."""
        return self.peek(reg.HOMING_OFFSET)

    @property
    def present(self) -> int:
        """Present position as the servo reports it (steps, 0..4095)."""
        return round(self.actual - self.homing) % reg.STEPS_PER_TURN

    def move_by_hand(self, present: float) -> None:
        """Someone moves the horn (torque off) so that it reads `present`."""
        self.actual = (present + self.homing) % reg.STEPS_PER_TURN
        self.velocity = 0.0
        self._refresh()

    @property
    def present_position(self) -> float:
        """Where the horn is in present steps (unrounded)."""
        return (self.actual - self.homing) % reg.STEPS_PER_TURN

    def load_cap(self) -> float:
        """Torque_Limit (tenths of a percent of full torque) is the most it gives."""
        return max(0.0, min(1.0, self.peek(reg.TORQUE_LIMIT) / FULL_LOAD))

    def _step(self, dt: float) -> None:
        torque = self.peek(reg.TORQUE_ENABLE) != 0
        # The servo works in its own frame (after Homing_Offset), within its position limits:
        # a goal never makes it turn across that frame's ends.
        goal = self.peek(reg.GOAL_POSITION)
        goal = max(self.peek(reg.MIN_POSITION_LIMIT), min(self.peek(reg.MAX_POSITION_LIMIT), goal))
        error = goal - self.present_position
        wants_to_move = torque and abs(error) > 0.5
        previous, self.velocity, self.load = self.velocity, 0.0, 0.0
        if wants_to_move and (self.faults.stalled or self.pushing(error)):
            self.load = self.push_load(error)
        elif wants_to_move and self.load_cap() > 0:
            self._move(error, dt, previous)
        self._protect(dt)
        self.heat(dt)

    def _move(self, error: float, dt: float, previous: float) -> None:
        speed = abs(self.peek(reg.GOAL_VELOCITY)) or MAX_SPEED
        accel = self.peek(reg.ACCELERATION) * ACCELERATION_UNIT
        wanted = math.copysign(min(speed, abs(error) / dt), error)
        if accel:
            change = max(-accel * dt, min(accel * dt, wanted - previous))
            wanted = previous + change
        self.actual += self.move_toward(error, wanted * dt, wanted, MAX_SPEED)

    def _protect(self, dt: float) -> None:
        # Tripped, it releases the horn and shows the overload bit until torque is written.
        if self.overload_tripped(dt):
            self.poke(reg.TORQUE_ENABLE, 0)

    def _refresh(self) -> None:
        self.poke(reg.PRESENT_POSITION, self.present)
        self.poke(reg.PRESENT_VELOCITY, round(self.velocity))
        self.poke(reg.PRESENT_LOAD, round(self.load * FULL_LOAD))
        self.poke(reg.PRESENT_CURRENT, round(self.load * STALL_CURRENT))
        self.poke(reg.PRESENT_VOLTAGE, round(self.voltage * 10))
        self.poke(reg.PRESENT_TEMPERATURE, max(0, min(255, round(self.temperature))))
        self.poke(reg.MOVING, 1 if self.velocity else 0)
        self.poke(reg.STATUS, self.error_byte)

    @property
    def error_byte(self) -> int:
        """The error bits of its status packets."""
        bits = ErrorBit(self.faults.error_bits)
        if self.temperature >= self.peek(reg.MAX_TEMPERATURE):
            bits |= ErrorBit.OVERHEAT
        if self.stall_time >= self.overload_after:
            bits |= ErrorBit.OVERLOAD
        if not 4.5 <= self.voltage <= 14.0:
            bits |= ErrorBit.VOLTAGE
        return int(bits)


class SimBus:
    """Servos on one bus, answering instruction packets."""

    family = FEETECH

    def __init__(self, servo_ids: tuple[int, ...] = (1, 2, 3, 4, 5, 6)) -> None:
        self.servos = {sid: SimServo(sid) for sid in servo_ids}
        self.corrupt_requests = 0
        self.handled = 0
        #: When a list: every write as (time, servo id, address, bytes), for latency benchmarks.
        self.write_log: list[tuple[float, int, int, bytes]] | None = None
        self._now = 0.0

    def servo(self, servo_id: int) -> SimServo:
        """The servo with that id."""
        return self.servos[servo_id]

    def advance(self, now: float) -> None:
        """Run every servo's model up to `now`."""
        for servo in self.servos.values():
            servo.advance(now)

    def parser(self) -> PacketParser:
        """A parser for the packets sent to this bus."""
        return PacketParser()

    def handle(self, packet: Packet | Corrupt, now: float) -> list[Reply]:
        """Carry out one instruction; the replies, in the order the servos send them. A frame
        with a bad checksum is counted and gets no answer."""
        if isinstance(packet, Corrupt):
            self.corrupt_requests += 1
            return []
        self.handled += 1
        self._now = now
        self.advance(now)
        params = packet.params
        try:
            code = Instruction(packet.code)
        except ValueError:
            return []  # servos ignore instructions they do not know
        if code is Instruction.SYNC_WRITE:
            self._sync_write(params)
            return []
        if code is Instruction.SYNC_READ:
            if len(params) < 2:
                return []
            address, length = params[0], params[1]
            return [
                self._status(servo, servo.read(address, length))
                for sid in params[2:]
                if (servo := self.servos.get(sid)) is not None
            ]
        if packet.servo_id == reg.BROADCAST_ID:
            for servo in self.servos.values():
                self._execute(servo, code, params)
            return []
        servo = self.servos.get(packet.servo_id)
        if servo is None:
            return []
        data = self._execute(servo, code, params)
        return [self._status(servo, data or b"")]

    def _execute(self, servo: SimServo, code: Instruction, params: bytes) -> bytes | None:
        if code is Instruction.READ and len(params) >= 2:
            return servo.read(params[0], params[1])
        if code is Instruction.WRITE and params:
            self._log(servo.servo_id, params[0], params[1:])
            servo.write(params[0], params[1:])
        elif code is Instruction.REG_WRITE and params:
            servo.pending = (params[0], params[1:])
        elif code is Instruction.ACTION and servo.pending is not None:
            servo.write(*servo.pending)
            servo.pending = None
        return None

    def _sync_write(self, params: bytes) -> None:
        if len(params) < 2:
            return
        address, length = params[0], params[1]
        body = params[2:]
        for start in range(0, len(body) - length, length + 1):
            servo = self.servos.get(body[start])
            if servo is not None:
                self._log(servo.servo_id, address, body[start + 1 : start + 1 + length])
                servo.write(address, body[start + 1 : start + 1 + length])

    def _log(self, servo_id: int, address: int, data: bytes) -> None:
        if self.write_log is not None:
            self.write_log.append((self._now, servo_id, address, bytes(data)))

    def _status(self, servo: SimServo, data: bytes) -> Reply:
        faults = servo.faults
        if faults.silent:
            return Reply(b"", 0.0)
        if faults.drop > 0:
            faults.drop -= 1
            return Reply(b"", 0.0)
        frame = encode(servo.servo_id, servo.error_byte, data)
        if faults.corrupt:
            frame = frame[:-1] + bytes(((frame[-1] + 1) & 0xFF,))
        delay = faults.late + servo.peek(reg.RETURN_DELAY) * 2e-6
        return Reply(frame, delay, late=faults.late > 0)


_REGISTER_AT = register_at(reg.REGISTERS)
