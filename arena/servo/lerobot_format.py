"""LeRobot's per-motor calibration and its arithmetic, exactly as LeRobot's `MotorsBus` does it.

LeRobot stores, per motor, `id`, `drive_mode`, `homing_offset`, `range_min`, `range_max` (steps).
The servo applies the homing itself (Feetech: `present = actual - Homing_Offset`, within one
turn; Dynamixel: `present = actual + Homing_Offset`, counting turns); LeRobot then reads, in
its degrees mode, `(present - mid) * 360 / (resolution - 1)` with `mid` the middle of the range
(no clamping, no drive mode), and for a 0-100 joint (a gripper) the present position clamped
into the range and scaled to 0..100 (inverted when `drive_mode` is 1, on Feetech servos: LeRobot
leaves a Dynamixel's direction to its Drive_Mode register). Pure: no bus, no files.
"""

from __future__ import annotations

import msgspec

from arena.servo.interface import MAX_STEP, STEPS_PER_TURN, ServoFamily

#: LeRobot's `max_res` for the STS3215 and the Dynamixel X series: resolution (4096) minus one.
MAX_RES = STEPS_PER_TURN - 1


class LeRobotMotor(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """One motor of a LeRobot calibration file, field for field."""

    id: int
    drive_mode: int
    homing_offset: int
    range_min: int
    range_max: int

    def problem(self, family: ServoFamily) -> str | None:
        """Why this entry cannot describe a servo of `family` (None: it can)."""
        if self.drive_mode not in (0, 1):
            return f"drive_mode {self.drive_mode} is not 0 or 1"
        if abs(self.homing_offset) > family.homing_limit:
            return (
                f"homing_offset {self.homing_offset} is outside the servo's +-{family.homing_limit}"
            )
        for field, value in (("range_min", self.range_min), ("range_max", self.range_max)):
            if not 0 <= value <= MAX_STEP:
                return f"{field} {value} is outside the servo's 0..{MAX_STEP}"
        if self.range_min >= self.range_max:
            return f"range_min {self.range_min} is not below range_max {self.range_max}"
        return None


class LeRobotJoint(msgspec.Struct, frozen=True, kw_only=True):
    """A motor's conversion: LeRobot's entry, its mode, and the servo's own Homing_Offset.

    `register_homing` is what the servo holds; when it differs from the file's (the file was
    not written to this servo), the difference is applied here so that the values are those
    LeRobot reads once it has written its calibration.
    """

    motor: LeRobotMotor
    percent: bool = False  # LeRobot's RANGE_0_100 (grippers), else DEGREES
    register_homing: int | None = None
    #: The family's `homing_sign`, `wraps`, and whether LeRobot applies `drive_mode` itself.
    homing_sign: int = -1
    wraps: bool = True
    drive_mode_applies: bool = True

    @property
    def _shift(self) -> int:
        # present (servo frame) + shift = present as the file's homing would make it
        if self.register_homing is None:
            return 0
        return self.homing_sign * (self.motor.homing_offset - self.register_homing)

    def _frame(self, step: int) -> int:
        return step % STEPS_PER_TURN if self.wraps else step

    def frame(self, margin: int) -> tuple[int, int]:
        """The Present_Positions (servo frame) the file's range spans, widened by `margin` on
        each side (for servos that count turns: outside it, `to_steps` is a turn away)."""
        m = self.motor
        return m.range_min - self._shift - margin, m.range_max - self._shift + margin

    def to_value(self, present: int) -> float:
        """The joint value LeRobot reads for a Present_Position of `present`."""
        m = self.motor
        homed = self._frame(present + self._shift)
        if self.percent:
            bounded = min(m.range_max, max(m.range_min, homed))
            norm = (bounded - m.range_min) / (m.range_max - m.range_min) * 100
            return 100 - norm if m.drive_mode and self.drive_mode_applies else norm
        return (homed - (m.range_min + m.range_max) / 2) * 360 / MAX_RES

    def to_steps(self, value: float) -> int:
        """The Goal_Position (servo frame) for a joint value, kept inside the file's range."""
        m = self.motor
        if self.percent:
            wanted = 100 - value if m.drive_mode and self.drive_mode_applies else value
            bounded = min(100.0, max(0.0, wanted))
            homed = bounded / 100 * (m.range_max - m.range_min) + m.range_min
        else:
            homed = value * MAX_RES / 360 + (m.range_min + m.range_max) / 2
        step = min(m.range_max, max(m.range_min, round(homed)))
        return self._frame(step - self._shift)
