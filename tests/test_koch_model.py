"""The Koch's model against the Koch v1.1's own CAD: its joint origins and axes are those of the
follower's SolidWorks URDF, its links' shapes the bounds of the CAD's printed parts and servos,
and its zero the CAD's assembly pose (upper arm up, forearm and hand level), which is where
LeRobot's degrees put 0 (the middle of each joint's range). A pose near that middle, as a real
arm reads it, is well clear of the table (issue 57: it used to put the hand in it)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from arena.robot import collision
from arena.robot.kinematics import Kinematics
from arena.robot.meshes import link_vertices
from arena.robot.model import load_robot_model

URDF = Path(__file__).resolve().parent.parent / "arena" / "robot_types" / "koch" / "koch.urdf"

#: The Koch v1.1 follower's URDF (SolidWorks export, `simulation/follower.urdf` of the Koch
#: v1.1 repository; Menagerie's low_cost_robot_arm repeats it): each joint's origin in its
#: parent link (metres) and its axis, up to sign (Menagerie turns two).
CAD_JOINTS = {
    "shoulder_pan": ((0.012, 0.0, 0.0409), (0, 0, 1)),
    "shoulder_lift": ((0.0, -0.0209, 0.0154), (0, 1, 0)),
    "elbow_flex": ((-0.0148, 0.0065, 0.1083), (0, 1, 0)),
    "wrist_flex": ((-0.10048, 0.00005, 0.0026999), (0, 1, 0)),
    "wrist_roll": ((-0.045, 0.013097, 0.0), (1, 0, 0)),
    "gripper": ((-0.01315, -0.0075, 0.0145), (0, 0, 1)),
}

#: Each link's extent in its own frame (metres, low and high corners) on that export's meshes,
#: printed part and servo together (`base_link.STL` with `base_link_motor.STL`, ...).
CAD_BOUNDS = {
    "base_link": ((0.0, -0.0675, 0.0), (0.08, 0.091, 0.0409)),
    "shoulder": ((-0.0143, -0.0209, -0.0019), (0.0383, 0.02, 0.0297)),
    "upper_arm": ((-0.0243, -0.0011, -0.0129), (0.013, 0.0429, 0.119)),
    "forearm": ((-0.11, -0.0031, -0.0085), (0.0084, 0.032, 0.0145)),
    "wrist": ((-0.045, -0.0033, -0.011), (0.009, 0.0387, 0.011)),
    "hand": ((-0.0689, -0.0175, -0.0148), (0.0, 0.0202, 0.0148)),
    "jaw": ((-0.0557, -0.0079, -0.0322), (0.0083, 0.0131, 0.0033)),
}

#: Issue 57's arm, read on its bus near the middle of its calibrated range (degrees).
NORMAL_POSE = {"shoulder_lift": -10.0, "elbow_flex": 12.5, "wrist_flex": -7.5}


def test_joint_origins_and_axes_are_the_cads() -> None:
    joints = {joint.name: joint for joint in Kinematics.from_urdf(URDF).joints}
    for name, (origin, axis) in CAD_JOINTS.items():
        assert joints[name].origin[1] == pytest.approx(origin, abs=1e-6), name
        assert [abs(a) for a in joints[name].axis] == pytest.approx(list(axis)), name


def test_each_links_shape_spans_the_cads_part_and_servo() -> None:
    vertices = link_vertices(URDF)
    assert set(vertices) == set(CAD_BOUNDS)
    for link, (low, high) in CAD_BOUNDS.items():
        points = vertices[link]
        assert points.min(axis=0) == pytest.approx(low, abs=1e-4), link
        assert points.max(axis=0) == pytest.approx(high, abs=1e-4), link


def test_zero_is_the_cads_assembly_pose() -> None:
    """0 degrees on every arm joint is the CAD's own pose: the upper arm stands straight up
    from the lift axis, the forearm and the hand lie level, reaching out along -x."""
    model = load_robot_model("koch")
    zero = {j.urdf_name: j.to_urdf(0.0) for j in model.joints if j.unit == "deg"}
    assert all(value == pytest.approx(0.0) for value in zero.values())
    for joint in model.joints:  # LeRobot's degrees: 0 is the middle of the range
        if joint.unit == "deg":
            assert joint.lower == pytest.approx(-joint.upper), joint.name
    poses = Kinematics.from_urdf(URDF).link_poses(zero)
    lift, elbow, wrist = (poses[link][1] for link in ("upper_arm", "forearm", "wrist"))
    assert elbow[0] == pytest.approx(lift[0] - 0.0148, abs=1e-6)  # the elbow above the lift
    assert elbow[2] - lift[2] == pytest.approx(0.1083, abs=1e-6)
    assert wrist[2] == pytest.approx(elbow[2] + 0.0027, abs=1e-4)  # the forearm level
    assert wrist[0] < elbow[0] - 0.1


def _lowest(values: dict[str, float]) -> dict[str, float]:
    """Each moving link's lowest capsule point above the table (metres) at wire `values`."""
    model = load_robot_model("koch")
    guard = collision.for_model(model)
    assert guard is not None
    urdf = {j.urdf_name: j.to_urdf(values.get(j.name, 0.0)) for j in model.joints}
    placed = guard.placed(urdf)
    return {
        capsule.link: min(a[2], b[2]) - radius
        for capsule, (a, b, radius) in zip(guard.capsules, placed, strict=True)
        if capsule.link != "base_link"
    }


def test_a_normal_pose_is_well_clear_of_the_table() -> None:
    """Issue 57: at shoulder_lift -10, elbow_flex 12.5, wrist_flex -7.5 the old model had the
    hand 5 cm inside the table. The arm stands there with its hand about 4 cm above it (the
    gripper points some 30 degrees down), and every link above the base clears the table."""
    model = load_robot_model("koch")
    guard = collision.for_model(model)
    assert guard is not None
    lowest = _lowest(NORMAL_POSE)
    assert min(lowest.values()) > 0.01, lowest
    assert min(lowest["hand"], lowest["jaw"]) > 0.03, lowest
    start = {j.urdf_name: j.to_urdf(NORMAL_POSE.get(j.name, 0.0)) for j in model.joints}
    goal = {**start, "shoulder_pan": start["shoulder_pan"] + math.radians(5)}
    hit, _, _ = guard.path_hit(start, goal, model.workspace)
    assert hit is None


def test_the_capsules_hold_the_cads_corners() -> None:
    """Every corner of a link's CAD bounds lies inside its capsule or within the box's own
    slack: the capsule is fitted to the boxes, so no corner of them is outside."""
    guard = collision.for_model(load_robot_model("koch"))
    assert guard is not None
    for capsule in guard.capsules:
        a, b = np.asarray(capsule.a), np.asarray(capsule.b)
        for corner in link_vertices(URDF)[capsule.link]:
            t = np.clip(np.dot(corner - a, b - a) / max(np.dot(b - a, b - a), 1e-12), 0, 1)
            assert np.linalg.norm(corner - (a + t * (b - a))) <= capsule.radius + 1e-9
