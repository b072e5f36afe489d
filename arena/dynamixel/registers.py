"""The Dynamixel X-series control table (the registers Arena and LeRobot use) and its encodings.

Addresses and sizes from ROBOTIS's X-series control table. Every multi-byte register is
little-endian; signed ones are two's complement. Addresses below 64 are EEPROM: a servo takes a
write there only while its torque is off.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

from arena.servo.interface import FaultBit

BROADCAST_ID = 0xFE
EEPROM_END = 64  # addresses below are EEPROM
HOMING_OFFSET_LIMIT = 1_044_479  # the X series' Homing_Offset range (+-)
#: Model numbers of the X-series servos LeRobot's arms use.
MODELS: dict[str, int] = {
    "xl330-m077": 1190,
    "xl330-m288": 1200,
    "xl430-w250": 1060,
    "xm430-w350": 1020,
    "xm540-w270": 1120,
    "xc430-w150": 1070,
}
#: Model numbers of the servos that read their current (Present_Current, Current_Limit and the
#: current-based modes); the others (XL430, XC430) read a Present_Load at address 126.
CURRENT_SENSING = frozenset(
    MODELS[name] for name in ("xl330-m077", "xl330-m288", "xm430-w350", "xm540-w270")
)
#: The Baud_Rate register's values.
BAUD_RATES: dict[int, int] = {
    9_600: 0,
    57_600: 1,
    115_200: 2,
    1_000_000: 3,
    2_000_000: 4,
    3_000_000: 5,
    4_000_000: 6,
}
RPM_PER_UNIT = 0.229  # Profile_Velocity and Velocity_Limit units


class OperatingMode(enum.IntEnum):
    """The Operating_Mode register: how the servo follows its goals."""

    CURRENT = 0
    VELOCITY = 1
    POSITION = 3  # one turn, within Min/Max_Position_Limit
    EXTENDED_POSITION = 4  # many turns, no limits
    CURRENT_POSITION = 5  # many turns, current-limited (LeRobot's Koch gripper)
    PWM = 16


#: Modes in which a servo goes to its Goal_Position.
POSITION_MODES = frozenset(
    {OperatingMode.POSITION, OperatingMode.EXTENDED_POSITION, OperatingMode.CURRENT_POSITION}
)


@dataclass(frozen=True, slots=True)
class Register:
    """One register: address, size in bytes, signed or not, writable or not."""

    name: str
    address: int
    size: int
    signed: bool = False
    writable: bool = True

    @property
    def eeprom(self) -> bool:
        """Whether it lives in EEPROM (written only with torque off)."""
        return self.address < EEPROM_END

    def encode(self, value: int) -> bytes:
        """The register's bytes for `value`."""
        return value.to_bytes(self.size, "little", signed=self.signed)

    def decode(self, data: bytes) -> int:
        """The value stored in `data` (the register's bytes)."""
        return int.from_bytes(data[: self.size], "little", signed=self.signed)


MODEL_NUMBER = Register("Model_Number", 0, 2, writable=False)
FIRMWARE_VERSION = Register("Firmware_Version", 6, 1, writable=False)
ID = Register("ID", 7, 1)
BAUD_RATE = Register("Baud_Rate", 8, 1)
RETURN_DELAY_TIME = Register("Return_Delay_Time", 9, 1)
DRIVE_MODE = Register("Drive_Mode", 10, 1)
OPERATING_MODE = Register("Operating_Mode", 11, 1)
PROTOCOL_TYPE = Register("Protocol_Type", 13, 1)
HOMING_OFFSET = Register("Homing_Offset", 20, 4, signed=True)
TEMPERATURE_LIMIT = Register("Temperature_Limit", 31, 1)
MAX_VOLTAGE_LIMIT = Register("Max_Voltage_Limit", 32, 2)
MIN_VOLTAGE_LIMIT = Register("Min_Voltage_Limit", 34, 2)
CURRENT_LIMIT = Register("Current_Limit", 38, 2)
VELOCITY_LIMIT = Register("Velocity_Limit", 44, 4)
MAX_POSITION_LIMIT = Register("Max_Position_Limit", 48, 4)
MIN_POSITION_LIMIT = Register("Min_Position_Limit", 52, 4)
TORQUE_ENABLE = Register("Torque_Enable", 64, 1)
LED = Register("LED", 65, 1)
STATUS_RETURN_LEVEL = Register("Status_Return_Level", 68, 1)
HARDWARE_ERROR_STATUS = Register("Hardware_Error_Status", 70, 1, writable=False)
POSITION_D_GAIN = Register("Position_D_Gain", 80, 2)
POSITION_I_GAIN = Register("Position_I_Gain", 82, 2)
POSITION_P_GAIN = Register("Position_P_Gain", 84, 2)
GOAL_CURRENT = Register("Goal_Current", 102, 2, signed=True)
GOAL_VELOCITY = Register("Goal_Velocity", 104, 4, signed=True)
PROFILE_ACCELERATION = Register("Profile_Acceleration", 108, 4)
PROFILE_VELOCITY = Register("Profile_Velocity", 112, 4)
GOAL_POSITION = Register("Goal_Position", 116, 4, signed=True)
MOVING = Register("Moving", 122, 1, writable=False)
PRESENT_CURRENT = Register("Present_Current", 126, 2, signed=True, writable=False)
PRESENT_VELOCITY = Register("Present_Velocity", 128, 4, signed=True, writable=False)
PRESENT_POSITION = Register("Present_Position", 132, 4, signed=True, writable=False)
PRESENT_INPUT_VOLTAGE = Register("Present_Input_Voltage", 144, 2, writable=False)
PRESENT_TEMPERATURE = Register("Present_Temperature", 146, 1, writable=False)

REGISTERS: tuple[Register, ...] = (
    MODEL_NUMBER,
    FIRMWARE_VERSION,
    ID,
    BAUD_RATE,
    RETURN_DELAY_TIME,
    DRIVE_MODE,
    OPERATING_MODE,
    PROTOCOL_TYPE,
    HOMING_OFFSET,
    TEMPERATURE_LIMIT,
    MAX_VOLTAGE_LIMIT,
    MIN_VOLTAGE_LIMIT,
    CURRENT_LIMIT,
    VELOCITY_LIMIT,
    MAX_POSITION_LIMIT,
    MIN_POSITION_LIMIT,
    TORQUE_ENABLE,
    LED,
    STATUS_RETURN_LEVEL,
    HARDWARE_ERROR_STATUS,
    POSITION_D_GAIN,
    POSITION_I_GAIN,
    POSITION_P_GAIN,
    GOAL_CURRENT,
    GOAL_VELOCITY,
    PROFILE_ACCELERATION,
    PROFILE_VELOCITY,
    GOAL_POSITION,
    MOVING,
    PRESENT_CURRENT,
    PRESENT_VELOCITY,
    PRESENT_POSITION,
    PRESENT_INPUT_VOLTAGE,
    PRESENT_TEMPERATURE,
)
MEMORY_SIZE = PRESENT_TEMPERATURE.address + 1
#: The block the telemetry read covers: current (load), velocity, position, voltage, temperature.
TELEMETRY_START = PRESENT_CURRENT.address
TELEMETRY_SIZE = PRESENT_TEMPERATURE.address + 1 - TELEMETRY_START


class HardwareError(enum.IntFlag):
    """Bits of Hardware_Error_Status; a status packet's alert bit says one is set."""

    INPUT_VOLTAGE = 1
    OVERHEATING = 4
    MOTOR_ENCODER = 8
    ELECTRICAL_SHOCK = 16
    OVERLOAD = 32


#: Hardware errors as the neutral fault flags the health monitor reads.
FAULTS: dict[HardwareError, FaultBit] = {
    HardwareError.INPUT_VOLTAGE: FaultBit.VOLTAGE,
    HardwareError.OVERHEATING: FaultBit.OVERHEAT,
    HardwareError.MOTOR_ENCODER: FaultBit.ANGLE,
    HardwareError.ELECTRICAL_SHOCK: FaultBit.OVERCURRENT,
    HardwareError.OVERLOAD: FaultBit.OVERLOAD,
}


def faults_of(hardware_error: int) -> int:
    """The neutral fault flags of a Hardware_Error_Status value."""
    flags = 0
    for bit, fault in FAULTS.items():
        if hardware_error & bit:
            flags |= fault
    return flags
