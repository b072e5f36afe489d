"""Robot types: a folder with a URDF and a `robot.toml`, turned into a `RobotModel`.

Units: the wire speaks degrees measured from each joint's *neutral* pose (or, for a joint whose
`unit` is `percent`, such as LeRobot's grippers, 0 to 100 across its URDF range); the URDF speaks
radians. `JointSpec.to_urdf` and `JointSpec.from_urdf` are the only conversions between them.
"""

from __future__ import annotations

import enum
import functools
import math
import os
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from arena.protocol.errors import ArenaError, ErrorCode, Severity
from arena.protocol.rest import MAX_JOIN_SPEED
from arena.robot.workspace import Workspace, workspace_from_json

#: Folder of the robot types shipped with Arena.
BUILTIN_TYPES_DIR = Path(__file__).resolve().parent.parent / "robot_types"
#: Environment variable naming extra folders of robot types (os.pathsep separated).
TYPES_PATH_ENV = "ARENA_ROBOT_TYPES"
CONFIG_FILE = "robot.toml"
#: A joint's default acceleration limit per deg/s of its velocity limit (full speed in 33 ms;
#: specs/motion.md says why).
ACCELERATION_PER_VELOCITY = 30.0
#: A joint's default jerk limit per deg/s^2 of its acceleration limit: full acceleration in
#: 5 ms, half a control tick (specs/motion.md: one encoder step read at 100 Hz is a jerk of
#: 88,000 deg/s^3 by divided differences, and a slower ramp trails a leader's reads).
JERK_PER_ACCELERATION = 200.0
#: A joint's `unit` when its wire value is 0..100 across its URDF range (LeRobot's grippers).
PERCENT = "percent"


class LossPolicy(enum.StrEnum):
    """What the robot does when its active master is lost."""

    ESTOP = "estop"
    HOLD = "hold"


@dataclass(frozen=True, slots=True)
class SafetyPolicy:
    """Per-robot safety settings (defaults come from the robot type's config)."""

    loss_policy: LossPolicy = LossPolicy.ESTOP
    command_rate: float = 100.0
    command_burst: int = 10
    estop_severity: Severity = Severity.CRITICAL
    control_rate: float = 100.0
    #: deg/s at which a measuring slave that joins is brought to the robot's pose.
    join_speed: float = 15.0


@dataclass(frozen=True, slots=True)
class JointSpec:
    """One joint as the protocol sees it: name, servo, limits in degrees and deg/s."""

    name: str
    servo_id: int
    aliases: tuple[str, ...]
    lower: float
    upper: float
    max_velocity: float
    neutral: float  # URDF radians that 0 degrees on the wire stands for
    urdf_joint: str = ""  # the URDF joint it drives, when its name differs from `name`
    #: "deg", or "percent": 0 is the URDF's lower limit, 100 its upper (`span` radians apart).
    unit: str = "deg"
    span: float = 0.0  # URDF radians from lower to upper limit (percent joints)
    #: The servo's model name in its bus family (`[bus] family`); "" for the family's default.
    servo_model: str = ""
    #: deg/s^2 (or %/s^2) and deg/s^3 the trajectory may ask of the joint; 0: the defaults,
    #: `ACCELERATION_PER_VELOCITY` times `max_velocity` and `JERK_PER_ACCELERATION` times that.
    acceleration: float = 0.0
    jerk: float = 0.0
    #: Percent of the servo's full torque it may give (the robot type's cap, as LeRobot caps
    #: its grippers; a usb-slave's `torqueLimit` overrides it); None: uncapped. specs/force.md.
    torque_limit: float | None = None

    @property
    def max_acceleration(self) -> float:
        """deg/s^2 (or %/s^2) the trajectory may ask of this joint."""
        return self.acceleration or ACCELERATION_PER_VELOCITY * self.max_velocity

    @property
    def max_jerk(self) -> float:
        """deg/s^3 (or %/s^3) the trajectory may ask of this joint."""
        return self.jerk or JERK_PER_ACCELERATION * self.max_acceleration

    @property
    def urdf_name(self) -> str:
        """The name of this joint in the URDF."""
        return self.urdf_joint or self.name

    @property
    def radians_per_unit(self) -> float:
        """URDF radians one wire unit (a degree, or a percent) stands for."""
        return self.span / 100.0 if self.unit == PERCENT else math.pi / 180.0

    def to_urdf(self, degrees: float) -> float:
        """Wire degrees (or percent) to URDF radians."""
        if self.unit == PERCENT:
            return self.neutral + degrees * self.span / 100.0
        return self.neutral + math.radians(degrees)

    def from_urdf(self, radians: float) -> float:
        """URDF radians to wire degrees (or percent)."""
        if self.unit == PERCENT:
            return (radians - self.neutral) * 100.0 / self.span
        return math.degrees(radians - self.neutral)

    def clamp(self, degrees: float) -> float:
        """The nearest value inside the joint's position limits."""
        return min(self.upper, max(self.lower, degrees))


@dataclass(frozen=True, slots=True)
class BusSpec:
    """The robot type's servo bus, by name only: which family of servos (`feetech`,
    `dynamixel`: the drivers know what they are) and its default baud rate (None: the family's)."""

    family: str = "feetech"
    baud_rate: int | None = None


@dataclass(frozen=True, slots=True)
class EndEffector:
    """The robot type's hand (`[end_effector]` in robot.toml): the URDF link whose pose is the
    hand's, the tool point `offset` in that link's frame (metres), and the joint that opens
    and closes it (`gripper`, a joint's protocol name, or "" for none)."""

    link: str
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gripper: str = ""


@dataclass(frozen=True)
class RobotModel:
    """Everything Arena knows about a robot type: joints in servo order, safety, URDF."""

    robot_type: str
    description: str
    joints: tuple[JointSpec, ...]
    safety: SafetyPolicy
    urdf_path: Path
    #: Where the arm may go (the collision guard's floor and keep-out boxes).
    workspace: Workspace = field(default_factory=Workspace)
    bus: BusSpec = field(default_factory=BusSpec)
    #: The hand whose pose `arena.robot.cartesian` computes and solves for (None: not named).
    end_effector: EndEffector | None = None

    _by_name: dict[str, JointSpec] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        names: dict[str, JointSpec] = {}
        for joint in self.joints:
            for name in (joint.name, *joint.aliases):
                names[name] = joint
                names[name.lower()] = joint
        object.__setattr__(self, "_by_name", names)

    def joint(self, name: str) -> JointSpec | None:
        """The joint called `name` (protocol name or alias, any case), or None."""
        found = self._by_name.get(name)
        return found if found is not None else self._by_name.get(name.lower())

    @property
    def joint_names(self) -> tuple[str, ...]:
        """Protocol names in servo order."""
        return tuple(j.name for j in self.joints)


def robot_type_dirs() -> list[Path]:
    """Folders searched for robot types: `$ARENA_ROBOT_TYPES` entries first, then built-ins."""
    extra = [Path(p) for p in os.environ.get(TYPES_PATH_ENV, "").split(os.pathsep) if p]
    return [*extra, BUILTIN_TYPES_DIR]


def list_robot_types() -> list[str]:
    """Names of every robot type found on the search path."""
    found: set[str] = set()
    for folder in robot_type_dirs():
        if folder.is_dir():
            found.update(p.parent.name for p in folder.glob(f"*/{CONFIG_FILE}"))
    return sorted(found)


def load_robot_model(robot_type: str) -> RobotModel:
    """Load a robot type by name from the search path.

    Raises `ArenaError(UNKNOWN_ROBOT_TYPE)` when no folder has it and `ArenaError(INVALID_CONFIG)`
    when its files are inconsistent.
    """
    for folder in robot_type_dirs():
        candidate = folder / robot_type
        if (candidate / CONFIG_FILE).is_file() and candidate.name == robot_type:
            return _load_from_folder(candidate.resolve())
    known = ", ".join(list_robot_types()) or "none"
    raise ArenaError(
        ErrorCode.UNKNOWN_ROBOT_TYPE, f"No robot type {robot_type!r}; known types: {known}."
    )


@functools.lru_cache(maxsize=32)
def _load_from_folder(folder: Path) -> RobotModel:
    def bad(why: str) -> ArenaError:
        return ArenaError(ErrorCode.INVALID_CONFIG, f"Robot type {folder.name!r}: {why}")

    try:
        config = tomllib.loads((folder / CONFIG_FILE).read_text(encoding="utf-8"))
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise bad(f"cannot read {CONFIG_FILE}: {exc}") from exc
    urdf_path = folder / str(config.get("urdf", f"{folder.name}.urdf"))
    urdf_joints = _read_urdf_joints(urdf_path, bad)
    try:
        safety = _safety_policy(config.get("safety", {}))
    except (TypeError, ValueError) as exc:
        raise bad(f"invalid [safety]: {exc}") from exc
    joints = tuple(_joint_spec(entry, urdf_joints, bad) for entry in config.get("joints", []))
    if not joints:
        raise bad("no [[joints]] defined")
    try:
        workspace = workspace_from_json(config.get("workspace", {}))
    except ValueError as exc:
        raise bad(f"invalid [workspace]: {exc}") from exc
    try:
        bus = _bus_spec(config.get("bus", {}))
    except (TypeError, ValueError) as exc:
        raise bad(f"invalid [bus]: {exc}") from exc
    names = [j.name for j in joints]
    end_effector = _end_effector(config.get("end_effector"), urdf_path, names, bad)
    every_name = [n for j in joints for n in {x.lower() for x in (j.name, *j.aliases)}]
    if len(set(every_name)) != len(every_name):
        raise bad(f"joint names and aliases must be unique: {names}")
    return RobotModel(
        robot_type=folder.name,
        description=str(config.get("description", folder.name)),
        joints=joints,
        safety=safety,
        urdf_path=urdf_path,
        workspace=workspace,
        bus=bus,
        end_effector=end_effector,
    )


def _end_effector(section: Any, urdf_path: Path, names: list[str], bad: Any) -> EndEffector | None:
    if section is None:
        return None
    from arena.robot.kinematics import Kinematics  # the standard library's XML parser only

    if not isinstance(section, dict) or not isinstance(section.get("link"), str):
        raise bad("[end_effector] needs link = the name of a URDF link")
    unknown = set(section) - {"link", "offset", "gripper"}
    if unknown:
        raise bad(f"[end_effector] has unknown keys {sorted(unknown)}")
    link = section["link"]
    if link not in Kinematics.from_urdf(urdf_path).links:
        raise bad(f"[end_effector] link {link!r} is not a link of {urdf_path.name}")
    offset = section.get("offset", [0.0, 0.0, 0.0])
    if (
        not isinstance(offset, list)
        or len(offset) != 3
        or not all(isinstance(v, int | float) and math.isfinite(v) for v in offset)
    ):
        raise bad("[end_effector] offset must be three finite numbers (metres)")
    gripper = section.get("gripper", "")
    if not isinstance(gripper, str) or (gripper and gripper not in names):
        raise bad(f"[end_effector] gripper must name one of the joints {names}")
    return EndEffector(link, (float(offset[0]), float(offset[1]), float(offset[2])), gripper)


def _bus_spec(section: dict[str, Any]) -> BusSpec:
    family = section.get("family", "feetech")
    baud = section.get("baud_rate")
    if not isinstance(family, str) or not family:
        raise ValueError("family must be a name such as 'feetech' or 'dynamixel'")
    if baud is not None and (not isinstance(baud, int) or baud <= 0):
        raise ValueError("baud_rate must be a positive integer")
    return BusSpec(family=family, baud_rate=baud)


@dataclass(frozen=True, slots=True)
class _UrdfJoint:
    lower: float
    upper: float
    velocity: float


def _read_urdf_joints(path: Path, bad: Any) -> dict[str, _UrdfJoint]:
    import yourdfpy  # costly import (trimesh, scipy): only when a type is first loaded

    try:
        urdf = yourdfpy.URDF.load(str(path), build_scene_graph=False, load_meshes=False)
    except Exception as exc:  # yourdfpy raises many kinds; all mean the same to the user
        raise bad(f"cannot parse URDF {path.name}: {exc}") from exc
    joints: dict[str, _UrdfJoint] = {}
    for joint in urdf.robot.joints:
        if joint.type != "revolute" or joint.limit is None:
            continue
        joints[joint.name] = _UrdfJoint(
            float(joint.limit.lower), float(joint.limit.upper), float(joint.limit.velocity)
        )
    return joints


def _safety_policy(section: dict[str, Any]) -> SafetyPolicy:
    policy = SafetyPolicy(
        loss_policy=LossPolicy(section.get("loss_policy", LossPolicy.ESTOP)),
        command_rate=float(section.get("command_rate", 100.0)),
        command_burst=int(section.get("command_burst", 10)),
        estop_severity=Severity(section.get("estop_severity", Severity.CRITICAL)),
        control_rate=float(section.get("control_rate", 100.0)),
        join_speed=float(section.get("join_speed", 15.0)),
    )
    if policy.command_rate <= 0 or policy.command_burst < 1 or policy.control_rate <= 0:
        raise ValueError("command_rate, command_burst and control_rate must be positive")
    if not 0 < policy.join_speed <= MAX_JOIN_SPEED:
        raise ValueError(f"join_speed must be above 0 and at most {MAX_JOIN_SPEED:g} deg/s")
    return policy


def _joint_spec(entry: dict[str, Any], urdf: dict[str, _UrdfJoint], bad: Any) -> JointSpec:
    name = str(entry.get("name", ""))
    urdf_joint = str(entry.get("urdf_joint", name))
    source = urdf.get(urdf_joint)
    if source is None:
        raise bad(f"joint {name!r} is not a revolute joint with limits in the URDF")
    unit = str(entry.get("unit", "deg"))
    if unit not in ("deg", PERCENT):
        raise bad(f"joint {name!r}: unit must be 'deg' or {PERCENT!r}, not {unit!r}")
    span = source.upper - source.lower
    if unit == PERCENT:
        # 0 % is the URDF's lower limit; velocities are in %/s.
        neutral, lower, upper = source.lower, 0.0, 100.0
        velocity = source.velocity * 100.0 / span
    else:
        neutral = float(entry.get("neutral", (source.lower + source.upper) / 2))
        lower = math.degrees(source.lower - neutral)
        upper = math.degrees(source.upper - neutral)
        velocity = math.degrees(source.velocity)
    # Optional soft limits narrow (never widen) what the URDF allows.
    soft_lower = float(entry.get("lower", lower))
    soft_upper = float(entry.get("upper", upper))
    if not lower - 1e-9 <= soft_lower < soft_upper <= upper + 1e-9:
        raise bad(f"joint {name!r}: soft limits must lie inside [{lower:.1f}, {upper:.1f}] {unit}")
    max_velocity = float(entry.get("max_velocity", velocity))
    if not 0 < max_velocity <= velocity + 1e-9:
        raise bad(f"joint {name!r}: max_velocity must be in (0, {velocity:.1f}] {unit}/s")
    acceleration = float(entry.get("max_acceleration", 0.0))
    jerk = float(entry.get("max_jerk", 0.0))
    for key, value in (("max_acceleration", acceleration), ("max_jerk", jerk)):
        if key in entry and not (math.isfinite(value) and value > 0):
            raise bad(f"joint {name!r}: {key} must be a positive number")
    torque_limit = entry.get("torque_limit")
    if torque_limit is not None and (
        isinstance(torque_limit, bool)
        or not isinstance(torque_limit, int | float)
        or not 0 < torque_limit <= 100
    ):
        raise bad(f"joint {name!r}: torque_limit must be a percent in (0, 100]")
    return JointSpec(
        name=name,
        servo_id=int(entry.get("servo_id", 0)),
        aliases=tuple(str(a) for a in entry.get("aliases", ())),
        lower=soft_lower,
        upper=soft_upper,
        max_velocity=max_velocity,
        neutral=neutral,
        urdf_joint="" if urdf_joint == name else urdf_joint,
        unit=unit,
        span=span,
        servo_model=str(entry.get("servo_model", "")),
        acceleration=acceleration,
        jerk=jerk,
        torque_limit=None if torque_limit is None else float(torque_limit),
    )
