"""Forward kinematics of a URDF tree: pure functions of joint values, no I/O after loading.

Poses are (rotation quaternion (x, y, z, w), translation (x, y, z)) pairs in metres, the form
Foxglove's `FrameTransform` and most collision code want. The URDF is read with the standard
library's XML parser: this runs in the recording process and the collision guard, where
yourdfpy's import (trimesh, scipy: ~0.6 s) is not worth paying.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ElementTree
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

Quaternion = tuple[float, float, float, float]  # x, y, z, w
Vector = tuple[float, float, float]
Pose = tuple[Quaternion, Vector]

IDENTITY: Pose = ((0.0, 0.0, 0.0, 1.0), (0.0, 0.0, 0.0))


def quaternion_multiply(a: Quaternion, b: Quaternion) -> Quaternion:
    """The rotation `a` after `b` (Hamilton product a * b)."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    )


def rotate(q: Quaternion, v: Vector) -> Vector:
    """The vector `v` rotated by the unit quaternion `q`."""
    x, y, z, w = q
    vx, vy, vz = v
    # v + 2w (u x v) + 2 u x (u x v), with u the quaternion's vector part
    cx = y * vz - z * vy
    cy = z * vx - x * vz
    cz = x * vy - y * vx
    return (
        vx + 2.0 * (w * cx + y * cz - z * cy),
        vy + 2.0 * (w * cy + z * cx - x * cz),
        vz + 2.0 * (w * cz + x * cy - y * cx),
    )


def compose(a: Pose, b: Pose) -> Pose:
    """The pose `b` expressed in the frame where `a` is given (a * b)."""
    qa, ta = a
    qb, tb = b
    moved = rotate(qa, tb)
    return quaternion_multiply(qa, qb), (ta[0] + moved[0], ta[1] + moved[1], ta[2] + moved[2])


def axis_angle(axis: Vector, angle: float) -> Quaternion:
    """The rotation by `angle` radians about the unit vector `axis`."""
    s = math.sin(angle / 2.0)
    return (axis[0] * s, axis[1] * s, axis[2] * s, math.cos(angle / 2.0))


def from_rpy(roll: float, pitch: float, yaw: float) -> Quaternion:
    """URDF's fixed-axis roll (X), then pitch (Y), then yaw (Z)."""
    qx = axis_angle((1.0, 0.0, 0.0), roll)
    qy = axis_angle((0.0, 1.0, 0.0), pitch)
    qz = axis_angle((0.0, 0.0, 1.0), yaw)
    return quaternion_multiply(qz, quaternion_multiply(qy, qx))


def to_matrix(pose: Pose) -> list[list[float]]:
    """The 4x4 homogeneous matrix of a pose (for comparisons and other libraries)."""
    (x, y, z, w), (tx, ty, tz) = pose
    return [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w), tx],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w), ty],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y), tz],
        [0.0, 0.0, 0.0, 1.0],
    ]


@dataclass(frozen=True, slots=True)
class UrdfJoint:
    """One joint of the tree: where its child sits on its parent, and how it moves."""

    name: str
    kind: str  # revolute, continuous, prismatic or fixed
    parent: str
    child: str
    origin: Pose
    axis: Vector

    def transform(self, value: float) -> Pose:
        """The child's pose in the parent's frame at joint value `value` (rad or m)."""
        rotation, translation = self.origin
        if self.kind in ("revolute", "continuous"):
            return quaternion_multiply(rotation, axis_angle(self.axis, value)), translation
        if self.kind == "prismatic":
            shift = rotate(
                rotation, (self.axis[0] * value, self.axis[1] * value, self.axis[2] * value)
            )
            return rotation, (
                translation[0] + shift[0],
                translation[1] + shift[1],
                translation[2] + shift[2],
            )
        return self.origin


@dataclass(frozen=True)
class Kinematics:
    """A URDF's kinematic tree, joints ordered parents first."""

    root: str
    joints: tuple[UrdfJoint, ...]

    @classmethod
    def from_urdf(cls, source: str | Path) -> Kinematics:
        """Read the tree from a URDF file (a path) or its text (a string holding XML)."""
        text = source if isinstance(source, str) and "<robot" in source else None
        element = (
            ElementTree.fromstring(text)
            if text is not None
            else ElementTree.parse(Path(source)).getroot()
        )
        # The robot's own children only: a <transmission> names joints too.
        joints = [_joint(node) for node in element.findall("joint")]
        links = [node.get("name", "") for node in element.findall("link")]
        children = {joint.child for joint in joints}
        roots = [link for link in links if link not in children]
        if len(roots) != 1:
            raise ValueError(f"a URDF tree needs exactly one root link, found {roots}")
        ordered: list[UrdfJoint] = []
        reached = {roots[0]}
        pending = list(joints)
        while pending:
            ready = [joint for joint in pending if joint.parent in reached]
            if not ready:
                raise ValueError("the URDF's joints do not form a tree from its root")
            for joint in ready:
                ordered.append(joint)
                reached.add(joint.child)
                pending.remove(joint)
        return cls(roots[0], tuple(ordered))

    @property
    def links(self) -> tuple[str, ...]:
        """Every link, the root first."""
        return (self.root, *(joint.child for joint in self.joints))

    def joint_transforms(self, values: Mapping[str, float]) -> list[tuple[UrdfJoint, Pose]]:
        """Each joint with its child's pose in its parent's frame; joints missing from
        `values` stand at 0."""
        return [(joint, joint.transform(values.get(joint.name, 0.0))) for joint in self.joints]

    def link_poses(self, values: Mapping[str, float]) -> dict[str, Pose]:
        """Every link's pose in the root link's frame."""
        poses: dict[str, Pose] = {self.root: IDENTITY}
        for joint, local in self.joint_transforms(values):
            poses[joint.child] = compose(poses[joint.parent], local)
        return poses


def parse_triple(text: str | None, default: Vector) -> Vector:
    """Three numbers of a URDF attribute (`xyz`, `rpy`, `scale`), or `default` if absent."""
    if not text:
        return default
    values = [float(part) for part in text.split()]
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise ValueError(f"expected three finite numbers, got {text!r}")
    return values[0], values[1], values[2]


def _joint(node: ElementTree.Element) -> UrdfJoint:
    origin = node.find("origin")
    xyz = parse_triple(None if origin is None else origin.get("xyz"), (0.0, 0.0, 0.0))
    rpy = parse_triple(None if origin is None else origin.get("rpy"), (0.0, 0.0, 0.0))
    axis_node = node.find("axis")
    axis = parse_triple(None if axis_node is None else axis_node.get("xyz"), (1.0, 0.0, 0.0))
    norm = math.sqrt(sum(c * c for c in axis)) or 1.0
    parent, child = node.find("parent"), node.find("child")
    if parent is None or child is None:
        raise ValueError(f"joint {node.get('name')!r} needs a parent and a child")
    return UrdfJoint(
        name=node.get("name", ""),
        kind=node.get("type", "fixed"),
        parent=parent.get("link", ""),
        child=child.get("link", ""),
        origin=(from_rpy(*rpy), xyz),
        axis=(axis[0] / norm, axis[1] / norm, axis[2] / norm),
    )
