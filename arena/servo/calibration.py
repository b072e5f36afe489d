"""Servo steps <-> protocol degrees, through a per-joint calibration; and its file format.

A servo reports a raw step in 0..4095. Calibration adds an offset per joint (`real = raw +
offset`, modulo one turn) chosen so that the pose the user matched to the twin reads as the
twin's values; then `degrees = direction * (real - 2048) * 360 / 4096`, wrapped into one turn
around the joint's neutral. Everything here is pure: no bus, no files except `load`/`save`.

The file holds degrees for every joint. A joint whose robot type says `percent` (LeRobot's
grippers) is read in its own unit at the edge (`to_values`, `to_goal_steps`): 0 at its rest,
the twin's 0 % (closed), to 100 across its captured range, or else its URDF span (`spans`:
degrees by joint), as LeRobot's RANGE_0_100 reads a gripper and as `to_lerobot` writes one.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import msgspec

from arena.protocol.errors import ArenaError, ErrorCode
from arena.servo.interface import CENTER_STEP, STEPS_PER_TURN, ServoFamily

DEGREES_PER_STEP = 360.0 / STEPS_PER_TURN


class JointCalibration(msgspec.Struct, frozen=True, kw_only=True):
    """One joint: its servo, the step offset, the direction, and the captured range (degrees)."""

    servo_id: int
    offset: int = 0
    direction: int = 1
    min_degrees: float | None = None
    max_degrees: float | None = None

    def to_degrees(self, raw: int) -> float:
        """Degrees from neutral for a raw step reading."""
        centered = (raw + self.offset - CENTER_STEP) % STEPS_PER_TURN
        if centered >= STEPS_PER_TURN // 2:
            centered -= STEPS_PER_TURN  # the short way round: into [-2048, 2047]
        return self.direction * centered * DEGREES_PER_STEP

    def to_steps(self, degrees: float) -> int:
        """The raw goal step (0..4095) for `degrees`, clamped to the captured range first."""
        degrees = self.clamp(degrees)
        steps = round(self.direction * degrees / DEGREES_PER_STEP)
        return (steps + CENTER_STEP - self.offset) % STEPS_PER_TURN

    def percent(self, degrees: float, span: float) -> float:
        """A percent joint's value for `degrees` (see the module docstring)."""
        low, high = self._percent_range(span)
        return (degrees - low) / (high - low) * 100.0

    def from_percent(self, value: float, span: float) -> float:
        """The degrees of a percent joint's `value`."""
        low, high = self._percent_range(span)
        return low + value / 100.0 * (high - low)

    def _percent_range(self, span: float) -> tuple[float, float]:
        low, high = self.min_degrees, self.max_degrees
        if low is None or high is None or high <= low:
            return 0.0, span
        return low, high

    def clamp(self, degrees: float) -> float:
        """`degrees` limited to the captured range of motion (if one was captured)."""
        if self.min_degrees is not None and degrees < self.min_degrees:
            return self.min_degrees
        if self.max_degrees is not None and degrees > self.max_degrees:
            return self.max_degrees
        return degrees


class Calibration(msgspec.Struct, frozen=True, kw_only=True):
    """A robot's calibration: one entry per joint (protocol names), as stored on disk."""

    robot_type: str = "so-arm100"
    joints: dict[str, JointCalibration] = msgspec.field(default_factory=dict)
    homing_in_servos: bool = False  # offsets live in the servos' Homing_Offset registers
    created: str | None = None

    @classmethod
    def identity(cls, servo_ids: Mapping[str, int], robot_type: str = "so-arm100") -> Calibration:
        """No offsets, no range: raw step 2048 reads as 0 degrees (an uncalibrated arm)."""
        return cls(
            robot_type=robot_type,
            joints={name: JointCalibration(servo_id=sid) for name, sid in servo_ids.items()},
        )

    def to_degrees(self, raw: Mapping[int, int]) -> dict[str, float]:
        """Joint degrees for raw steps keyed by servo id (joints without a reading are left out)."""
        return {
            name: joint.to_degrees(raw[joint.servo_id])
            for name, joint in self.joints.items()
            if joint.servo_id in raw
        }

    def to_steps(self, degrees: Mapping[str, float]) -> dict[int, int]:
        """Raw goal steps keyed by servo id for joint degrees (unknown joints are left out)."""
        return {
            joint.servo_id: joint.to_steps(value)
            for name, value in degrees.items()
            if (joint := self.joints.get(name)) is not None
        }

    def to_values(self, raw: Mapping[int, int], spans: Mapping[str, float]) -> dict[str, float]:
        """Joint values in the robot type's units for raw steps by servo id: degrees, and 0 to
        100 for the percent joints of `spans` (their URDF spans in degrees)."""
        values = self.to_degrees(raw)
        for name, span in spans.items():
            if name in values:
                values[name] = self.joints[name].percent(values[name], span)
        return values

    def to_goal_steps(
        self, values: Mapping[str, float], spans: Mapping[str, float]
    ) -> dict[int, int]:
        """Raw goal steps by servo id for joint values in the robot type's units."""
        return self.to_steps(in_degrees(self, values, spans))

    def save(self, path: Path) -> None:
        """Write atomically (a crash leaves the old file or the new one, never half of one)."""
        path.parent.mkdir(parents=True, exist_ok=True)
        temporary = path.with_suffix(path.suffix + ".tmp")
        temporary.write_bytes(msgspec.json.format(msgspec.json.encode(self)) + b"\n")
        temporary.replace(path)

    @classmethod
    def load(cls, path: Path) -> Calibration:
        """Read a calibration file; a missing or malformed one raises `ArenaError`."""
        try:
            return msgspec.json.decode(path.read_bytes(), type=cls)
        except FileNotFoundError:
            raise ArenaError(
                ErrorCode.INVALID_CONFIG, f"No calibration file at {path}: calibrate first."
            ) from None
        except (OSError, msgspec.DecodeError) as exc:
            raise ArenaError(
                ErrorCode.INVALID_CONFIG, f"Calibration file {path} is unreadable: {exc}"
            ) from exc


def in_degrees(
    calibration: Calibration, values: Mapping[str, float], spans: Mapping[str, float]
) -> dict[str, float]:
    """Joint values in the robot type's units as the calibration's degrees (percent joints of
    `spans` through their range; a joint the calibration lacks as it is)."""
    return {
        name: joint.from_percent(value, spans[name])
        if name in spans and (joint := calibration.joints.get(name)) is not None
        else value
        for name, value in values.items()
    }


def rest_degrees(rest: Mapping[str, float], spans: Mapping[str, float]) -> dict[str, float]:
    """A rest pose in the robot type's units as the degrees a new calibration's offsets are
    made for (no range captured yet: a percent joint's 100 is its whole span)."""
    return {
        name: value * spans[name] / 100.0 if name in spans else value
        for name, value in rest.items()
    }


def offset_for(raw: int, rest_degrees: float, direction: int = 1) -> int:
    """The offset that makes `raw` read as `rest_degrees`, in [-2048, 2047]."""
    wanted = round(direction * rest_degrees / DEGREES_PER_STEP) + CENTER_STEP
    offset = (wanted - raw) % STEPS_PER_TURN
    return offset - STEPS_PER_TURN if offset >= STEPS_PER_TURN // 2 else offset


def homing_offset_register(offset: int, current: int, family: ServoFamily) -> int:
    """The Homing_Offset value that makes the servo itself apply `offset` on top of `current`.

    The servo reports `present = actual + sign * homing` (Feetech: sign -1, Dynamixel: +1), so
    adding `offset` to what it reports means homing = current + sign * offset. An offset that
    would leave the register's range (Feetech: +-2047) cannot go into the servo, nor any into
    a servo that counts turns (Dynamixel), whose present position would then leave one turn.
    """
    if not family.wraps:
        # Its present position would leave one turn (it counts turns), which Arena's own
        # calibration does not read: the offset stays in the file.
        raise ArenaError(
            ErrorCode.INVALID_CONFIG,
            f"{family.name} servos count turns: their offsets stay in the calibration file "
            "(leave writeHoming out).",
        )
    homing = current + family.homing_sign * offset
    if abs(homing) > family.homing_limit:
        raise ArenaError(
            ErrorCode.INVALID_CONFIG,
            f"Offset {offset} is outside the Homing_Offset register's +-{family.homing_limit}; "
            "keep it in the calibration file instead.",
        )
    return homing


@dataclass
class RangeCapture:
    """Min and max degrees seen per joint while the user moves the arm through its range."""

    low: dict[str, float] = field(default_factory=dict)
    high: dict[str, float] = field(default_factory=dict)

    def observe(self, degrees: Mapping[str, float]) -> None:
        """Widen each joint's range to include the new reading."""
        for name, value in degrees.items():
            if not math.isfinite(value):
                continue
            self.low[name] = min(self.low.get(name, value), value)
            self.high[name] = max(self.high.get(name, value), value)

    def apply(self, calibration: Calibration, min_span: float = 1.0) -> Calibration:
        """`calibration` with the captured ranges; joints that barely moved keep no range."""
        joints = dict(calibration.joints)
        for name, joint in joints.items():
            low, high = self.low.get(name), self.high.get(name)
            if low is None or high is None or high - low < min_span:
                continue
            joints[name] = replace_range(joint, low, high)
        return replace_joints(calibration, joints)


def replace_range(joint: JointCalibration, low: float, high: float) -> JointCalibration:
    """`joint` with a new captured range."""
    return msgspec.structs.replace(joint, min_degrees=round(low, 3), max_degrees=round(high, 3))


def replace_joints(calibration: Calibration, joints: Mapping[str, JointCalibration]) -> Calibration:
    """`calibration` with new joint entries."""
    return msgspec.structs.replace(calibration, joints=dict(joints))


def calibrate_rest(
    calibration: Calibration,
    raw: Mapping[int, int],
    rest: Mapping[str, float],
    joints: Iterable[str] | None = None,
) -> Calibration:
    """New offsets so the raw pose `raw` (by servo id) reads as `rest` (degrees by joint).

    Joints missing from `raw` or `rest` keep their old entry. Captured ranges are cleared: they
    were measured in the old frame.
    """
    names = set(joints) if joints is not None else set(calibration.joints)
    updated = dict(calibration.joints)
    for name in names:
        joint = calibration.joints.get(name)
        if joint is None or joint.servo_id not in raw or name not in rest:
            continue
        updated[name] = msgspec.structs.replace(
            joint,
            offset=offset_for(raw[joint.servo_id], rest[name], joint.direction),
            min_degrees=None,
            max_degrees=None,
        )
    return replace_joints(calibration, updated)
