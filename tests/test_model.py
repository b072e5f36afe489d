"""The robot model: so-arm100 facts, units both ways, limits, robot types from folders."""

from __future__ import annotations

import math
import re
import shutil
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from arena.protocol.errors import ArenaError, ErrorCode, Severity
from arena.robot.model import (
    BUILTIN_TYPES_DIR,
    TYPES_PATH_ENV,
    LossPolicy,
    list_robot_types,
    load_robot_model,
)
from tests.conftest import missing, shared_dir

SPECS = Path(__file__).resolve().parent.parent / "specs"
#: The reference URDF, in the `shared/` folder beside the repository (see `shared_dir`).
REFERENCE_URDF = Path("robots/so-arm100/so100-reference.urdf")


def test_so_arm100_joints_servo_ids_and_aliases() -> None:
    model = load_robot_model("so-arm100")
    assert model.joint_names == ("Rotation", "Pitch", "Elbow", "Wrist_Pitch", "Wrist_Roll", "Jaw")
    assert [j.servo_id for j in model.joints] == [1, 2, 3, 4, 5, 6]
    lerobot = ["shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll", "gripper"]
    for alias, name in zip(lerobot, model.joint_names, strict=True):
        found = model.joint(alias)
        assert found is not None and found.name == name
    assert model.joint("ROTATION") is model.joint("Rotation")
    assert model.joint("Shoulder") is None


def test_limits_come_from_the_urdf_in_wire_degrees() -> None:
    model = load_robot_model("so-arm100")
    pitch = model.joint("Pitch")
    assert pitch is not None
    # URDF range [0, 3.5] rad, neutral in the middle: +-100.27 degrees on the wire.
    assert pitch.lower == pytest.approx(-math.degrees(1.75), abs=1e-5)
    assert pitch.upper == pytest.approx(math.degrees(1.75), abs=1e-5)
    assert pitch.to_urdf(pitch.lower) == pytest.approx(0.0)
    assert pitch.to_urdf(pitch.upper) == pytest.approx(3.5)
    for joint in model.joints:
        assert joint.max_velocity == pytest.approx(math.degrees(4.71239))  # the STS3215's


def test_seed_example_values_are_valid_targets() -> None:
    model = load_robot_model("so-arm100")
    examples = {"Rotation": 45.0, "Pitch": -30.0}
    for name, value in examples.items():
        joint = model.joint(name)
        assert joint is not None and joint.clamp(value) == value
    for joint in model.joints:  # the demos move +-25 degrees around zero
        assert joint.clamp(25.0) == 25.0 and joint.clamp(-25.0) == -25.0


@given(st.floats(-90, 90, allow_nan=False))
def test_degrees_and_radians_round_trip(degrees: float) -> None:
    for joint in load_robot_model("so-arm100").joints:
        assert joint.from_urdf(joint.to_urdf(degrees)) == pytest.approx(degrees, abs=1e-9)


def test_urdf_limits_match_the_reference_urdf() -> None:
    shared = shared_dir()
    if shared is None or not (shared / REFERENCE_URDF).exists():
        missing(f"shared/{REFERENCE_URDF} is not beside the repository (or at ARENA_SHARED)")
    text = (shared / REFERENCE_URDF).read_text()
    model = load_robot_model("so-arm100")
    for joint in model.joints:
        block = text.split(f'<joint name="{joint.aliases[0]}"', 1)[1]
        lower, upper = (
            float(x) for x in re.search(r'lower="([^"]+)" upper="([^"]+)"', block).groups()
        )  # type: ignore[union-attr]
        assert joint.to_urdf(joint.lower) == pytest.approx(lower, abs=1e-6)
        assert joint.to_urdf(joint.upper) == pytest.approx(upper, abs=1e-6)


def test_spec_joint_table_matches_the_model() -> None:
    text = (SPECS / "robot-model.md").read_text()
    rows = [line for line in text.splitlines() if line.startswith("| ") and "|---" not in line]
    table = {
        cells[0]: cells for cells in ([c.strip() for c in r.strip("|").split("|")] for r in rows)
    }
    for joint in load_robot_model("so-arm100").joints:
        cells = table[joint.name]
        assert cells[1] == ", ".join(joint.aliases)
        assert int(cells[2]) == joint.servo_id
        assert float(cells[4]) == pytest.approx(joint.lower, abs=0.05)
        assert float(cells[5]) == pytest.approx(joint.upper, abs=0.05)
        assert float(cells[6]) == pytest.approx(joint.max_velocity, abs=0.05)


def test_safety_defaults() -> None:
    policy = load_robot_model("so-arm100").safety
    assert policy.loss_policy is LossPolicy.ESTOP
    assert policy.command_rate == 100.0
    assert policy.estop_severity is Severity.CRITICAL


def test_unknown_robot_type() -> None:
    with pytest.raises(ArenaError) as info:
        load_robot_model("no-such-arm")
    assert info.value.code is ErrorCode.UNKNOWN_ROBOT_TYPE
    assert "so-arm100" in info.value.message


TWO_JOINT_URDF = """<?xml version="1.0"?>
<robot name="pan-tilt">
  <link name="base"/><link name="pan_link"/><link name="tilt_link"/>
  <joint name="pan" type="revolute">
    <parent link="base"/><child link="pan_link"/><axis xyz="0 0 1"/>
    <limit lower="-1.0" upper="1.0" effort="1" velocity="2.0"/>
  </joint>
  <joint name="tilt" type="revolute">
    <parent link="pan_link"/><child link="tilt_link"/><axis xyz="0 1 0"/>
    <limit lower="0.0" upper="1.0" effort="1" velocity="1.0"/>
  </joint>
</robot>
"""

TWO_JOINT_CONFIG = """
description = "a pan-tilt head"
urdf = "pan-tilt.urdf"
[safety]
loss_policy = "hold"
command_rate = 20
[[joints]]
name = "Pan"
urdf_joint = "pan"
servo_id = 7
aliases = ["yaw"]
neutral = 0.0
[[joints]]
name = "Tilt"
urdf_joint = "tilt"
servo_id = 8
neutral = 0.0
upper = 45.0
max_velocity = 30.0
max_acceleration = 120.0
max_jerk = 2400.0
"""


def _write_type(root: Path, urdf: str, config: str) -> Path:
    folder = root / "pan-tilt"
    folder.mkdir(parents=True)
    (folder / "pan-tilt.urdf").write_text(urdf)
    (folder / "robot.toml").write_text(config)
    return folder


def test_a_new_robot_type_is_a_folder(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    _write_type(tmp_path, TWO_JOINT_URDF, TWO_JOINT_CONFIG)
    monkeypatch.setenv(TYPES_PATH_ENV, str(tmp_path))
    assert "pan-tilt" in list_robot_types() and "so-arm100" in list_robot_types()
    model = load_robot_model("pan-tilt")
    assert model.joint_names == ("Pan", "Tilt")
    assert model.joint("yaw") is model.joint("Pan")
    tilt = model.joint("Tilt")
    assert tilt is not None
    assert (tilt.lower, tilt.upper) == (0.0, 45.0)  # soft upper limit narrows the URDF's 57.3
    assert tilt.max_velocity == 30.0
    assert (tilt.max_acceleration, tilt.max_jerk) == (120.0, 2400.0)  # the trajectory's limits
    pan = model.joint("Pan")
    assert pan is not None  # unset: full speed in 1/30 s, full acceleration in 1/200 s
    assert pan.max_acceleration == 30 * pan.max_velocity
    assert pan.max_jerk == 200 * pan.max_acceleration
    assert model.safety.loss_policy is LossPolicy.HOLD
    assert model.safety.command_rate == 20.0
    assert model.safety.join_speed == 15.0  # the default when a type does not say
    assert load_robot_model("so-arm100").safety.join_speed == 15.0


@pytest.mark.parametrize(
    ("urdf", "config", "fragment"),
    [
        (TWO_JOINT_URDF, TWO_JOINT_CONFIG.replace("upper = 45.0", "upper = 90.0"), "soft limits"),
        (
            TWO_JOINT_URDF,
            TWO_JOINT_CONFIG.replace('urdf_joint = "tilt"', 'urdf_joint = "x"'),
            "not a revolute joint",
        ),
        (
            TWO_JOINT_URDF,
            TWO_JOINT_CONFIG.replace("max_velocity = 30.0", "max_velocity = 300.0"),
            "max_velocity",
        ),
        (
            TWO_JOINT_URDF,
            TWO_JOINT_CONFIG.replace("max_jerk = 2400.0", "max_jerk = -1.0"),
            "max_jerk must be a positive number",
        ),
        (
            TWO_JOINT_URDF,
            TWO_JOINT_CONFIG.replace("max_acceleration = 120.0", "max_acceleration = nan"),
            "max_acceleration must be a positive number",
        ),
        (
            TWO_JOINT_URDF,
            TWO_JOINT_CONFIG.replace('loss_policy = "hold"', 'loss_policy = "pray"'),
            "[safety]",
        ),
        (
            TWO_JOINT_URDF,
            TWO_JOINT_CONFIG.replace("command_rate = 20", "command_rate = 20\njoin_speed = 0"),
            "join_speed",
        ),
        (
            TWO_JOINT_URDF,
            TWO_JOINT_CONFIG.replace("command_rate = 20", "command_rate = 20\njoin_speed = 200"),
            "join_speed",
        ),
        (
            TWO_JOINT_URDF,
            TWO_JOINT_CONFIG.replace('aliases = ["yaw"]', 'aliases = ["tilt"]'),
            "unique",
        ),
        (TWO_JOINT_URDF, "this is = = not toml", "cannot read"),
        ("<robot", TWO_JOINT_CONFIG, "cannot parse URDF"),
    ],
)
def test_broken_robot_types_are_refused_with_a_reason(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, urdf: str, config: str, fragment: str
) -> None:
    _write_type(tmp_path, urdf, config)
    monkeypatch.setenv(TYPES_PATH_ENV, str(tmp_path))
    with pytest.raises(ArenaError) as info:
        load_robot_model("pan-tilt")
    assert info.value.code is ErrorCode.INVALID_CONFIG
    assert fragment in info.value.message


def test_a_copied_type_folder_loads_under_its_own_name(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    shutil.copytree(BUILTIN_TYPES_DIR / "so-arm100", tmp_path / "so-arm100-left")
    monkeypatch.setenv(TYPES_PATH_ENV, str(tmp_path))
    model = load_robot_model("so-arm100-left")
    assert model.robot_type == "so-arm100-left"
    assert len(model.joints) == 6


def test_the_koch_table_in_the_spec_matches_its_robot_type() -> None:
    text = (SPECS / "robot-model.md").read_text()
    section = text[text.index("## koch") : text.index("## Robot types")]
    rows = [line for line in section.splitlines() if line.startswith("| ") and "|---" not in line]
    table = {
        cells[0]: cells for cells in ([c.strip() for c in r.strip("|").split("|")] for r in rows)
    }
    model = load_robot_model("koch")
    assert model.bus.family == "dynamixel"
    for joint in model.joints:
        cells = table[joint.name]
        assert int(cells[1]) == joint.servo_id
        assert cells[2] == joint.servo_model.upper()
        assert cells[3] == joint.unit
        assert float(cells[4].split()[0]) == pytest.approx(joint.neutral, abs=0.001)
        assert float(cells[5]) == pytest.approx(joint.lower, abs=0.05)
        assert float(cells[6]) == pytest.approx(joint.upper, abs=0.05)
        assert float(cells[7]) == pytest.approx(joint.max_velocity, abs=0.05)
