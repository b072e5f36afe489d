"""The STS3215 register map and the value encodings the servo uses.

Addresses and sizes from the servo's memory table (see the so-arm100 robot notes). Multi-byte
registers are little-endian; signed registers use sign-magnitude with the sign in a fixed bit.
"""

from __future__ import annotations

from dataclasses import dataclass

from arena.servo.interface import CENTER_STEP as CENTER_STEP
from arena.servo.interface import MAX_STEP as MAX_STEP
from arena.servo.interface import STEPS_PER_TURN as STEPS_PER_TURN
from arena.servo.interface import FaultBit

STS3215_MODEL = 777
BROADCAST_ID = 0xFE
HOMING_OFFSET_LIMIT = 2047  # sign bit 11: magnitude fits in 11 bits


@dataclass(frozen=True, slots=True)
class Register:
    """One register: address, size in bytes, sign bit (None: unsigned), EEPROM or SRAM."""

    name: str
    address: int
    size: int
    sign_bit: int | None = None
    eeprom: bool = False
    writable: bool = True

    def encode(self, value: int) -> bytes:
        """The register's bytes for `value` (sign-magnitude where signed)."""
        return encode_value(value, self.size, self.sign_bit)

    def decode(self, data: bytes) -> int:
        """The value stored in `data` (the register's bytes)."""
        return decode_value(data, self.sign_bit)


MODEL_NUMBER = Register("Model_Number", 3, 2, eeprom=True, writable=False)
ID = Register("ID", 5, 1, eeprom=True)
BAUD_RATE = Register("Baud_Rate", 6, 1, eeprom=True)
RETURN_DELAY = Register("Return_Delay", 7, 1, eeprom=True)
MIN_POSITION_LIMIT = Register("Min_Position_Limit", 9, 2, eeprom=True)
MAX_POSITION_LIMIT = Register("Max_Position_Limit", 11, 2, eeprom=True)
MAX_TEMPERATURE = Register("Max_Temperature", 13, 1, eeprom=True)
MAX_TORQUE = Register("Max_Torque", 16, 2, eeprom=True)
HOMING_OFFSET = Register("Homing_Offset", 31, 2, sign_bit=11, eeprom=True)
OPERATING_MODE = Register("Operating_Mode", 33, 1, eeprom=True)
TORQUE_ENABLE = Register("Torque_Enable", 40, 1)
ACCELERATION = Register("Acceleration", 41, 1)
GOAL_POSITION = Register("Goal_Position", 42, 2, sign_bit=15)
GOAL_TIME = Register("Goal_Time", 44, 2)
GOAL_VELOCITY = Register("Goal_Velocity", 46, 2, sign_bit=15)
TORQUE_LIMIT = Register("Torque_Limit", 48, 2)
LOCK = Register("Lock", 55, 1)
PRESENT_POSITION = Register("Present_Position", 56, 2, sign_bit=15, writable=False)
PRESENT_VELOCITY = Register("Present_Velocity", 58, 2, sign_bit=15, writable=False)
PRESENT_LOAD = Register("Present_Load", 60, 2, sign_bit=10, writable=False)
PRESENT_VOLTAGE = Register("Present_Voltage", 62, 1, writable=False)
PRESENT_TEMPERATURE = Register("Present_Temperature", 63, 1, writable=False)
STATUS = Register("Status", 65, 1, writable=False)
MOVING = Register("Moving", 66, 1, writable=False)
PRESENT_CURRENT = Register("Present_Current", 69, 2, sign_bit=15, writable=False)

REGISTERS: tuple[Register, ...] = (
    MODEL_NUMBER,
    ID,
    BAUD_RATE,
    RETURN_DELAY,
    MIN_POSITION_LIMIT,
    MAX_POSITION_LIMIT,
    MAX_TEMPERATURE,
    MAX_TORQUE,
    HOMING_OFFSET,
    OPERATING_MODE,
    TORQUE_ENABLE,
    ACCELERATION,
    GOAL_POSITION,
    GOAL_TIME,
    GOAL_VELOCITY,
    TORQUE_LIMIT,
    LOCK,
    PRESENT_POSITION,
    PRESENT_VELOCITY,
    PRESENT_LOAD,
    PRESENT_VOLTAGE,
    PRESENT_TEMPERATURE,
    STATUS,
    MOVING,
    PRESENT_CURRENT,
)
MEMORY_SIZE = 71  # bytes of the register file, up to and including Present_Current
# The block the telemetry read covers: position, velocity, load, voltage, temperature.
TELEMETRY_START = PRESENT_POSITION.address
TELEMETRY_SIZE = PRESENT_TEMPERATURE.address + 1 - TELEMETRY_START


#: Bits of a status packet's error byte: the STS3215's are the neutral fault flags, bit for bit.
ErrorBit = FaultBit


def encode_value(value: int, size: int, sign_bit: int | None = None) -> bytes:
    """Little-endian bytes of `value`; negative values as sign-magnitude when `sign_bit` is set."""
    if value < 0:
        if sign_bit is None:
            raise ValueError(f"{value} is negative but the register is unsigned")
        magnitude = -value
        if magnitude >= 1 << sign_bit:
            raise ValueError(f"{value} does not fit below sign bit {sign_bit}")
        value = magnitude | (1 << sign_bit)
    if value >= 1 << (8 * size):
        raise ValueError(f"{value} does not fit in {size} bytes")
    return value.to_bytes(size, "little")


def decode_value(data: bytes, sign_bit: int | None = None) -> int:
    """The integer in little-endian `data`, sign-magnitude when `sign_bit` is set."""
    raw = int.from_bytes(data, "little")
    if sign_bit is not None and raw & (1 << sign_bit):
        return -(raw & ((1 << sign_bit) - 1))
    return raw
