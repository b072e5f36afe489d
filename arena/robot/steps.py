"""The step a target may take after the last three, pure (used by `arena.robot.motion`): the
interval the limits allow each joint by divided differences, and targets held back within them
on the line the collision guard checked.

A step's velocity is `(x - p0) / (at - t0)`, with `x` the new target at sample time `at` and
`(t0, p0)` the last. Velocity, acceleration and jerk by divided differences over the last three
targets and the new one are each linear in `x`: each limit is an interval of step velocities,
and so is their intersection.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

#: Degrees of a joint's way to its aim under which it counts as already there (no line to
#: keep to: a joint a step aims to leave where it is).
STILL = 1e-9


def allowed(
    times: Sequence[float],
    points: Sequence[Sequence[float]],
    at: float,
    accel: Sequence[float],
    jerk: Sequence[float],
    speeds: Sequence[float],
) -> list[tuple[float, float]]:
    """Each joint's interval of step velocity at sample time `at` after the targets `points`
    at `times` (the last three, oldest first): acceleration and jerk within their limits, and
    within `speeds` where they allow it (a velocity the history has already brought over a cap
    is brought down as fast as they allow)."""
    t2, t1, t0 = times
    p2, p1, p0 = points
    h1, h2 = at - t1, at - t2
    hh = h1 * h2
    span1, span2, span02 = t0 - t1, t1 - t2, t0 - t2
    result = []
    for k in range(len(p0)):
        d1 = (p0[k] - p1[k]) / span1
        f2 = (d1 - (p1[k] - p2[k]) / span2) / span02  # acceleration / 2
        spread_a = h1 * accel[k] / 2.0
        low, high = d1 - spread_a, d1 + spread_a
        mid, spread_j = d1 + h1 * f2, hh * jerk[k] / 6.0
        low_j, high_j = mid - spread_j, mid + spread_j
        # (comparisons, not min and max: this runs for every joint of every target)
        if low_j > high:  # (over the acceleration limit: brought back at the jerk's pace)
            low = high = low_j
        elif high_j < low:
            low = high = high_j
        else:
            if low_j > low:
                low = low_j
            if high_j < high:
                high = high_j
        fast = speeds[k]
        slow = -fast
        if low < slow <= high or low <= fast < high:
            if slow > low:
                low = slow
            if fast < high:
                high = fast
        elif high <= slow:
            low = high
        elif low >= fast:
            high = low
        result.append((low, high))
    return result


def passes(
    times: Sequence[float],
    points: Sequence[Sequence[float]],
    at: float,
    goals: Sequence[float],
    velocity: Sequence[float] | None,
    accel: Sequence[float],
    jerk: Sequence[float],
    speeds: Sequence[float],
) -> bool:
    """Whether a stream's `goals` go out as they are at sample time `at` (a stream's common
    case, checked without building the intervals): each joint's step within the interval
    `allowed` gives it (the same comparisons: within the speed, the acceleration's and the
    jerk's intervals), the velocity the jerk adds while it takes the step's acceleration back
    to zero (and a step more: the grid is discrete) within the speed too, and, where the
    goals' `velocity` is known, the step within a tick's acceleration of it (an arm catching
    up on a hand that stops would overshoot it). False sends the stream through the full
    check (`MotionLimiter._track`), which passes the same goals where this does."""
    t2, t1, t0 = times
    p2, p1, p0 = points
    h, h1 = at - t0, at - t1
    hh = h1 * (at - t2)
    span1, span2, span02 = t0 - t1, t1 - t2, t0 - t2
    for k, (goal, x0, x1, fast, limit) in enumerate(zip(goals, p0, p1, speeds, accel, strict=True)):
        step = (goal - x0) / h
        if step > fast or step < -fast:
            return False
        d1 = (x0 - x1) / span1
        spread = h1 * limit / 2.0
        if step < d1 - spread or step > d1 + spread:
            return False
        mid = d1 + h1 * ((d1 - (x1 - p2[k]) / span2) / span02)
        spread = hh * jerk[k] / 6.0
        if step < mid - spread or step > mid + spread:
            return False
        if ramp_over(step, d1, h, h1, fast, jerk[k]):
            return False
        if velocity is not None and abs(step - velocity[k]) > limit * h:
            return False
    return True


def ramp_over(step: float, was: float, h: float, h1: float, fast: float, jerk: float) -> bool:
    """Whether a step of velocity `step` after one of `was` (`h` seconds on, `h1` since the
    target before) leaves the joint over `fast` once the jerk has taken the step's
    acceleration back to zero, a step more counted (the grid is discrete): a goal allowed now
    that the joint could not keep under its cap after."""
    gain = 2.0 * (step - was) / h1
    ahead = step + gain * h / 2.0 + gain * abs(gain) / (2.0 * jerk) + gain * h
    return ahead > fast or ahead < -fast


def on_line(p0: Sequence[float], aims: Sequence[float], wants: list[float]) -> list[float]:
    """`wants` (each joint's own step toward `aims`) moved onto the line from `p0` to `aims`,
    as far along it as the joint that goes the smallest part of its way: the targets of a
    stream held back stay on the straight line the guard checked to its newest goal. Where a
    joint's own step turns back (it must pass its aim and return), there is no such point:
    `wants` as they are."""
    part = 1.0
    for start, aim, want in zip(p0, aims, wants, strict=True):
        way = aim - start
        if abs(way) > STILL:
            share = (want - start) / way
            if share < 0.0:
                return wants
            part = min(part, share)
    if part == 1.0:
        return wants
    return [
        start + part * (aim - start) if abs(aim - start) > STILL else want
        for start, aim, want in zip(p0, aims, wants, strict=True)
    ]


def held(
    p0: Sequence[float], wants: Sequence[float], bounds: Sequence[tuple[float, float]], h: float
) -> list[float] | None:
    """Targets within `bounds` (`allowed`) a step of `h` seconds after `p0`, toward `wants`;
    None when `wants` are within them already. One factor for every joint where one suits
    them all (the farthest along the line from `p0` to `wants`: the arm holds to the line the
    guard checked); each joint its own nearest otherwise (a motion under way that must bend
    off the line to keep within the limits). A joint that is not to move but cannot stop at
    once is held on its own, the rest on the line."""
    for k, (low, high) in enumerate(bounds):  # (the common case first: nothing to hold back)
        step = (wants[k] - p0[k]) / h
        if step < low or step > high:
            break
    else:
        return None
    least, most = 0.0, 1.0
    loose = []
    for k, ((low, high), want) in enumerate(zip(bounds, wants, strict=True)):
        way = want - p0[k]
        if abs(way) <= STILL:
            if low * h > STILL or high * h < -STILL:
                loose.append(k)
            continue
        a, b = low * h / way, high * h / way
        if way < 0.0:
            a, b = b, a
        least, most = max(least, a), min(most, b)
    if least <= most:
        out = [p0[k] + most * (want - p0[k]) for k, want in enumerate(wants)]
        for k in loose:
            out[k] = _nearest(p0[k], wants[k], bounds[k], h)
        return out
    return [_nearest(p0[k], want, bounds[k], h) for k, want in enumerate(wants)]


def stopping_speed(distance: float, accel: float, h: float) -> float:
    """The speed from which braking at `accel`, a step of `h` seconds at a time, stops within
    `distance` (a speed v, v - accel h, v - 2 accel h, ... whose steps add up to it):
    accel h (sqrt(1/4 + 2 d / (accel h^2)) - 1/2), in a form without cancellation (a
    distance of float dust still gives a speed) and without dividing by h (0 when h is)."""
    if distance <= 0.0:
        return 0.0
    brake = accel * h
    reach = 2.0 * accel * distance
    return reach / (math.sqrt(brake * brake / 4.0 + reach) + brake / 2.0)


def toward(
    goal: float,
    here: float,
    step: float,
    was: float,
    moving: float,
    accel: float,
    h: float,
    fast: float,
) -> float:
    """A stream's target for a joint the limits keep from its `goal` a step of `h` seconds
    on (`step`: the velocity onto it; `was`: the joint's last): toward the goal, relative to
    the goal's own velocity `moving` (a stamped stream's line; else 0), at most at the
    velocity from which braking at `accel`, step by step, stops on it, the distance counted
    from a step on (the jerk's ramp to that braking), and within the cap `fast`."""
    moving = max(-fast, min(fast, moving))
    distance = abs(goal - here) - abs(was - moving) * h
    stop = stopping_speed(distance, accel, h)
    ahead = moving + max(-stop, min(stop, step - moving))
    # Never past the goal nor away from it: the goals' velocity is their last, not their next
    # (the ticks carried an arm trailing a flick on at it past where the hand stopped: 2
    # degrees); a motion the limits cannot stop in time is carried on by the caller's hold
    # (`held`), as little as they allow.
    if step >= 0.0:
        ahead = 0.0 if ahead < 0.0 else step if ahead > step else ahead
    else:
        ahead = step if ahead < step else 0.0 if ahead > 0.0 else ahead
    return here + max(-fast, min(fast, ahead)) * h


def _nearest(p0: float, want: float, bound: tuple[float, float], h: float) -> float:
    """One joint's target nearest `want` within its interval of step velocity."""
    low, high = bound
    step = (want - p0) / h
    if step < low:
        return p0 + low * h
    if step > high:
        return p0 + high * h
    return want
