"""The collision guard for an arm that already collides in the model: signed clearances, and
whether a move takes it out or deeper in (specs/collision.md, "An arm that already collides").

A measured arm is adopted where it is, and a model a little off the real arm may put it in the
table or in itself; refusing every motion from there leaves it stuck. So from such a pose a move
is allowed when no clearance that is negative gets smaller and none becomes negative, and
refused otherwise, with the clearances in the sentence. Pure: `collision.CollisionModel`'s
capsules and pairs, measured exactly (slower than its `assess`, and needed only here).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

from arena.robot.collision import PATH_STEP, CollisionModel, Hit, segment_distance
from arena.robot.kinematics import Vector
from arena.robot.workspace import Box, Workspace

#: Metres a clearance may lose from one pose to the next and still count as kept: rounding in
#: the kinematics, not motion (a turn about the vertical leaves a floor gap as it was).
CLEARANCE_TOLERANCE = 1e-6


@dataclass(frozen=True, slots=True)
class Escape:
    """A move from a pose that already collides in the model (`escape`): the constraint that
    decides it, its clearance (metres, signed: negative is how deep the parts overlap) at the
    start and at the pose that decides (the first checked where it shrinks, or the goal), and
    whether the move is allowed."""

    hit: Hit
    before: float
    after: float
    allowed: bool

    def describe(self) -> str:
        """The clearance change in a few words, millimetres signed."""
        return f"{self.hit} {self.before * 1000:+.1f} mm to {self.after * 1000:+.1f} mm"


def clearances(
    model: CollisionModel, values: Mapping[str, float], workspace: Workspace
) -> dict[Hit, float]:
    """The signed clearance of every constraint of the pose `values` (URDF radians): metres
    between the two parts less the margin, negative when they overlap (as deep as they do)."""
    ends = [(a, b) for a, b, _ in model.placed(values)]
    margin = workspace.margin
    found: dict[Hit, float] = {}
    if workspace.floor is not None:
        for index in model.floor_links:
            (a, b), capsule = ends[index], model.capsules[index]
            found[Hit(capsule.link, "floor")] = (
                min(a[2], b[2]) - capsule.radius - workspace.floor - margin
            )
    for box in workspace.keep_out:
        for (a, b), capsule in zip(ends, model.capsules, strict=True):
            gap = _segment_box_signed(a, b, box) - capsule.radius - margin
            found[Hit(capsule.link, box.name)] = gap
    for i, j in model.pairs:
        first, second = model.capsules[i], model.capsules[j]
        distance = segment_distance(*ends[i], *ends[j])
        found[Hit(first.link, second.link)] = distance - first.radius - second.radius - margin
    return found


def escape(
    model: CollisionModel,
    start: Mapping[str, float],
    goal: Mapping[str, float],
    workspace: Workspace,
    step: float = PATH_STEP,
) -> Escape | None:
    """A move from a pose `start` that collides (None if it does not): allowed when, at every
    pose checked on the straight way to `goal` (as `CollisionModel.path_hit` checks them), no
    clearance that was negative at `start` is smaller than it was, and none that was not is
    negative. The answer names the constraint that refuses it, or else the deepest one at
    `start` with its clearance at the goal."""
    before = clearances(model, start, workspace)
    deepest = min(before, key=before.__getitem__, default=None)
    if deepest is None or before[deepest] >= 0.0:
        return None
    largest = max((abs(goal[n] - start.get(n, goal[n])) for n in goal), default=0.0)
    count = max(1, math.ceil(largest / step))
    now = before
    for k in range(1, count + 1):
        f = k / count
        pose = {n: start.get(n, v) + (v - start.get(n, v)) * f for n, v in goal.items()}
        now = clearances(model, {**start, **pose}, workspace)
        for hit, value in now.items():
            was = before.get(hit, math.inf)
            if value < 0.0 and value < min(was, 0.0) - CLEARANCE_TOLERANCE:
                return Escape(hit, was, value, False)
    return Escape(deepest, before[deepest], now[deepest], True)


def _segment_box_signed(a: Vector, b: Vector, box: Box) -> float:
    """A lower bound of the signed distance from segment a-b to a box: points every 1 cm along
    the segment, outside each one's distance to the box, inside less how far it is from the
    nearest face (so a move deeper into a box reads as a smaller clearance); less half the
    spacing."""
    length = math.dist(a, b)
    count = max(1, math.ceil(length / 0.01))
    best = math.inf
    for k in range(count + 1):
        f = k / count
        point = (a[0] + (b[0] - a[0]) * f, a[1] + (b[1] - a[1]) * f, a[2] + (b[2] - a[2]) * f)
        sides = tuple(zip(point, box.low, box.high, strict=True))
        outside = math.sqrt(sum(max(lo - p, 0.0, p - hi) ** 2 for p, lo, hi in sides))
        if outside == 0.0:
            outside = -min(min(p - lo, hi - p) for p, lo, hi in sides)
        best = min(best, outside)
    return best - length / count / 2
