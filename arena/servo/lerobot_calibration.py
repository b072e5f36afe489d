"""The calibration files LeRobot users already have: found, checked, read, and written.

A `usb-slave`/`usb-master` given `"calibration": "PATH"` (a value with a `/` or ending in
`.json`) or `"calibration": "lerobot:ID"` reads LeRobot's JSON file (one entry per motor) and
reads its joints as LeRobot does (`lerobot_format`). A file that does not fit the robot type is
refused before the bus is opened, so before any torque. `to_lerobot` writes an Arena
calibration in LeRobot's format (`arena calibrate --format lerobot`).
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import msgspec

from arena.protocol.errors import ArenaError, ErrorCode
from arena.robot.model import PERCENT, RobotModel
from arena.servo.calibration import DEGREES_PER_STEP, Calibration, JointCalibration
from arena.servo.interface import CENTER_STEP, MAX_STEP, STEPS_PER_TURN, ServoBus, ServoFamily
from arena.servo.lerobot_format import MAX_RES, LeRobotJoint, LeRobotMotor

#: Steps a servo that counts turns may read past its file's range and still take torque: a
#: joint a little past the end LeRobot's sweep recorded (its goal, clamped into the range, is
#: that close), far from the whole turn a joint turned by hand is away.
FRAME_MARGIN = 256
#: The prefix of a calibration value naming a file in LeRobot's own folder by its arm id.
LEROBOT_PREFIX = "lerobot:"


def is_lerobot_reference(value: str | None) -> bool:
    """Whether a `calibration` value names a LeRobot file (a path or `lerobot:ID`)."""
    return value is not None and (
        value.startswith(LEROBOT_PREFIX) or "/" in value or value.endswith(".json")
    )


def lerobot_calibration_dir(env: Mapping[str, str] | None = None) -> Path:
    """LeRobot's calibration folder: `$HF_LEROBOT_CALIBRATION`, else under `$HF_LEROBOT_HOME`,
    else under `$HF_HOME`, else `~/.cache/huggingface/lerobot/calibration` (as LeRobot finds it)."""
    env = os.environ if env is None else env
    if env.get("HF_LEROBOT_CALIBRATION"):
        return Path(env["HF_LEROBOT_CALIBRATION"]).expanduser()
    if env.get("HF_LEROBOT_HOME"):
        return Path(env["HF_LEROBOT_HOME"]).expanduser() / "calibration"
    hf_home = Path(env.get("HF_HOME") or "~/.cache/huggingface").expanduser()
    return hf_home / "lerobot" / "calibration"


def resolve(
    value: str,
    robot_type: str,
    family: ServoFamily,
    *,
    leader: bool,
    env: Mapping[str, str] | None = None,
) -> Path:
    """The file a LeRobot `calibration` value means; `lerobot:ID` is looked for under every
    folder name LeRobot has used for this robot type (`family.lerobot_folders`: the type's
    own, else the family's `*`). A missing file is an error saying where it was looked for."""
    if not value.startswith(LEROBOT_PREFIX):
        path = Path(value).expanduser()
        if path.suffix != ".json":
            raise ArenaError(
                ErrorCode.INVALID_CONFIG, f"Calibration {value!r}: a path must name a .json file."
            )
        if not path.is_file():
            raise ArenaError(ErrorCode.INVALID_CONFIG, f"No calibration file at {value}.")
        return path
    arm_id = value.removeprefix(LEROBOT_PREFIX)
    if not arm_id or "/" in arm_id or arm_id.startswith("."):
        raise ArenaError(
            ErrorCode.INVALID_CONFIG, f"Calibration {value!r}: `lerobot:` needs an arm id."
        )
    kind = "teleoperators" if leader else "robots"
    root = lerobot_calibration_dir(env) / kind
    folders = family.lerobot_folders.get(robot_type) or family.lerobot_folders.get("*", {})
    tried = [root / name / f"{arm_id}.json" for name in folders.get(kind, ())]
    for path in tried:
        if path.is_file():
            return path
    raise ArenaError(
        ErrorCode.INVALID_CONFIG,
        f"No LeRobot calibration {arm_id!r}: looked for {', '.join(map(str, tried))}.",
    )


class LeRobotCalibration(Calibration, frozen=True, kw_only=True):
    """A calibration read from LeRobot's file: joints read as LeRobot reads them.

    `joints` still maps each joint to its servo (offsets unused); `lerobot` holds each joint's
    conversion and `source` the file it came from (Arena never writes over it).
    """

    lerobot: dict[str, LeRobotJoint] = msgspec.field(default_factory=dict)
    source: str = ""

    def to_degrees(self, raw: Mapping[int, int]) -> dict[str, float]:
        """Joint values (degrees, or 0..100) for raw Present_Position steps by servo id."""
        return {
            name: joint.to_value(raw[joint.motor.id])
            for name, joint in self.lerobot.items()
            if joint.motor.id in raw
        }

    def to_steps(self, degrees: Mapping[str, float]) -> dict[int, int]:
        """Goal_Position steps by servo id for joint values (unknown joints are left out)."""
        return {
            joint.motor.id: joint.to_steps(value)
            for name, value in degrees.items()
            if (joint := self.lerobot.get(name)) is not None
        }

    def to_values(self, raw: Mapping[int, int], spans: Mapping[str, float]) -> dict[str, float]:
        """As LeRobot reads them: degrees, and 0..100 for its RANGE_0_100 joints already."""
        return self.to_degrees(raw)

    def to_goal_steps(
        self, values: Mapping[str, float], spans: Mapping[str, float]
    ) -> dict[int, int]:
        """Goal steps for values as LeRobot reads them (see `to_values`)."""
        return self.to_steps(values)

    def with_register_homings(self, homings: Mapping[int, int]) -> LeRobotCalibration:
        """This calibration for servos whose Homing_Offset registers hold `homings` (by id)."""
        joints = {
            name: msgspec.structs.replace(joint, register_homing=homings.get(joint.motor.id))
            for name, joint in self.lerobot.items()
        }
        return msgspec.structs.replace(self, lerobot=joints)

    def frames(self, margin: int = FRAME_MARGIN) -> dict[int, tuple[int, int]]:
        """Each servo's frame (by id): the Present_Positions its file range spans, widened by
        `margin` (for servos that count turns; see `LeRobotJoint.frame`)."""
        return {joint.motor.id: joint.frame(margin) for joint in self.lerobot.values()}


def from_lerobot(
    data: Any, model: RobotModel, source: str, family: ServoFamily
) -> LeRobotCalibration:
    """Check LeRobot's per-motor entries against `model` (its servos of `family`) and build the
    calibration. Every refusal names the motor and the value (`INVALID_CONFIG`)."""

    def refuse(why: str) -> ArenaError:
        return ArenaError(ErrorCode.INVALID_CONFIG, f"LeRobot calibration {source}: {why}.")

    try:
        motors = msgspec.convert(data, dict[str, LeRobotMotor])
    except msgspec.ValidationError as exc:
        raise refuse(f"not LeRobot's format ({exc})") from None
    joints: dict[str, LeRobotJoint] = {}
    for motor_name, motor in motors.items():
        joint = model.joint(motor_name)
        if joint is None:
            raise refuse(f"motor {motor_name!r} is not a joint of the {model.robot_type}")
        if motor.id != joint.servo_id:
            raise refuse(
                f"motor {motor_name!r} has id {motor.id}, but the {model.robot_type}'s "
                f"{joint.name} is servo {joint.servo_id}"
            )
        problem = motor.problem(family)
        if problem is not None:
            raise refuse(f"motor {motor_name!r}: {problem}")
        joints[joint.name] = LeRobotJoint(
            motor=motor,
            percent=joint.unit == PERCENT,
            homing_sign=family.homing_sign,
            wraps=family.wraps,
            drive_mode_applies=family.wraps,  # (LeRobot's Feetech bus applies it, not Dynamixel's)
        )
    missing = [j.name for j in model.joints if j.name not in joints]
    if missing:
        raise refuse(f"no entry for {', '.join(missing)}")
    return LeRobotCalibration(
        robot_type=model.robot_type,
        joints={name: JointCalibration(servo_id=j.motor.id) for name, j in joints.items()},
        homing_in_servos=True,
        lerobot=joints,
        source=source,
    )


def to_lerobot(
    calibration: Calibration,
    model: RobotModel,
    register_homings: Mapping[int, int],
    family: ServoFamily,
    rest_present: Mapping[int, int] | None = None,
) -> dict[str, dict[str, int]]:
    """An Arena calibration (`arena calibrate`: the rest pose is every joint at 0) in LeRobot's
    format, keyed by LeRobot's joint names, so that LeRobot reads the rest pose as 0.

    `register_homings`: what the servos' Homing_Offset registers held while it was made (by
    id). The offset moves into `homing_offset`, so the rest pose reads step 2048 in LeRobot.
    LeRobot's zero is the middle of the range, so a degree joint's range is made symmetric
    about the rest pose, as wide as the captured range's wider side (or, when the joint was not
    swept, the robot type's limits), within the servo's steps. A 0-100 joint (a gripper) rests
    at 0, its range_min, and spans its captured range or else its URDF range.

    A servo that counts turns (Dynamixel) reads the homing unwrapped, so its homing must put
    the rest pose at exactly step 2048, not a turn away: `rest_present`, the Present_Position
    each servo read at rest (by id), says where that is.
    """
    if not family.wraps and rest_present is None:
        raise ArenaError(
            ErrorCode.INVALID_CONFIG,
            f"LeRobot's format for {family.name} servos needs the rest pose's present positions.",
        )
    out: dict[str, dict[str, int]] = {}
    for spec in model.joints:
        joint = calibration.joints.get(spec.name)
        if joint is None:
            continue
        if joint.direction != 1:
            raise ArenaError(
                ErrorCode.INVALID_CONFIG,
                f"Joint {spec.name} runs reversed (direction -1): LeRobot's degrees cannot.",
            )
        register = register_homings.get(spec.servo_id, 0)
        if rest_present is None or family.wraps:
            # Arena reads real = present + offset; the servo reports present = actual - homing:
            # real = actual - (homing - offset), which is LeRobot's homing_offset.
            homing = _wrapped(register + family.homing_sign * joint.offset)
        else:
            # present = actual + homing, unwrapped: LeRobot's present at rest is
            # rest - register + homing, which must be 2048.
            homing = register + CENTER_STEP - rest_present[spec.servo_id]
        low, high = joint.min_degrees, joint.max_degrees
        if spec.unit == PERCENT:
            if low is None or high is None:
                low, high = 0.0, math.degrees(spec.span)
            range_min = max(0, round(CENTER_STEP + low / DEGREES_PER_STEP))
            range_max = min(MAX_STEP, round(CENTER_STEP + high / DEGREES_PER_STEP))
        else:
            if low is None or high is None:
                low, high = spec.lower, spec.upper
            half = math.ceil(max(-low, high) * MAX_RES / 360)
            half = max(1, min(half, CENTER_STEP, MAX_STEP - CENTER_STEP))
            range_min, range_max = CENTER_STEP - half, CENTER_STEP + half
        out[spec.aliases[0] if spec.aliases else spec.name] = {
            "id": spec.servo_id,
            "drive_mode": 0,
            "homing_offset": homing,
            "range_min": range_min,
            "range_max": range_max,
        }
    return out


def _wrapped(homing: int) -> int:
    """`homing` as the equivalent register value (one turn is the same pose), -2048..2047."""
    homing %= STEPS_PER_TURN
    return homing - STEPS_PER_TURN if homing >= STEPS_PER_TURN // 2 else homing


def save_lerobot(
    calibration: Calibration,
    model: RobotModel,
    register_homings: Mapping[int, int],
    family: ServoFamily,
    path: Path,
    rest_present: Mapping[int, int] | None = None,
) -> None:
    """Write `calibration` in LeRobot's format (see `to_lerobot`), atomically."""
    data = to_lerobot(calibration, model, register_homings, family, rest_present)
    text = msgspec.json.format(msgspec.json.encode(data), indent=4)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_suffix(path.suffix + ".tmp")
    temporary.write_bytes(text + b"\n")
    temporary.replace(path)


def load_calibration(path: Path, model: RobotModel, family: ServoFamily) -> Calibration:
    """Read a calibration file in either format: Arena's (it has `joints`) or LeRobot's."""
    try:
        data = msgspec.json.decode(path.read_bytes())
    except FileNotFoundError:
        return Calibration.load(path)  # (its error says: calibrate first)
    except (OSError, msgspec.DecodeError) as exc:
        raise ArenaError(
            ErrorCode.INVALID_CONFIG, f"Calibration file {path} is unreadable: {exc}"
        ) from None
    if isinstance(data, dict) and isinstance(data.get("joints"), dict):
        return Calibration.load(path)
    return from_lerobot(data, model, str(path), family)


def read_register_homings(bus: ServoBus, servo_ids: tuple[int, ...]) -> dict[int, int]:
    """Each servo's Homing_Offset register (runs in the bus thread)."""
    return bus.read_homings(servo_ids)
