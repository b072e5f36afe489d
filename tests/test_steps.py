"""arena.robot.steps: the stream's quick check (`passes`) decides as the full one does."""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from arena.robot import steps

JOINTS = 3
ACCEL = (8100.0, 6000.0, 12000.0)
JERK = (54000.0, 40000.0, 90000.0)
SPEEDS = (270.0, 200.0, 340.0)

angles = st.floats(-180.0, 180.0, allow_nan=False)
spacings = st.floats(0.001, 0.05, allow_nan=False)


def full_check(
    times: list[float],
    points: list[list[float]],
    at: float,
    goals: list[float],
    velocity: list[float] | None,
) -> bool:
    """Every joint's goal passed by the rule `MotionLimiter._track` applies joint by joint:
    within `steps.allowed`'s interval, the jerk's ramp within the speed, and near the goals'
    velocity where it is known."""
    bounds = steps.allowed(times, points, at, ACCEL, JERK, SPEEDS)
    (_, t1, t0), (_, p1, p0) = times, points
    h = at - t0
    for k, (low, high) in enumerate(bounds):
        step = (goals[k] - p0[k]) / h
        gain = 2.0 * (step - (p0[k] - p1[k]) / (t0 - t1)) / (at - t1)
        ahead = step + gain * h / 2.0 + gain * abs(gain) / (2.0 * JERK[k]) + gain * h
        if not (low <= step <= high and -SPEEDS[k] <= ahead <= SPEEDS[k]):
            return False
        if velocity is not None and abs(step - velocity[k]) > ACCEL[k] * h:
            return False
    return True


@settings(max_examples=3000, deadline=None)
@given(
    st.lists(spacings, min_size=3, max_size=3),
    st.lists(angles, min_size=JOINTS, max_size=JOINTS),
    st.lists(st.floats(-2.0, 2.0, allow_nan=False), min_size=2 * JOINTS, max_size=2 * JOINTS),
    st.lists(st.floats(-3.0, 3.0, allow_nan=False), min_size=JOINTS, max_size=JOINTS),
    st.one_of(st.none(), st.lists(st.floats(-300.0, 300.0), min_size=JOINTS, max_size=JOINTS)),
)
def test_the_quick_check_passes_a_streams_goals_where_the_full_check_does(
    spacing: list[float],
    start: list[float],
    moves: list[float],
    reach: list[float],
    velocity: list[float] | None,
) -> None:
    """Histories near the limits (steps of a few degrees a few milliseconds apart, goals a
    few degrees on): the two agree on every case, passed or not; both kinds occur."""
    t2 = 10.0
    times = [t2, t2 + spacing[0], t2 + spacing[0] + spacing[1]]
    p2 = start
    p1 = [x + moves[k] for k, x in enumerate(p2)]
    p0 = [x + moves[JOINTS + k] for k, x in enumerate(p1)]
    at = times[2] + spacing[2]
    goals = [x + reach[k] for k, x in enumerate(p0)]
    quick = steps.passes(times, [p2, p1, p0], at, goals, velocity, ACCEL, JERK, SPEEDS)
    assert quick == full_check(times, [p2, p1, p0], at, goals, velocity)


def test_the_quick_check_refuses_what_any_one_limit_refuses() -> None:
    """At rest, a step each limit alone refuses (speed, acceleration, jerk, the jerk's ramp
    over the speed, a goal far off the goals' own velocity) is not passed; a small one is."""
    times, here = [0.0, 1e-4, 2e-4], [0.0] * JOINTS
    history = [here, here, here]
    at = 0.01

    def quick(goal: float, velocity: list[float] | None = None) -> bool:
        goals = [goal, 0.0, 0.0]
        return steps.passes(times, history, at, goals, velocity, ACCEL, JERK, SPEEDS)

    assert quick(1e-4)
    assert not quick(3.0)  # 300 deg/s: over the speed
    assert not quick(0.01)  # 1 deg/s from rest in one tick: over the jerk alone
    assert not quick(0.5)  # 50 deg/s: over the acceleration too
    assert not quick(1e-4, velocity=[-200.0, 0.0, 0.0])  # far off the goals' own velocity
    for goal in (1e-4, 0.01, 0.5, 3.0):
        assert quick(goal) == full_check(times, history, at, [goal, 0.0, 0.0], None)
    # At 260 deg/s and gaining, a step at 268 is within every interval, but the jerk's ramp
    # from its acceleration back to zero would carry the joint past its 270.
    times, history = [0.0, 0.01, 0.02], [[0.0] * JOINTS, [2.5, 0, 0], [5.1, 0, 0]]
    goals = [5.1 + 2.68, 0.0, 0.0]
    assert (
        steps.held(
            history[2], goals, steps.allowed(times, history, 0.03, ACCEL, JERK, SPEEDS), 0.01
        )
        is None
    )
    assert not steps.passes(times, history, 0.03, goals, None, ACCEL, JERK, SPEEDS)
    steady = [[0.0] * JOINTS, [1.0, 0, 0], [2.0, 0, 0]]  # 100 deg/s, on at it: passed
    assert steps.passes(times, steady, 0.03, [3.0, 0, 0], None, ACCEL, JERK, SPEEDS)
