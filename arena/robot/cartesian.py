"""Where the hand is and which joints put it somewhere: forward and inverse kinematics of the
chain from a robot type's root link to its end effector (`[end_effector]` in robot.toml).

Pure functions of joint values in the wire's units (degrees, or percent for a gripper), no I/O.
Poses are metres in the root link's frame and unit quaternions (x, y, z, w). The inverse is
damped least squares (Levenberg-Marquardt) on the chain's geometric Jacobian, started from the
pose the caller gives (the arm's current one), the joints kept inside their limits at every
step; a few other starts are tried only when that one fails. See specs/cartesian.md.
"""

from __future__ import annotations

import functools
import math
import random
from collections.abc import Mapping
from dataclasses import dataclass

from arena.robot.kinematics import Kinematics, Quaternion, Vector
from arena.robot.model import JointSpec, RobotModel

#: A pose counts as reached within this far (metres) of the target...
POSITION_TOLERANCE = 0.0005
#: ... and, when an orientation is asked for, within this angle (radians, about 0.5 degree).
ANGLE_TOLERANCE = math.radians(0.5)
#: Metres one radian of orientation error weighs as, where both are asked for.
ORIENTATION_WEIGHT = 0.1
#: Iterations of one start, and the starts tried in all (the caller's first).
MAX_ITERATIONS = 80
MAX_STARTS = 8  # six left the Koch stretched up and back (its whole lift range) unsolved
#: The largest step of one joint in one iteration (radians): keeps a step near a singularity
#: from swinging the arm across its range.
MAX_STEP = 0.35


@dataclass(frozen=True, slots=True)
class HandPose:
    """The hand's pose: tool point (metres), orientation (x, y, z, w) and the gripper's wire
    value (None: the robot type names no gripper, or its value is not known)."""

    position: Vector
    orientation: Quaternion
    gripper: float | None


@dataclass(frozen=True, slots=True)
class Solution:
    """What the inverse kinematics found: joint values (wire units) of the chain, how far the
    hand they give is from the target, and whether that is within the tolerances."""

    joints: dict[str, float]
    distance: float  # metres
    angle: float  # radians (0 when no orientation was asked for)
    reached: bool
    iterations: int


Matrix = tuple[float, float, float, float, float, float, float, float, float]  # row-major 3x3
_IDENTITY: Matrix = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)


@dataclass(frozen=True, slots=True)
class _Joint:
    spec: JointSpec
    turn: Matrix  # the fixed rotation from the previous joint's frame to this one's
    shift: Vector  # ... and translation (previous joint's frame)
    axis: Vector  # unit vector in the joint's frame
    low: float  # limits in URDF radians
    high: float

    def rotation(self, angle: float) -> Matrix:
        """The fixed rotation, then the joint's own turn by `angle` (Rodrigues' formula)."""
        x, y, z = self.axis
        s, c = math.sin(angle), math.cos(angle)
        v = 1.0 - c
        own = (
            c + x * x * v, x * y * v - z * s, x * z * v + y * s,
            y * x * v + z * s, c + y * y * v, y * z * v - x * s,
            z * x * v - y * s, z * y * v + x * s, c + z * z * v,
        )  # fmt: skip
        return _multiply(self.turn, own)


class Hand:
    """The kinematic chain of one robot type, from its root link to its end effector.

    Pure Python floats: for a chain of five or six joints, numpy's per-call cost (microseconds
    for each 3x3 product) is many times the arithmetic."""

    def __init__(self, model: RobotModel) -> None:
        effector = model.end_effector
        if effector is None:
            raise ValueError(f"robot type {model.robot_type!r} names no [end_effector]")
        self.model = model
        self.link = effector.link
        tree = Kinematics.from_urdf(model.urdf_path)
        self.root = tree.root
        by_child = {joint.child: joint for joint in tree.joints}
        path = []
        link = effector.link
        while link != tree.root:
            path.append(by_child[link])
            link = by_child[link].parent
        path.reverse()
        specs = {spec.urdf_name: spec for spec in model.joints}
        joints: list[_Joint] = []
        turn, shift = _IDENTITY, (0.0, 0.0, 0.0)  # fixed transforms not yet folded in
        for urdf_joint in path:
            rotation, translation = urdf_joint.origin
            shift = _add(shift, _apply(turn, translation))
            turn = _multiply(turn, _matrix(rotation))
            spec = specs.get(urdf_joint.name)
            if urdf_joint.kind not in ("revolute", "continuous") or spec is None:
                continue  # fixed (or driven by nothing Arena commands): stays at its zero
            low, high = sorted((spec.to_urdf(spec.lower), spec.to_urdf(spec.upper)))
            joints.append(_Joint(spec, turn, shift, urdf_joint.axis, low, high))
            turn, shift = _IDENTITY, (0.0, 0.0, 0.0)
        self._joints = tuple(joints)
        self._tail = (turn, _add(shift, _apply(turn, effector.offset)))
        self._gripper = model.joint(effector.gripper) if effector.gripper else None
        #: Protocol names of the joints that move the hand, root first.
        self.joint_names = tuple(j.spec.name for j in joints)

    @property
    def gripper(self) -> JointSpec | None:
        """The joint that opens and closes the hand, if the robot type names one."""
        return self._gripper

    @functools.cached_property
    def reach(self) -> float:
        """A bound of how far the tool point can be from the first joint (metres)."""
        lengths = [math.hypot(*j.shift) for j in self._joints[1:]]
        return sum(lengths) + math.hypot(*self._tail[1])

    @functools.cached_property
    def shoulder(self) -> Vector:
        """Where the first joint's axis passes (metres, root frame)."""
        return self._joints[0].shift

    # -- forward ------------------------------------------------------------------------------

    def pose(self, values: Mapping[str, float]) -> HandPose | None:
        """The hand's pose at joint values `values` (wire units, by protocol name); None if a
        joint of the chain is missing."""
        try:
            q = [j.spec.to_urdf(values[j.spec.name]) for j in self._joints]
        except KeyError:
            return None
        rotation, position, _, _ = self._forward(q)
        gripper = None if self._gripper is None else values.get(self._gripper.name)
        return HandPose(position, _quaternion(rotation), gripper)

    def _forward(self, q: list[float]) -> tuple[Matrix, Vector, list[Vector], list[Vector]]:
        """The tool's rotation and position at URDF values `q`, and each joint's origin and
        axis (root frame)."""
        rotation, position = _IDENTITY, (0.0, 0.0, 0.0)
        origins: list[Vector] = []
        axes: list[Vector] = []
        for joint, angle in zip(self._joints, q, strict=True):
            position = _add(position, _apply(rotation, joint.shift))
            frame = _multiply(rotation, joint.turn)
            origins.append(position)
            axes.append(_apply(frame, joint.axis))
            rotation = _multiply(rotation, joint.rotation(angle))
        turn, shift = self._tail
        return _multiply(rotation, turn), _add(position, _apply(rotation, shift)), origins, axes

    # -- inverse ------------------------------------------------------------------------------

    def solve(
        self,
        position: Vector,
        orientation: Quaternion | None,
        start: Mapping[str, float],
        starts: int = MAX_STARTS,
        iterations: int = MAX_ITERATIONS,
    ) -> Solution:
        """Joint values (wire units) that put the tool point at `position` and, if given, the
        hand at `orientation`, found from `start` (wire values by name; a joint missing there
        starts at 0). Other starts are tried only if that one does not reach; the best found
        is returned either way (`reached` says which)."""
        rotation = None if orientation is None else _matrix(orientation)
        q = [self._clip(k, j.spec.to_urdf(start.get(j.spec.name, 0.0))) for k, j in self._enum]
        best: tuple[float, list[float], float, float] | None = None
        used = 0
        first = q
        randomly = random.Random(58)  # the other starts: the same ones on every call
        for attempt in range(starts):
            if attempt == 1:
                q = self._facing(first, position)
            elif attempt > 1:  # anywhere, and every other one turned to face the target
                q = [randomly.uniform(j.low, j.high) for j in self._joints]
                q = self._facing(q, position) if attempt % 2 else q
            q, distance, angle, taken = self._descend(q, position, rotation, iterations)
            used += taken
            score = distance + ORIENTATION_WEIGHT * angle
            if best is None or score < best[0]:
                best = (score, q, distance, angle)
            if distance <= POSITION_TOLERANCE and angle <= ANGLE_TOLERANCE:
                break
        assert best is not None
        _, q, distance, angle = best
        joints = {
            j.spec.name: j.spec.clamp(j.spec.from_urdf(v))
            for j, v in zip(self._joints, q, strict=True)
        }
        reached = distance <= POSITION_TOLERANCE and angle <= ANGLE_TOLERANCE
        return Solution(joints, distance, angle, reached, used)

    def _facing(self, q: list[float], target: Vector) -> list[float]:
        """`q` with its first joint turned so that the tool point is on the target's side of
        it (the arm's pan: where local descent most often stalls against a limit)."""
        _, tool, origins, axes = self._forward(q)
        axis, origin = axes[0], origins[0]

        def across(point: Vector) -> Vector:  # the part of point - origin across the axis
            d = _sub(point, origin)
            along = d[0] * axis[0] + d[1] * axis[1] + d[2] * axis[2]
            return _sub(d, (along * axis[0], along * axis[1], along * axis[2]))

        a, b = across(tool), across(target)
        if math.hypot(*a) < 1e-6 or math.hypot(*b) < 1e-6:
            return q
        c = _cross(a, b)
        turn = math.atan2(
            c[0] * axis[0] + c[1] * axis[1] + c[2] * axis[2],
            a[0] * b[0] + a[1] * b[1] + a[2] * b[2],
        )
        return [self._clip(0, q[0] + turn), *q[1:]]

    @functools.cached_property
    def _enum(self) -> tuple[tuple[int, _Joint], ...]:
        return tuple(enumerate(self._joints))

    def _clip(self, k: int, value: float) -> float:
        joint = self._joints[k]
        return min(joint.high, max(joint.low, value))

    def _descend(
        self, q: list[float], target: Vector, rotation: Matrix | None, iterations: int
    ) -> tuple[list[float], float, float, int]:
        """Levenberg-Marquardt from `q`: the values it ends at, their distance and angle to the
        target, and the iterations it took."""
        damping = 0.01
        error, jacobian, distance, angle = self._residual(q, target, rotation)
        cost = sum(e * e for e in error)
        for iteration in range(1, iterations + 1):
            if distance <= POSITION_TOLERANCE / 10 and angle <= ANGLE_TOLERANCE / 10:
                return q, distance, angle, iteration
            step = self._step(q, jacobian, error, damping)
            largest = max(abs(s) for s in step)
            scale = MAX_STEP / largest if largest > MAX_STEP else 1.0
            moved = zip(q, step, strict=True)
            trial = [self._clip(k, v + scale * s) for k, (v, s) in enumerate(moved)]
            t_error, t_jacobian, t_distance, t_angle = self._residual(trial, target, rotation)
            t_cost = sum(e * e for e in t_error)
            if t_cost < cost:
                gain = cost - t_cost
                q, error, jacobian, cost = trial, t_error, t_jacobian, t_cost
                distance, angle = t_distance, t_angle
                damping = max(damping / 2, 1e-4)
                if gain < 1e-14:
                    return q, distance, angle, iteration  # stalled: as near as it gets
            else:
                damping *= 4
                if damping > 1e3:
                    return q, distance, angle, iteration  # no step helps: a local minimum
        return q, distance, angle, iterations

    def _step(
        self, q: list[float], jacobian: list[list[float]], error: list[float], damping: float
    ) -> list[float]:
        """The damped step, solved again without each joint it would push past a limit it
        stands at (a clipped step is no longer downhill: the others must make up for it)."""
        step = _damped_step(jacobian, error, damping)
        for _ in range(len(q)):
            pinned = [
                k
                for k, (v, s) in enumerate(zip(q, step, strict=True))
                if (s > 0 and v >= self._joints[k].high - 1e-9)
                or (s < 0 and v <= self._joints[k].low + 1e-9)
            ]
            if not pinned:
                return step
            free = [[0.0 if k in pinned else c for k, c in enumerate(row)] for row in jacobian]
            step = _damped_step(free, error, damping)
            jacobian = free
        return step

    def _residual(
        self, q: list[float], target: Vector, rotation: Matrix | None
    ) -> tuple[list[float], list[list[float]], float, float]:
        """The weighted error to the target, its Jacobian (rows), the distance and angle left."""
        frame, tool, origins, axes = self._forward(q)
        columns = [_cross(a, _sub(tool, o)) for a, o in zip(axes, origins, strict=True)]
        offset = _sub(target, tool)
        distance = math.hypot(*offset)
        rows = [[c[i] for c in columns] for i in range(3)]
        if rotation is None:
            return list(offset), rows, distance, 0.0
        turn = _rotation_vector(_multiply(rotation, _transpose(frame)))
        angle = math.hypot(*turn)
        w = ORIENTATION_WEIGHT
        rows += [[w * a[i] for a in axes] for i in range(3)]
        return [*offset, w * turn[0], w * turn[1], w * turn[2]], rows, distance, angle


def _damped_step(rows: list[list[float]], error: list[float], damping: float) -> list[float]:
    """J^T (J J^T + damping^2 I)^-1 e, by Gaussian elimination (J is 3 or 6 rows)."""
    m, n = len(rows), len(rows[0])
    square = [
        [sum(rows[i][k] * rows[j][k] for k in range(n)) for j in range(m)] + [error[i]]
        for i in range(m)
    ]
    for i in range(m):
        square[i][i] += damping * damping
    for i in range(m):  # positive definite: no pivoting needed
        pivot = square[i][i]
        for r in range(i + 1, m):
            factor = square[r][i] / pivot
            if factor:
                row, top = square[r], square[i]
                for c in range(i, m + 1):
                    row[c] -= factor * top[c]
    y = [0.0] * m
    for i in range(m - 1, -1, -1):
        y[i] = (square[i][m] - sum(square[i][c] * y[c] for c in range(i + 1, m))) / square[i][i]
    return [sum(rows[i][k] * y[i] for i in range(m)) for k in range(n)]


def _multiply(a: Matrix, b: Matrix) -> Matrix:
    a0, a1, a2, a3, a4, a5, a6, a7, a8 = a
    b0, b1, b2, b3, b4, b5, b6, b7, b8 = b
    return (
        a0 * b0 + a1 * b3 + a2 * b6, a0 * b1 + a1 * b4 + a2 * b7, a0 * b2 + a1 * b5 + a2 * b8,
        a3 * b0 + a4 * b3 + a5 * b6, a3 * b1 + a4 * b4 + a5 * b7, a3 * b2 + a4 * b5 + a5 * b8,
        a6 * b0 + a7 * b3 + a8 * b6, a6 * b1 + a7 * b4 + a8 * b7, a6 * b2 + a7 * b5 + a8 * b8,
    )  # fmt: skip


def _transpose(a: Matrix) -> Matrix:
    return (a[0], a[3], a[6], a[1], a[4], a[7], a[2], a[5], a[8])


def _apply(a: Matrix, v: Vector) -> Vector:
    x, y, z = v
    return (
        a[0] * x + a[1] * y + a[2] * z,
        a[3] * x + a[4] * y + a[5] * z,
        a[6] * x + a[7] * y + a[8] * z,
    )


def _add(a: Vector, b: Vector) -> Vector:
    return a[0] + b[0], a[1] + b[1], a[2] + b[2]


def _sub(a: Vector, b: Vector) -> Vector:
    return a[0] - b[0], a[1] - b[1], a[2] - b[2]


def _cross(a: Vector, b: Vector) -> Vector:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


@functools.lru_cache(maxsize=32)
def hand_for(model: RobotModel) -> Hand | None:
    """The hand of a robot type (built once), or None if its robot.toml names none."""
    return None if model.end_effector is None else Hand(model)


def _matrix(q: Quaternion) -> Matrix:
    x, y, z, w = q
    return (
        1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
        2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
        2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
    )  # fmt: skip


def _quaternion(r: Matrix) -> Quaternion:
    """The unit quaternion (x, y, z, w, w >= 0) of a rotation matrix (Shepperd's method)."""
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = r
    trace = r00 + r11 + r22
    if trace > 0:
        s = 2.0 * math.sqrt(trace + 1.0)
        q = ((r21 - r12) / s, (r02 - r20) / s, (r10 - r01) / s, s / 4)
    elif r00 > r11 and r00 > r22:
        s = 2.0 * math.sqrt(1.0 + r00 - r11 - r22)
        q = (s / 4, (r01 + r10) / s, (r02 + r20) / s, (r21 - r12) / s)
    elif r11 > r22:
        s = 2.0 * math.sqrt(1.0 + r11 - r00 - r22)
        q = ((r01 + r10) / s, s / 4, (r12 + r21) / s, (r02 - r20) / s)
    else:
        s = 2.0 * math.sqrt(1.0 + r22 - r00 - r11)
        q = ((r02 + r20) / s, (r12 + r21) / s, s / 4, (r10 - r01) / s)
    sign = -1.0 if q[3] < 0 else 1.0
    return sign * q[0], sign * q[1], sign * q[2], sign * q[3]


def _rotation_vector(r: Matrix) -> Vector:
    """The axis times the angle (radians, at most pi) of a rotation matrix."""
    x, y, z, w = _quaternion(r)
    sine = math.sqrt(x * x + y * y + z * z)
    if sine < 1e-12:
        return 2 * x, 2 * y, 2 * z  # near the identity: the angle is twice the sine
    scale = 2.0 * math.atan2(sine, w) / sine
    return x * scale, y * scale, z * scale


def normalized(q: Quaternion) -> Quaternion:
    """`q` scaled to unit length (raises ValueError for a quaternion near zero)."""
    norm = math.sqrt(sum(c * c for c in q))
    if not norm > 1e-6:
        raise ValueError("an orientation quaternion must not be zero")
    return q[0] / norm, q[1] / norm, q[2] / norm, q[3] / norm


def angle_between(a: Quaternion, b: Quaternion) -> float:
    """The angle (radians) of the rotation from `a` to `b`."""
    dot = abs(sum(x * y for x, y in zip(a, b, strict=True)))
    return 2.0 * math.acos(min(1.0, dot))
