"""Planned paths: a way in joint space from where the arm is to a goal that the collision guard
lets through, found by OMPL, shortened by OMPL's simplifier and timed within the joints'
velocity and acceleration limits (specs/cartesian.md, "Planned paths").

The check is the guard's own (`arena.robot.collision.CollisionModel`): a pose is valid when
`assess` finds no hit; the straight way between two poses is free when the guard's own bound
(`CollisionModel.near`: no point of the arm can move as far as the gaps of the pose it starts
from) proves it, step by step: from each pose checked, as far on as the bound proves safe,
then check there; where the gaps are too small to prove a step of `FINE_STEP`, the way goes on
by that step between checked poses (the guard checks a command's way in 5-degree steps). Every
pose the move will command is checked once more. No second collision model: what the planner
finds free, the guard lets through.

OMPL (the `plan` extra) is imported when a plan needs a search, not before. No I/O; the
caller runs `plan` in a thread: the checks are Python, which gives up the GIL every switch
interval, and the checks pause now and then (`YIELD_EVERY`) so the event loop gets it at once.
"""

from __future__ import annotations

import collections
import itertools
import math
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from arena.robot.collision import CollisionModel, Hit, Reference
from arena.robot.model import RobotModel
from arena.robot.workspace import Workspace

#: Seconds a plan's search may take by default (the caller's `budget`).
DEFAULT_BUDGET = 1.0
#: A planned way is gentler than the trajectory's limits: a joint reaches its velocity limit
#: from rest in no less than this time (seconds), and never faster than its acceleration
#: limit allows, so the trajectory that plays it follows the way checked closely (a sharper
#: way's corners are rounded by the jerk limit, off the checked line).
ACCELERATION_TIME = 0.25
#: Seconds between the poses of a timed path (each one command: 50 a second, half the default
#: command rate, so the stream stays inside the rate limit's budget).
SAMPLE_PERIOD = 0.02
#: Radians (of the joint that moves most): where the guard's bound cannot prove a step this
#: long, the way goes on by this step between poses checked (the guard itself checks a
#: command's way 5 degrees apart).
FINE_STEP = math.radians(1.0)
#: Rounds of the simplifier at most (it stops sooner when a round changes nothing).
SIMPLIFY_ROUNDS = 5
#: The plan's thread sleeps YIELD_FOR seconds after every YIELD_EVERY seconds of checks. The
#: event loop's thread, waiting for the GIL, takes it at once then; without the pauses it
#: waits for the 5 ms switch interval each time it wants the GIL back (after every wait for
#: I/O): a 1 ms sleep on the loop took 15 ms at the median while a plan ran, 0.4 ms with them,
#: for a fifth of the plan's time.
YIELD_EVERY = 0.002
YIELD_FOR = 0.0005
#: Poses whose check is kept during one plan (the tree's nodes are checked again and again).
CACHE = 200_000

Values = tuple[float, ...]  # one value per joint of the model, URDF units, the model's order


class NoPath(Exception):
    """No path within the budget: `reason` says why in a sentence, `hit` names what blocks
    (None: nothing in particular, or the plan was cancelled: `cancelled`)."""

    def __init__(self, reason: str, hit: Hit | None = None, *, cancelled: bool = False) -> None:
        super().__init__(reason)
        self.reason = reason
        self.hit = hit
        self.cancelled = cancelled


@dataclass(frozen=True, slots=True)
class PlannedPath:
    """A path found and timed: the corners of the simplified path and the poses to command at
    their times (seconds from the start; every joint, wire units, the last one the goal)."""

    waypoints: tuple[dict[str, float], ...]
    samples: tuple[tuple[float, dict[str, float]], ...]
    duration: float  # seconds
    planning: float  # seconds spent finding (and simplifying) the path
    straight: bool  # the straight way was free: no search was needed
    checks: int  # poses checked by the guard's model


class GuardCheck:
    """The collision guard's model as a planner's check: poses in the model's joint order and
    URDF units, each checked once (cached), what blocked counted."""

    def __init__(self, model: RobotModel, guard: CollisionModel, workspace: Workspace) -> None:
        self.guard = guard
        self.workspace = workspace
        self.names = tuple(j.urdf_name for j in model.joints)
        place = {name: k for k, name in enumerate(self.names)}
        # The guard's joints in its own order, as indices into a pose of the model (None: a
        # joint the model does not command, which stays at 0).
        self._order = tuple(place.get(j.name) for j in guard.kinematics.joints)
        self._cache: dict[Values, Reference | None] = {}
        self._hits: dict[Values, Hit] = {}
        #: What blocked, by how often a pose hit it.
        self.blocked: collections.Counter[Hit] = collections.Counter()
        self.checks = 0
        #: Called between checks of a way: True ends it (as not free), the budget spent.
        self.stop: Callable[[], bool] | None = None
        self._paused = time.perf_counter()

    def pose(self, values: Values) -> dict[str, float]:
        """A pose as the guard takes it (URDF joint name to value)."""
        return dict(zip(self.names, values, strict=True))

    def check(self, values: Values) -> Reference | None:
        """The pose's reference (its gaps, for `near`), or None when it collides."""
        found = self._cache.get(values, False)
        if found is not False:
            return found  # type: ignore[return-value]
        if len(self._cache) >= CACHE:
            self._cache.clear()
            self._hits.clear()
        self.checks += 1
        if time.perf_counter() - self._paused >= YIELD_EVERY:  # (see YIELD_EVERY)
            time.sleep(YIELD_FOR)
            self._paused = time.perf_counter()
        pose = self.pose(values)
        hit, gaps = self.guard.assess(pose, self.workspace)
        if hit is not None:
            self.blocked[hit] += 1
            self._hits[values] = hit
            reference = None
        else:
            reference = self.guard.reference(pose, gaps)
        self._cache[values] = reference
        return reference

    def hit(self, values: Values) -> Hit | None:
        """What the pose hits (None: nothing)."""
        if self.check(values) is not None:
            return None
        return self._hits.get(values) or self.guard.hit(self.pose(values), self.workspace)

    def valid(self, values: Values) -> bool:
        """The pose collides with nothing."""
        return self.check(values) is not None

    def _ordered(self, values: Values) -> Values:
        return tuple(0.0 if k is None else values[k] for k in self._order)

    def free(self, a: Values, b: Values) -> bool:
        """The straight way from `a` to `b` is free (see the module's docstring): from each
        pose checked, as far on as the guard's bound proves safe from it (at least
        FINE_STEP), until the bound reaches `b`. False too once `stop` says so."""
        near = CollisionModel.near
        end = self._ordered(b)
        p = a
        while True:
            if self.stop is not None and self.stop():
                return False
            at = self.check(p)
            if at is None:
                return False
            if near(at, end):
                return True
            d = [y - x for x, y in zip(p, b, strict=True)]
            largest = max(abs(x) for x in d)
            step = max(_provable(at, self._ordered(tuple(d))), FINE_STEP / largest)
            p = b if step >= 1.0 else tuple(x + dx * step for x, dx in zip(p, d, strict=True))

    def first_hit(self, a: Values, b: Values) -> Hit | None:
        """What the straight way from `a` to `b` first hits (the guard's own `path_hit`)."""
        return self.guard.path_hit(self.pose(a), self.pose(b), self.workspace)[0]


def _provable(at: Reference, way: Values) -> float:
    """The fraction of the straight `way` (changes of every joint, the guard's order) from the
    pose checked as `at` that `CollisionModel.near` proves safe: its bound is linear in the
    way's length (the turns times each joint's reach against the smallest gap they change),
    so the fraction is that gap over the sweep, a hair less for `near`'s strict test."""
    total = floor_total = 0.0
    limit = floor_limit = math.inf
    for k, change in enumerate(way):
        if change:
            total += abs(change) * at.units[k]
            floor_total += abs(change) * at.floor_units[k]
            limit = min(limit, at.limits[k])
            floor_limit = min(floor_limit, at.floor_limits[k])
    fraction = limit / total if total > 0.0 else math.inf
    if floor_total > 0.0:
        fraction = min(fraction, floor_limit / floor_total)
    return fraction * 0.999


def ompl_modules() -> tuple[Any, Any, Any]:
    """OMPL's base, geometric and util modules (ImportError when the extra is missing)."""
    from ompl import base, geometric, util  # type: ignore[import-untyped]

    util.setLogLevel(util.LOG_NONE)  # its progress lines would go to the server's stdout
    return base, geometric, util


def plan(
    model: RobotModel,
    guard: CollisionModel,
    workspace: Workspace,
    start: Mapping[str, float],
    goal: Mapping[str, float],
    *,
    budget: float = DEFAULT_BUDGET,
    speed: float = 1.0,
    cancel: threading.Event | None = None,
) -> PlannedPath:
    """A collision-free path from `start` to `goal` (wire values by protocol name, every joint
    of the model; values outside the limits are clamped), timed at `speed` (a fraction of each
    joint's velocity and acceleration limits). Raises `NoPath` when the start or the goal
    collides, when no path is found within `budget` seconds, or when `cancel` is set."""
    began = time.perf_counter()
    specs = model.joints
    check = GuardCheck(model, guard, workspace)
    a = tuple(s.to_urdf(s.clamp(start[s.name])) for s in specs)
    b = tuple(s.to_urdf(s.clamp(goal[s.name])) for s in specs)
    found = check.hit(a)
    if found is not None:
        raise NoPath(f"the arm is in collision where it starts ({found})", found)
    found = check.hit(b)
    if found is not None:
        raise NoPath(f"the goal itself would bring {found} together", found)
    straight = check.free(a, b)
    corners = [a, b] if straight else _search(check, model, a, b, budget, cancel, began)
    samples = timed(corners, model, speed)
    for _, pose in samples:  # every pose commanded: the guard's check, as the core will do
        found = check.hit(pose)
        if found is not None:  # (a way stepped through by FINE_STEP can graze something)
            raise NoPath(f"the path found grazes {found}", found)
    wire = [
        {s.name: s.clamp(s.from_urdf(v)) for s, v in zip(specs, p, strict=True)} for p in corners
    ]
    return PlannedPath(
        tuple(wire),
        tuple(
            (t, {s.name: s.clamp(s.from_urdf(v)) for s, v in zip(specs, p, strict=True)})
            for t, p in samples
        ),
        samples[-1][0] if samples else 0.0,
        time.perf_counter() - began,
        straight,
        check.checks,
    )


def _search(
    check: GuardCheck,
    model: RobotModel,
    a: Values,
    b: Values,
    budget: float,
    cancel: threading.Event | None,
    began: float,
) -> list[Values]:
    """RRT-Connect from `a` to `b`, then OMPL's simplifier, within what is left of `budget`."""
    base, geometric, _ = ompl_modules()
    n = len(a)
    space = base.RealVectorStateSpace(n)
    bounds = base.RealVectorBounds(n)
    for k, spec in enumerate(model.joints):
        low, high = sorted((spec.to_urdf(spec.lower), spec.to_urdf(spec.upper)))
        bounds.setLow(k, low)
        bounds.setHigh(k, high)
    space.setBounds(bounds)
    setup = geometric.SimpleSetup(space)

    def read(state: Any) -> Values:
        return tuple(state[k] for k in range(n))

    setup.setStateValidityChecker(lambda state: check.valid(read(state)))
    info = setup.getSpaceInformation()

    class Way(base.MotionValidator):  # type: ignore[misc,name-defined]
        """The guard's straight-way check, for OMPL."""

        def checkMotion(self, first: Any, second: Any) -> bool:
            return check.free(read(first), read(second))

    way = Way(info)
    info.setMotionValidator(way)
    ends = []
    for values in (a, b):
        state = space.allocState()
        for k, v in enumerate(values):
            state[k] = v
        ends.append(state)
    setup.setStartAndGoalStates(ends[0], ends[1])
    setup.setPlanner(geometric.RRTConnect(info))
    deadline = began + budget
    stop = threading.Event() if cancel is None else cancel

    def done() -> bool:
        return stop.is_set() or time.perf_counter() >= deadline

    check.stop = done
    setup.solve(base.PlannerTerminationCondition(done))
    if stop.is_set():
        raise NoPath("the plan was cancelled (an e-stop)", cancelled=True)
    if not setup.haveExactSolutionPath():
        check.stop = None
        hit = check.first_hit(a, b)  # what the straight way runs into
        if hit is None and check.blocked:
            hit = check.blocked.most_common(1)[0][0]
        what = f" around {hit}" if hit is not None else ""
        raise NoPath(f"no collision-free path found{what} in {budget:g} s", hit)
    path = setup.getSolutionPath()
    # Shorten within half the budget more: drop corners the way between their neighbours
    # makes needless, then cut across (each way checked as above). No B-spline smoothing:
    # it adds corners, and every corner is a stop (`timed`).
    finish = time.perf_counter() + budget / 2
    simplifier = geometric.PathSimplifier(info)

    def shortened() -> bool:
        return stop.is_set() or time.perf_counter() >= finish

    check.stop = shortened
    for _ in range(SIMPLIFY_ROUNDS):
        changed = simplifier.reduceVertices(path)
        changed = simplifier.ropeShortcutPath(path) or changed
        if not changed or shortened():
            break
    simplifier.reduceVertices(path)
    check.stop = None
    corners = [read(state) for state in path.getStates()]
    corners[0], corners[-1] = a, b  # exactly where it starts and ends
    return [p for k, p in enumerate(corners) if k == 0 or p != corners[k - 1]]


def timed(
    corners: Sequence[Values], model: RobotModel, speed: float = 1.0, period: float = SAMPLE_PERIOD
) -> list[tuple[float, Values]]:
    """The poses to command along straight ways between `corners` (URDF units), one every
    `period` seconds and the last corner at the end: each way from rest to rest, its progress
    a trapezoid (or a triangle) so that no joint passes its velocity limit times `speed` or its
    acceleration (`ACCELERATION_TIME`, and the joint's limit) times `speed`."""
    velocity = [s.max_velocity * s.radians_per_unit * speed for s in model.joints]
    acceleration = [
        min(v / ACCELERATION_TIME, s.max_acceleration * s.radians_per_unit * speed)
        for v, s in zip(velocity, model.joints, strict=True)
    ]
    ways: list[tuple[float, float, float, float, Values, Values]] = []  # t0, T, ta, rate, p, q
    clock = 0.0
    for p, q in itertools.pairwise(corners):
        d = [y - x for x, y in zip(p, q, strict=True)]
        moved = [(abs(x), v, acc) for x, v, acc in zip(d, velocity, acceleration, strict=True) if x]
        if not moved:
            continue
        rate = min(v / x for x, v, _ in moved)  # the fastest progress (of 1) per second
        push = min(acc / x for x, _, acc in moved)  # ... and its change per second
        ramp = rate / push
        if ramp * rate >= 1.0:  # never at full speed: accelerate half the way, then brake
            ramp = math.sqrt(1.0 / push)
            rate = push * ramp
            total = 2.0 * ramp
        else:
            total = 1.0 / rate + ramp
        ways.append((clock, total, ramp, rate, p, q))
        clock += total
    samples: list[tuple[float, Values]] = []
    if not ways:
        return [(0.0, tuple(corners[-1]))] if corners else []
    k = 1
    for t0, total, ramp, rate, p, q in ways:
        push = rate / ramp
        while k * period < t0 + total - 1e-9:
            t = k * period - t0
            if t <= ramp:
                s = 0.5 * push * t * t
            elif t <= total - ramp:
                s = 0.5 * push * ramp * ramp + rate * (t - ramp)
            else:
                s = 1.0 - 0.5 * push * (total - t) ** 2
            samples.append((k * period, tuple(x + (y - x) * s for x, y in zip(p, q, strict=True))))
            k += 1
        samples.append((t0 + total, q))  # the corner itself, at rest
        if k * period <= t0 + total + 1e-9:
            k += 1
    return samples
