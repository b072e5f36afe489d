"""The collision guard, pure: capsules around the links, a workspace, and distance checks.

Each link with meshes gets one capsule (a segment and a radius) that holds every vertex of its
meshes, fitted once per robot type. A pose collides when two links that are not neighbours
come closer than the workspace's margin, or a link comes within it of the floor or a keep-out
box. Capsules are cheap to test (segment distances, a few microseconds a pair in pure Python)
and deterministic; a convex-hull library (python-fcl, coal) would be tighter but costs a
native dependency and, per call from Python, more than the whole check does here.

Which pairs are checked is decided once, as MoveIt's setup assistant does: neighbours in the
tree never, nor pairs that touch in the neutral pose (their meshes overlap by design); every
other pair always. The floor the same way: links that touch it in the neutral pose (the base
standing on it) are not checked against it.

All geometry is in metres in the root link's frame; joint values are URDF radians here (the
robot core converts from wire degrees).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from arena.robot.kinematics import (
    IDENTITY,
    Kinematics,
    Pose,
    Quaternion,
    Vector,
    quaternion_multiply,
    rotate,
)
from arena.robot.workspace import Box, Workspace

if TYPE_CHECKING:
    from arena.robot.model import RobotModel

#: A joint whose axis is within this (the sine of its angle) of the vertical counts as turning
#: about the vertical: its sweep moves points up or down by that fraction only.
LEVEL_TILT = 1e-3

#: Capsules closer than this (metres) in the zero pose touch by design (their meshes are
#: neighbours on the arm, or the shoulder turning on its base just above the table): that pair,
#: or that link and the floor, is not checked.
REST_CONTACT = 0.01
#: Default spacing of the poses checked along a move (radians of the joint that moves most).
PATH_STEP = math.radians(5.0)


@dataclass(frozen=True)
class Capsule:
    """A link's collision shape: the points within `radius` of the segment a-b (link frame)."""

    link: str
    a: Vector
    b: Vector
    radius: float

    @functools.cached_property
    def middle(self) -> Vector:
        """The segment's middle (link frame)."""
        return (
            (self.a[0] + self.b[0]) / 2,
            (self.a[1] + self.b[1]) / 2,
            (self.a[2] + self.b[2]) / 2,
        )

    @functools.cached_property
    def reach(self) -> float:
        """The radius of a sphere around `middle` that holds the capsule."""
        return math.dist(self.a, self.b) / 2 + self.radius


@dataclass(frozen=True, slots=True)
class Hit:
    """What a pose would hit: two links, or a link and `floor` / a keep-out box's name."""

    first: str
    second: str

    def __str__(self) -> str:
        return f"{self.first} and {self.second}"


@dataclass(frozen=True, slots=True)
class Reference:
    """A pose checked in full (`CollisionModel.reference`): its joint values (in the
    kinematics' joint order and URDF units, unless `in_order` re-expressed them), and per
    joint the smallest gap (and floor gap) its motion can change and how far a unit of that
    motion can move a point (and move it up or down)."""

    values: tuple[float, ...]
    limits: tuple[float, ...]
    floor_limits: tuple[float, ...]
    checked: bool  # False for a pose whose gaps are unknown: nothing is near it
    units: tuple[float, ...]  # how far a unit of a joint's motion moves a point
    floor_units: tuple[float, ...]  # ... up or down (see `_floor_factors`)

    def in_order(
        self, values: tuple[float, ...], index: tuple[int | None, ...], scales: tuple[float, ...]
    ) -> Reference:
        """The same reference for poses listed another way: joint k of the new order is the
        kinematics' joint `index[k]` (None: a joint the guard does not know, which changes no
        gap) with its value in units of which one is `scales[k]` URDF units (degrees: pi/180;
        a 0-100 gripper: its range / 100), and `values` is the checked pose so listed. A joint
        of the kinematics left out must never move (it stays where the check saw it)."""

        def pick(
            numbers: tuple[float, ...], missing: float, times: bool = False
        ) -> tuple[float, ...]:
            return tuple(
                missing if k is None else numbers[k] * (scales[i] if times else 1.0)
                for i, k in enumerate(index)
            )

        return Reference(
            values,
            pick(self.limits, math.inf),
            pick(self.floor_limits, math.inf),
            self.checked,
            pick(self.units, 0.0, times=True),
            pick(self.floor_units, 0.0, times=True),
        )


@dataclass(frozen=True)
class CollisionModel:
    """Capsules of a robot's links and the pairs worth checking."""

    kinematics: Kinematics
    capsules: tuple[Capsule, ...]
    pairs: tuple[tuple[int, int], ...]  # indices into `capsules`
    floor_links: tuple[int, ...]  # capsules checked against the floor

    @functools.cached_property
    def reaches(self) -> tuple[float, ...]:
        """Per joint, a bound of how far any point of a capsule it moves lies from its axis
        (metres): turned by d radians, it moves no point by more than its reach times d. A
        point of a link below the joint is reached through the origins of the joints between
        them (each as long as its offset) and then lies inside the link's capsule."""
        extent = {c.link: max(math.hypot(*c.a), math.hypot(*c.b)) + c.radius for c in self.capsules}
        depth = {self.kinematics.root: 0.0}  # the offsets summed from the root to each link
        children: dict[str, list[str]] = {}
        for joint in self.kinematics.joints:  # parents come first
            depth[joint.child] = depth[joint.parent] + math.hypot(*joint.origin[1])
            children.setdefault(joint.parent, []).append(joint.child)

        def deepest(top: str) -> float:
            """The largest depth plus extent of `top` and the links under it."""
            own = depth[top] + extent[top] if top in extent else 0.0
            return max([own, *(deepest(child) for child in children.get(top, ()))])

        return tuple(
            max(0.0, deepest(joint.child) - depth[joint.child]) for joint in self.kinematics.joints
        )

    def placed(self, values: Mapping[str, float]) -> list[tuple[Vector, Vector, float]]:
        """Each capsule's segment ends in the root frame at joint values `values`."""
        poses = self.kinematics.link_poses(values)
        return [
            (_apply(poses[c.link], c.a), _apply(poses[c.link], c.b), c.radius)
            for c in self.capsules
        ]

    def hit(self, values: Mapping[str, float], workspace: Workspace) -> Hit | None:
        """The first collision of the pose `values` (URDF radians), or None."""
        return self.assess(values, workspace)[0]

    def assess(
        self, values: Mapping[str, float], workspace: Workspace
    ) -> tuple[Hit | None, tuple[float, ...]]:
        """The first collision of the pose `values` (URDF radians), or None with the gaps
        (metres, the margin kept) of every constraint: each link above the floor, each link
        outside the boxes, each pair apart. Each is a lower bound of how far the parts may
        move before they could touch. See `safe_move`.

        A broad phase first: each capsule's bounding sphere (its middle, half its length plus
        its radius) rules out most pairs and the floor with one distance, which also bounds
        their clearance; only what is near gets the exact segment test."""
        poses = self.kinematics.link_poses(values)
        capsules = self.capsules
        middles = [_apply(poses[c.link], c.middle) for c in capsules]
        ends: dict[int, tuple[Vector, Vector]] = {}

        def segment(index: int) -> tuple[Vector, Vector]:
            found = ends.get(index)
            if found is None:
                pose = poses[capsules[index].link]
                found = ends[index] = (
                    _apply(pose, capsules[index].a),
                    _apply(pose, capsules[index].b),
                )
            return found

        margin = workspace.margin
        count = len(capsules)
        gaps = [math.inf] * (2 * count + len(self.pairs))  # floor, boxes, pairs (`_constraints`)
        if workspace.floor is not None:
            floor = workspace.floor + margin
            for index in self.floor_links:
                capsule = capsules[index]
                gap = middles[index][2] - capsule.reach - floor
                if gap < 0.0:
                    a, b = segment(index)
                    gap = min(a[2], b[2]) - capsule.radius - floor
                    if gap < 0.0:
                        return Hit(capsule.link, "floor"), ()
                gaps[index] = gap
        for box in workspace.keep_out:
            for index, capsule in enumerate(capsules):
                a, b = segment(index)
                gap = _segment_box_distance(a, b, box) - capsule.radius - margin
                if gap < 0.0:
                    return Hit(capsule.link, box.name), ()
                gaps[count + index] = min(gaps[count + index], gap)
        for number, (i, j) in enumerate(self.pairs):
            first, second = capsules[i], capsules[j]
            m1, m2 = middles[i], middles[j]
            dx, dy, dz = m1[0] - m2[0], m1[1] - m2[1], m1[2] - m2[2]
            gap = math.sqrt(dx * dx + dy * dy + dz * dz) - first.reach - second.reach - margin
            if gap < 0.0:
                a1, b1 = segment(i)
                a2, b2 = segment(j)
                distance = _segment_distance(a1, b1, a2, b2)
                gap = distance - first.radius - second.radius - margin
                if gap < 0.0:
                    return Hit(first.link, second.link), ()
            gaps[2 * count + number] = gap
        return None, tuple(gaps)

    @functools.cached_property
    def _affected(self) -> tuple[tuple[tuple[int, ...], tuple[int, ...]], ...]:
        """Per joint, the constraints (indices into `assess`'s gaps) whose gap it can change,
        as (floor gaps, the others): a link's floor and boxes by every joint above the link; a
        pair by the joints between its two links (those above both move them together).

        So a gap closes by at most `reach` times the turns of the joints that change it. Seen
        from the lowest link above both of a pair's links, each joint between them moves one
        of the two and not the other, and turning it by d moves no point by more than
        `reach * d` (the arc, longer than the chord); a link's floor and box gaps are moved
        by the joints above it alone. `near` relies on this; a test checks it on the arm."""
        above: dict[str, set[str]] = {self.kinematics.root: set()}
        for joint in self.kinematics.joints:
            above[joint.child] = above[joint.parent] | {joint.name}
        links = [c.link for c in self.capsules]
        moved_by = [above[link] for link in links] * 2
        moved_by += [above[links[i]] ^ above[links[j]] for i, j in self.pairs]
        floors = len(links)  # the first gaps are each link's above the floor
        affected = []
        for joint in self.kinematics.joints:
            changed = [k for k, joints in enumerate(moved_by) if joint.name in joints]
            affected.append(
                (tuple(k for k in changed if k < floors), tuple(k for k in changed if k >= floors))
            )
        return tuple(affected)

    @functools.cached_property
    def _floor_factors(self) -> tuple[float, ...]:
        """Per joint, how much of a turn's sweep can move a point up or down: the sine of its
        axis's tilt from the vertical (the root frame's z) for a revolute joint that only ever
        turns about an (almost) vertical axis, else 1. A turn about a vertical axis leaves
        every height, so every floor gap, as it was; the first joint of an arm usually is one.
        A joint is such a turn when its axis is vertical at rest and every moving joint above
        it is such a turn too (those keep the axes below them as they were to the vertical)."""
        frames: dict[str, Quaternion] = {self.kinematics.root: IDENTITY[0]}
        tilted: set[str] = set()  # links that a joint above can tilt
        factors = []
        for joint in self.kinematics.joints:
            orientation = quaternion_multiply(frames[joint.parent], joint.origin[0])
            frames[joint.child] = orientation
            axis = rotate(orientation, joint.axis)
            norm = math.sqrt(axis[0] ** 2 + axis[1] ** 2 + axis[2] ** 2) or 1.0
            tilt = math.hypot(axis[0], axis[1]) / norm
            level = joint.kind in ("revolute", "continuous") and tilt < LEVEL_TILT
            if joint.parent in tilted or (joint.kind != "fixed" and not level):
                tilted.add(joint.child)
                factors.append(1.0)
            else:
                factors.append(tilt if level else 1.0)
        return tuple(factors)

    def reference(self, pose: Mapping[str, float], clearances: tuple[float, ...]) -> Reference:
        """A pose checked in full, with its gaps from `assess`, made ready for `near`: per
        joint, the smallest gap its turns can change (floor gaps apart)."""
        gap = clearances.__getitem__
        limits, floor_limits = [], []
        for floor, others in self._affected:
            limits.append(min(map(gap, others), default=math.inf))
            floor_limits.append(min(map(gap, floor), default=math.inf))
        units, floor_units = self._sweeps
        return Reference(
            self.values_of(pose),
            tuple(limits),
            tuple(floor_limits),
            bool(clearances),
            units,
            floor_units,
        )

    def values_of(self, pose: Mapping[str, float]) -> tuple[float, ...]:
        """A pose's joint values in the order `near` takes them (a missing joint is 0)."""
        return tuple(pose.get(joint.name, 0.0) for joint in self.kinematics.joints)

    @functools.cached_property
    def _sweeps(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """Per joint: how far a unit of its motion can move a point (its reach per radian, 1
        per metre), and how far up or down (times `_floor_factors`)."""
        units = tuple(
            1.0 if joint.kind == "prismatic" else reach
            for joint, reach in zip(self.kinematics.joints, self.reaches, strict=True)
        )
        return units, tuple(u * f for u, f in zip(units, self._floor_factors, strict=True))

    @staticmethod
    def near(reference: Reference, end: Iterable[float]) -> bool:
        """True when a pose `end` (joint values as `reference` lists them), and the straight
        way to it, is safe because `reference` was, by the bound `_affected` rests on: a gap
        closes by at most `reach` times the sum of the turns of the joints that change it (a
        prismatic joint's metres count once), and only the gaps the moving joints can change
        are at stake (the floor's only by the share of each sweep that goes up or down).
        `end` lists every joint. Called for every command and target while an arm moves, so
        it is one pass that looks further only at the joints that moved (most do not)."""
        if not reference.checked:
            return False
        values, units, floor_units = reference.values, reference.units, reference.floor_units
        total = floor_total = 0.0  # how far any point may have moved; up or down
        limit = floor_limit = math.inf  # the smallest gap at stake; of a floor gap
        for k, value in enumerate(end):
            if value != values[k]:
                sweep = abs(value - values[k])
                total += sweep * units[k]
                floor_total += sweep * floor_units[k]
                gap = reference.limits[k]
                if gap < limit:
                    limit = gap
                gap = reference.floor_limits[k]
                if gap < floor_limit:
                    floor_limit = gap
        return total < limit and floor_total < floor_limit

    def safe_move(
        self,
        clearances: tuple[float, ...],
        start: Mapping[str, float],
        end: Mapping[str, float],
    ) -> bool:
        """`near` from `start` with these gaps from `assess` (see `reference`)."""
        return self.near(self.reference(start, clearances), self.values_of(end))

    def path_hit(
        self,
        start: Mapping[str, float],
        goal: Mapping[str, float],
        workspace: Workspace,
        step: float = PATH_STEP,
    ) -> tuple[Hit | None, float, tuple[float, ...]]:
        """The first collision on the straight way (in joint space) from `start` to `goal`,
        checked at least every `step` radians of the joint that moves most, goal included;
        the fraction of the way that is safe (1.0 with no hit); and the goal's clearance."""
        largest = max((abs(goal[n] - start.get(n, goal[n])) for n in goal), default=0.0)
        count = max(1, math.ceil(largest / step))
        for k in range(1, count):
            f = k / count
            pose = {n: start.get(n, v) + (v - start.get(n, v)) * f for n, v in goal.items()}
            found = self.hit(pose, workspace)
            if found is not None:
                return found, (k - 1) / count, ()
        found, clearances = self.assess(goal, workspace)
        if found is not None:
            return found, (count - 1) / count, ()
        return None, 1.0, clearances


def _apply(pose: Pose, point: Vector) -> Vector:
    moved = rotate(pose[0], point)
    t = pose[1]
    return (moved[0] + t[0], moved[1] + t[1], moved[2] + t[2])


def _segment_distance(p1: Vector, q1: Vector, p2: Vector, q2: Vector) -> float:
    """The distance between segments p1-q1 and p2-q2 (Ericson, Real-Time Collision
    Detection, 5.1.9)."""
    d1 = (q1[0] - p1[0], q1[1] - p1[1], q1[2] - p1[2])
    d2 = (q2[0] - p2[0], q2[1] - p2[1], q2[2] - p2[2])
    r = (p1[0] - p2[0], p1[1] - p2[1], p1[2] - p2[2])
    a = d1[0] * d1[0] + d1[1] * d1[1] + d1[2] * d1[2]
    e = d2[0] * d2[0] + d2[1] * d2[1] + d2[2] * d2[2]
    f = d2[0] * r[0] + d2[1] * r[1] + d2[2] * r[2]
    eps = 1e-12
    if a <= eps and e <= eps:
        s = t = 0.0
    elif a <= eps:
        s, t = 0.0, min(1.0, max(0.0, f / e))
    else:
        c = d1[0] * r[0] + d1[1] * r[1] + d1[2] * r[2]
        if e <= eps:
            s, t = min(1.0, max(0.0, -c / a)), 0.0
        else:
            b = d1[0] * d2[0] + d1[1] * d2[1] + d1[2] * d2[2]
            denominator = a * e - b * b
            s = min(1.0, max(0.0, (b * f - c * e) / denominator)) if denominator > eps else 0.0
            t = (b * s + f) / e
            if t < 0.0:
                s, t = min(1.0, max(0.0, -c / a)), 0.0
            elif t > 1.0:
                s, t = min(1.0, max(0.0, (b - c) / a)), 1.0
    dx = r[0] + d1[0] * s - d2[0] * t
    dy = r[1] + d1[1] * s - d2[1] * t
    dz = r[2] + d1[2] * s - d2[2] * t
    return math.sqrt(dx * dx + dy * dy + dz * dz)


def segment_distance(p1: Vector, q1: Vector, p2: Vector, q2: Vector) -> float:
    """The distance between segments p1-q1 and p2-q2 (for the guard's other modules)."""
    return _segment_distance(p1, q1, p2, q2)


def _segment_box_distance(a: Vector, b: Vector, box: Box) -> float:
    """A lower bound of the distance from segment a-b to a box: points every 1 cm along the
    segment, each less the half spacing (so the bound never overstates it).

    The distance to a box changes by at most the way moved: a point at distance D cannot be
    followed by a nearer one than the best so far for (D - best) / spacing points, which are
    skipped (the same minimum, without computing points that cannot be it: a far box costs
    a point or two, not one per centimetre)."""
    length = math.dist(a, b)
    count = max(1, math.ceil(length / 0.01))
    spacing = length / count
    (ax, ay, az), (lx, ly, lz), (hx, hy, hz) = a, box.low, box.high
    dx, dy, dz = b[0] - ax, b[1] - ay, b[2] - az
    best = math.inf
    k = 0
    while k <= count:
        f = k / count
        x, y, z = ax + dx * f, ay + dy * f, az + dz * f
        ex = lx - x if x < lx else (x - hx if x > hx else 0.0)
        ey = ly - y if y < ly else (y - hy if y > hy else 0.0)
        ez = lz - z if z < lz else (z - hz if z > hz else 0.0)
        gap = math.sqrt(ex * ex + ey * ey + ez * ez)
        if gap < best:
            best = gap
        # points before k + skip are at least gap - skip * spacing >= best away
        k += 1 + (int((gap - best) / spacing) if spacing > 0.0 else count)
    return max(0.0, best - spacing / 2)


def for_model(model: RobotModel) -> CollisionModel | None:
    """A robot type's collision model (cached), its pairs chosen at the wire's zero pose."""
    return build(model.urdf_path, {j.urdf_name: j.to_urdf(0.0) for j in model.joints})


def build(urdf_path: Path, neutral: Mapping[str, float]) -> CollisionModel | None:
    """The collision model of a URDF from its meshes (None if no link has a mesh), with the
    pairs chosen at `neutral` (URDF radians of the pose where the arm rests unharmed)."""
    return _build(urdf_path, tuple(sorted(neutral.items())))


@functools.lru_cache(maxsize=16)
def _build(urdf_path: Path, neutral: tuple[tuple[str, float], ...]) -> CollisionModel | None:
    kinematics = Kinematics.from_urdf(urdf_path)
    capsules = tuple(fit_capsules(urdf_path))
    if not capsules:
        return None
    trial = CollisionModel(kinematics, capsules, (), ())
    placed = trial.placed(dict(neutral))
    neighbours = {frozenset((j.parent, j.child)) for j in kinematics.joints}
    pairs = []
    for i in range(len(capsules)):
        for j in range(i + 1, len(capsules)):
            if frozenset((capsules[i].link, capsules[j].link)) in neighbours:
                continue
            (a1, b1, r1), (a2, b2, r2) = placed[i], placed[j]
            if _segment_distance(a1, b1, a2, b2) - r1 - r2 >= REST_CONTACT:  # apart at rest
                pairs.append((i, j))
    floor_links = tuple(
        i for i, (a, b, r) in enumerate(placed) if min(a[2], b[2]) - r >= REST_CONTACT
    )  # a link on (or within a hair of) the floor's plane at rest stands on it: the base
    return CollisionModel(kinematics, capsules, tuple(pairs), floor_links)


def fit_capsules(urdf_path: Path) -> list[Capsule]:
    """One capsule per link holding every vertex of its visual meshes (STL only)."""
    import numpy as np  # only to fit, once per robot type

    from arena.robot.meshes import link_vertices

    capsules = []
    for link, vertices in link_vertices(urdf_path).items():
        points = np.asarray(vertices, dtype=float)
        center = points.mean(axis=0)
        _, _, axes = np.linalg.svd(points - center, full_matrices=False)
        axis = axes[0]
        along = (points - center) @ axis
        across = np.linalg.norm(points - center - np.outer(along, axis), axis=1)
        best: tuple[float, float, float, float] | None = None
        low, high = float(along.min()), float(along.max())
        for shrink in np.linspace(0.0, float(across.max()), 9):
            lo, hi = low + shrink, high - shrink
            if lo > hi:
                lo = hi = (low + high) / 2
            clamped = np.clip(along, lo, hi)
            radius = float(np.max(np.hypot(along - clamped, across)))
            volume = math.pi * radius**2 * (hi - lo) + 4 / 3 * math.pi * radius**3
            if best is None or volume < best[0]:
                best = (volume, lo, hi, radius)
        assert best is not None
        _, lo, hi, radius = best
        a, b = center + lo * axis, center + hi * axis
        capsules.append(
            Capsule(
                link,
                (float(a[0]), float(a[1]), float(a[2])),
                (float(b[0]), float(b[1]), float(b[2])),
                radius,
            )
        )
    return capsules
