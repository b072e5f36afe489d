"""The reach task, pure: where the gripper's tip is, targets drawn where the arm can reach, when
the task is done, and a scripted expert that solves it (inverse kinematics on Arena's own
kinematics, `arena.robot.kinematics`). No trio, no I/O after loading the robot type.

Joint values here are Arena's wire units in servo order (degrees; the so-arm100's gripper too).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, TypeAlias

import numpy as np
import numpy.typing as npt

from arena.robot.collision import for_model
from arena.robot.kinematics import Kinematics, Vector, rotate
from arena.robot.meshes import link_vertices
from arena.robot.model import RobotModel

#: Joint values: a sequence or a numpy vector (wire units, servo order).
Joints: TypeAlias = Sequence[float] | npt.NDArray[Any]
#: A vector of floats.
Vec: TypeAlias = npt.NDArray[np.float64]

#: Success: the tip within this distance (metres) of the target ...
SUCCESS_DISTANCE = 0.02
#: ... for this long (seconds).
SUCCESS_HOLD = 0.5
#: The joints the task moves (the first four: pan, lift, elbow, wrist flex); the wrist's roll
#: and the gripper stay where they are.
ARM_JOINTS = 4
#: Where targets come from: the tip at joint values drawn in these ranges (degrees), kept if
#: the pose is clear of the table and of itself and the tip at least `MIN_HEIGHT` above the
#: table. Drawing joints rather than points makes every target reachable.
TARGET_RANGES = ((-35.0, 35.0), (-20.0, 40.0), (-40.0, 40.0), (-40.0, 40.0))
MIN_HEIGHT = 0.06
#: The expert's largest step per action (degrees), and the gain of its correction for sag.
EXPERT_STEP = 4.0
EXPERT_GAIN = 0.1
#: How far (degrees) a following expert's plan may run ahead of the measured arm.
EXPERT_LEASH = 8.0
#: The plan counts as there within this distance (metres) of the target.
PLAN_REACHED = 0.005
#: Damped least-squares steps the inverse kinematics takes at most.
IK_ITERATIONS = 100


def tip_link(model: RobotModel, kinematics: Kinematics) -> str:
    """The link that carries the fixed jaw: the parent of the gripper's joint (the hand's
    `gripper`, else the type's last joint). The so-arm100's `gripper`, the so-101's
    `gripper_link`."""
    hand = model.end_effector
    name = hand.gripper if hand is not None and hand.gripper else model.joints[-1].name
    urdf = next(spec.urdf_name for spec in model.joints if spec.name == name)
    for joint in kinematics.joints:
        if joint.name == urdf:
            return joint.parent
    raise ValueError(f"{model.robot_type}: no URDF joint {urdf!r} for the gripper")


def tip_offset(model: RobotModel, link: str) -> Vector:
    """The tip in `link`'s frame: the middle of its mesh's points within 1 cm of its point
    farthest from the link's origin (the end of the fixed jaw)."""
    points = link_vertices(model.urdf_path)[link]
    reach = np.linalg.norm(points, axis=1)
    far = points[reach > reach.max() - 0.01].mean(axis=0)
    return float(far[0]), float(far[1]), float(far[2])


@dataclass
class Reach:
    """The reach task on one robot type."""

    model: RobotModel
    kinematics: Kinematics = field(init=False)
    tip_link: str = field(init=False)
    tip: Vector = field(init=False)

    def __post_init__(self) -> None:
        self.kinematics = Kinematics.from_urdf(self.model.urdf_path)
        self.tip_link = tip_link(self.model, self.kinematics)
        self.tip = tip_offset(self.model, self.tip_link)
        self._collision = for_model(self.model)

    def _urdf(self, joints: Joints) -> dict[str, float]:
        return {
            spec.urdf_name: spec.to_urdf(value)
            for spec, value in zip(self.model.joints, joints, strict=False)
        }

    def tip_position(self, joints: Joints) -> Vector:
        """Where the gripper's tip is (metres, the base's frame) at `joints`."""
        rotation, origin = self.kinematics.link_poses(self._urdf(joints))[self.tip_link]
        moved = rotate(rotation, self.tip)
        return origin[0] + moved[0], origin[1] + moved[1], origin[2] + moved[2]

    def distance(self, joints: Joints, target: Sequence[float]) -> float:
        """The tip's distance (metres) from `target` at `joints`."""
        return math.dist(self.tip_position(joints), target)

    def clear(self, joints: Joints) -> bool:
        """The pose keeps the collision guard's margins (table, keep-out boxes, itself)."""
        if self._collision is None:
            return True
        return self._collision.hit(self._urdf(joints), self.model.workspace) is None

    def draw_target(self, rng: np.random.Generator) -> Vector:
        """A target the tip can reach, above the table, from `rng` (the same draws give the
        same target)."""
        floor = self.model.workspace.floor or 0.0
        rest = [0.0] * len(self.model.joints)
        while True:
            joints = list(rest)
            for index, (low, high) in enumerate(TARGET_RANGES):
                joints[index] = float(rng.uniform(low, high))
            point = self.tip_position(joints)
            if point[2] >= floor + MIN_HEIGHT and self.clear(joints):
                return point

    def jacobian(self, joints: Joints) -> Vec:
        """d tip / d joint (metres per degree) for the arm's joints, by central differences."""
        columns = []
        for index in range(ARM_JOINTS):
            plus, minus = list(joints), list(joints)
            plus[index] += 0.5
            minus[index] -= 0.5
            columns.append(np.subtract(self.tip_position(plus), self.tip_position(minus)))
        return np.stack(columns, axis=1)

    def ik_step(self, joints: Joints, target: Sequence[float]) -> Vec:
        """The change of the arm's joints (degrees) that moves the tip toward `target`: damped
        least squares, which stays sane near a singular pose."""
        error = np.subtract(target, self.tip_position(joints))
        jac = self.jacobian(joints)
        damping = 1e-6  # (metres per degree)^2: a small fraction of a column's square
        solved: Vec = jac.T @ np.linalg.solve(jac @ jac.T + damping * np.eye(3), error)
        return solved

    def solve(self, target: Sequence[float], start: Joints) -> Vec:
        """Joints (from `start`, the arm's moved) that put the tip on `target`, as near as
        `IK_ITERATIONS` damped steps of at most 10 degrees get; within the joints' limits."""
        joints: Vec = np.array(start, dtype=float)
        for _ in range(IK_ITERATIONS):
            step = np.clip(self.ik_step(joints, target), -10.0, 10.0)
            joints[:ARM_JOINTS] += step
            for index, spec in enumerate(self.model.joints[:ARM_JOINTS]):
                joints[index] = spec.clamp(float(joints[index]))
            if self.distance(joints, target) < 1e-4:
                break
        return joints


class Success:
    """Counts how long the tip has stayed near the target: done after `SUCCESS_HOLD` seconds
    at `fps` steps a second."""

    def __init__(self, fps: float) -> None:
        self.needed = max(1, math.ceil(SUCCESS_HOLD * fps))
        self.held = 0

    def update(self, distance: float) -> bool:
        """One step at `distance` from the target; True once it has held long enough."""
        self.held = self.held + 1 if distance <= SUCCESS_DISTANCE else 0
        return self.held >= self.needed


class Expert:
    """The scripted expert. It solves the inverse kinematics once (`Reach.solve`), then moves
    the commanded joints toward the solution, at most `EXPERT_STEP` degrees a joint an action;
    once there, a slow integral term made from where the tip really is makes up for the arm's
    sag under gravity, which the kinematics cannot know.

    `follow`: its plan is kept within `EXPERT_LEASH` degrees of the measured arm, so its
    action stays a function of what it sees. A corrector is so: its commands are eased in
    at the joining speed, and a plan of its own would run far ahead of the arm, labelling
    the states it passes with actions the arm is nowhere near. (Not the plan reset to the
    arm each step: an arm that sags more than a step under gravity then never gets there.)

    `bias`: the sag compensation, known beforehand (`arena.gym.dagger.Compensation`), added
    from the first action and never changed: no integral term, so the action is a function of
    the state and the target alone."""

    def __init__(
        self,
        task: Reach,
        target: Sequence[float],
        start: Joints,
        follow: bool = False,
        bias: Joints | None = None,
    ) -> None:
        self.task = task
        self.follow = follow
        self.target = tuple(target)
        self.plan: Vec = np.array(start, dtype=float)
        self.goal = task.solve(target, start)
        #: A given bias is held fixed (no integral term): the action is then a function of
        #: the state alone, not of how long the arm has been near the target.
        self.fixed = bias is not None
        self.bias: Vec = np.array(bias if bias is not None else np.zeros(ARM_JOINTS), dtype=float)

    def act(self, measured: Joints) -> Vec:
        """The next action (every joint, wire units) from the measured joints."""
        if self.follow:  # the plan kept on a leash of `EXPERT_LEASH` degrees from the arm
            arm = np.asarray(measured, dtype=float)[:ARM_JOINTS]
            self.plan[:ARM_JOINTS] = np.clip(
                self.plan[:ARM_JOINTS], arm - EXPERT_LEASH, arm + EXPERT_LEASH
            )
        step = np.clip(self.goal - self.plan, -EXPERT_STEP, EXPERT_STEP)
        self.plan += step
        if not self.fixed and self.task.distance(self.plan, self.target) < PLAN_REACHED:
            correction = EXPERT_GAIN * self.task.ik_step(measured, self.target)
            self.bias = np.asarray(
                np.clip(self.bias + np.clip(correction, -1.0, 1.0), -10.0, 10.0), dtype=float
            )
        action = self.plan.copy()
        action[:ARM_JOINTS] += self.bias
        for index, spec in enumerate(self.task.model.joints):
            action[index] = spec.clamp(float(action[index]))
        return action
