"""Jerk-limited trajectories, checked on the targets the slaves are sent (specs/motion.md).

The core is driven as the robot's actor drives it (a command's own targets, then control ticks
while it moves) on a simulated clock, and every emitted target is recorded with the trajectory
time it stands for. Velocity, acceleration and jerk are then taken by divided differences of
those targets: for a trajectory whose jerk is bounded by J, every third divided difference
times 6 lies within [-J, J] (it is the jerk somewhere in between), and likewise for the
acceleration and velocity; so the only tolerance needed is float rounding, stated as `TOL`.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import random
from collections.abc import Iterable, Mapping

import pytest

from arena.robot.core import RobotCore
from arena.robot.model import RobotModel, load_robot_model
from arena.robot.motion import OVERDUE, Command, JointGoal

MODEL = load_robot_model("so-arm100")
#: Relative tolerance on the limits (float rounding of divided differences over 10 ms).
TOL = 1e-3
#: Factor over the time-optimal duration within which a step from rest arrives (plus one
#: tick of sampling: the targets are emitted on the control ticks, not at the exact instant).
OPTIMAL_FACTOR = 1.05
#: Median and worst lag (seconds) of a 100 Hz minimum-jerk sweep at up to 180 deg/s, from when
#: the leader was somewhere to the time the target that gets there stands for (a tick after it
#: is sent): 11 / 17 ms measured with the so-arm100's limits (1 / 7 ms from the send;
#: specs/motion.md). The stream planned to a stop at each goal trailed by 26 ms at the median.
LAG = 0.015
WORST_LAG = 0.03
#: Seconds between the targets the derivatives are taken of (see `derivatives`).
SPACING = 1e-3

#: (time, goals) or (time, goals, stamp): when the command arrives, and when its goals were true.
Schedule = Iterable[tuple[float, Mapping[str, float]] | tuple[float, Mapping[str, float], float]]


def fast_core(model: RobotModel = MODEL) -> RobotCore:
    """A core with the command rate limit out of the way."""
    policy = dataclasses.replace(model.safety, command_rate=1e9, command_burst=10**9)
    return RobotCore(model, 0.0, policy)


def drive(
    core: RobotCore,
    schedule: Schedule,
    until: float,
    *,
    speed: float | None = None,
    sent: bool = False,
) -> list[tuple[float, dict[str, float]]]:
    """Run `schedule` (time, goals) through `core` as the actor does; the emitted targets, each
    with the trajectory time it stands for (`MotionLimiter.sampled`: a target emitted at `now`
    is the trajectory at `now + tick`, a stamped goal's at its stamp's), from the start pose
    on; with `sent`, each with the time it was sent and a tick (what a lag is measured from)."""
    emitted = [(0.0, core.motion.positions)]
    pending = sorted(schedule, key=lambda item: item[0])
    next_tick: float | None = None
    now = 0.0
    while now <= until:
        due_command = pending[0][0] if pending else math.inf
        due_tick = next_tick if next_tick is not None else math.inf
        now = min(due_command, due_tick)
        if now == math.inf or now > until:
            break
        if due_command <= due_tick:
            _, goals, *stamp = pending.pop(0)
            joints = tuple(JointGoal(n, v, speed=speed) for n, v in goals.items())
            command = Command(joints, stamp=stamp[0] if stamp else None)
            result, step = core.command(None, command, now)
            assert result.accepted, result
            targets = step.targets
            next_tick = core.reschedule(next_tick, now)
        else:
            next_tick = None
            targets = core.tick(now)
            next_tick = core.next_tick(now)
        if targets is not None:
            emitted.append((now + core.tick_interval if sent else core.motion.sampled, targets))
    return emitted


def derivatives(
    emitted: list[tuple[float, dict[str, float]]], joint: str
) -> tuple[list[float], list[float], list[float]]:
    """Velocity, acceleration and jerk of one joint's targets by divided differences (of the
    targets at least `SPACING` apart: any subset of a trajectory's samples bounds it as well,
    and two a hair apart would only measure rounding)."""
    times: list[float] = []
    values: list[float] = []
    for t, targets in emitted:
        if times and t - times[-1] < SPACING:
            times.pop()
            values.pop()
        times.append(t)
        values.append(targets[joint])

    def divided(order: int) -> list[float]:
        table = values[:]
        for k in range(1, order + 1):
            table = [
                (table[i + 1] - table[i]) / (times[i + k] - times[i]) for i in range(len(table) - 1)
            ]
        return [math.factorial(order) * d for d in table]

    return divided(1), divided(2), divided(3)


def assert_within_limits(emitted: list[tuple[float, dict[str, float]]], model: RobotModel) -> None:
    """No joint's targets exceed its velocity, acceleration or jerk limit."""
    for joint in model.joints:
        v, a, j = derivatives(emitted, joint.name)
        peaks = (max(map(abs, v), default=0), max(map(abs, a), default=0), max(map(abs, j)))
        limits = (joint.max_velocity, joint.max_acceleration, joint.max_jerk)
        for what, peak, limit in zip(
            ("velocity", "acceleration", "jerk"), peaks, limits, strict=True
        ):
            assert peak <= limit * (1 + TOL), f"{joint.name}: {what} {peak:g} > {limit:g}"


def optimal_duration(distance: float, v: float, a: float, j: float) -> float:
    """The least time a rest-to-rest move of `distance` takes under the three limits (the
    textbook seven-phase profile, solved here without Ruckig)."""

    def ramp(peak: float) -> tuple[float, float]:  # time and distance from rest to `peak`
        t = peak / a + a / j if peak >= a * a / j else 2 * math.sqrt(peak / j)
        return t, peak * t / 2

    t_v, d_v = ramp(v)
    if 2 * d_v <= distance:
        return 2 * t_v + (distance - 2 * d_v) / v
    low, high = 0.0, v
    for _ in range(200):
        mid = (low + high) / 2
        low, high = (mid, high) if 2 * ramp(mid)[1] < distance else (low, mid)
    return 2 * ramp(low)[0]


def arrival(emitted: list[tuple[float, dict[str, float]]], goals: Mapping[str, float]) -> float:
    """When the targets first stood on `goals`."""
    for t, targets in emitted:
        if all(targets[name] == value for name, value in goals.items()):
            return t
    raise AssertionError(f"never arrived at {goals}")


@pytest.mark.parametrize("distance", [0.5, 2.2, 10.0, 45.0, 90.0])
def test_a_step_command_keeps_the_limits_and_arrives_near_the_optimal_time(distance: float) -> None:
    core = fast_core()
    emitted = drive(core, [(0.0, {"Rotation": distance})], until=5.0)
    assert_within_limits(emitted, MODEL)
    joint = MODEL.joint("Rotation")
    assert joint is not None
    best = optimal_duration(distance, joint.max_velocity, joint.max_acceleration, joint.max_jerk)
    took = arrival(emitted, {"Rotation": distance})
    assert best <= took <= best * OPTIMAL_FACTOR + core.tick_interval
    assert core.next_tick(took) is None  # at rest on its goal: no more ticks


def test_a_reversal_mid_motion_bends_the_trajectory_without_a_velocity_step() -> None:
    core = fast_core()
    emitted = drive(core, [(0.0, {"Rotation": 90.0}), (0.3, {"Rotation": -30.0})], until=5.0)
    assert_within_limits(emitted, MODEL)
    v, _, _ = derivatives(emitted, "Rotation")
    assert max(v) > 150.0 and min(v) < -150.0  # it did go both ways, fast
    assert emitted[-1][1]["Rotation"] == -30.0
    assert max(targets["Rotation"] for _, targets in emitted) < 90.0  # bent before the goal


def test_a_burst_of_commands_keeps_the_limits_and_ends_on_the_newest() -> None:
    core = fast_core()
    burst = [(k * 1e-4, {"Rotation": 40.0 * math.sin(k), "Pitch": 5.0 * k % 30}) for k in range(50)]
    emitted = drive(core, burst, until=5.0)
    assert_within_limits(emitted, MODEL)
    assert emitted[-1][1]["Rotation"] == burst[-1][1]["Rotation"]
    assert emitted[-1][1]["Pitch"] == burst[-1][1]["Pitch"]


def test_a_policy_like_chunk_stream_keeps_the_limits_and_settles_on_the_last_action() -> None:
    # 30 actions a second, in chunks of 10 whose starts disagree with the chunk before
    # (each chunk a ramp from a jumped start): the seams a policy makes.
    core = fast_core()
    schedule = []
    for k in range(60):
        chunk, step = divmod(k, 10)
        value = (-15.0 if chunk % 2 else 15.0) + 2.0 * step
        schedule.append((k / 30, {"Rotation": value, "Elbow": -value / 2}))
    emitted = drive(core, schedule, until=6.0)
    assert_within_limits(emitted, MODEL)
    assert emitted[-1][1]["Rotation"] == schedule[-1][1]["Rotation"]
    assert emitted[-1][1]["Elbow"] == schedule[-1][1]["Elbow"]


def test_a_smooth_stream_is_tracked_closely_and_the_end_lands_on_the_last_goal() -> None:
    # A leader arm's sweep at 100 Hz (minimum-jerk, 60 degrees in 0.625 s: 180 deg/s at its
    # peak): the trajectory meets the stream's velocity instead of stopping at every goal.
    core = fast_core()

    def leader(t: float) -> float:
        f = min(1.0, t / 0.625)
        return 60.0 * f**3 * (10 - 15 * f + 6 * f * f)

    schedule = [(k / 100, {"Rotation": leader(k / 100)}) for k in range(1, 64)]
    emitted = drive(core, schedule, until=3.0)
    assert_within_limits(emitted, MODEL)
    # Lag: from when the leader was somewhere to when the emitted target got there.
    lags = []
    for t, targets in emitted:
        x = targets["Rotation"]
        if 3.0 < x < 57.0:
            low, high = 0.0, 0.625
            for _ in range(60):
                mid = (low + high) / 2
                low, high = (mid, high) if leader(mid) < x else (low, mid)
            lags.append(t - low)
    lags.sort()
    assert lags[len(lags) // 2] <= LAG  # (from the time a target stands for: a tick after its send)
    assert lags[-1] <= WORST_LAG
    assert emitted[-1][1]["Rotation"] == pytest.approx(60.0)
    assert max(targets["Rotation"] for _, targets in emitted) <= 60.0 + 1.0  # overshoot bound


def test_a_leaders_stream_is_followed_by_its_read_times_not_its_late_arrivals() -> None:
    # A leader read every 10 ms whose readings reach the robot 2 to 12 ms later (a bus and a
    # busy loop): by arrival the stream's pace jumps by half from one goal to the next, and
    # the trajectory trailed (27 ms at the median on a recorded run); measured at its read
    # times (`Command.stamp`), every goal is the hand's smooth motion and goes out whole the
    # moment it arrives, no lag added to its own.
    def leader(t: float) -> float:
        f = min(1.0, t / 0.625)
        return 60.0 * f**3 * (10 - 15 * f + 6 * f * f)

    delays = [0.002 + 0.01 * ((k * 7919) % 11) / 10 for k in range(64)]  # 2..12 ms, mixed
    schedule = [(k / 100 + delays[k], {"Rotation": leader(k / 100)}, k / 100) for k in range(1, 64)]
    emitted = drive(fast_core(), schedule, until=3.0)
    assert_within_limits(emitted, MODEL)
    assert emitted[-1][1]["Rotation"] == pytest.approx(60.0)
    sent = {
        round(t, 9): targets["Rotation"]
        for t, targets in drive(fast_core(), schedule, until=3.0, sent=True)
    }
    tick = fast_core().tick_interval
    for arrival, goal, _ in schedule:
        assert sent[round(arrival + tick, 9)] == goal["Rotation"]


def flick_schedule(seed: int) -> list[tuple[float, dict[str, float], float]]:
    """A leader's flick as Arena's leader arm sends it: 20 degrees in 0.13 s (minimum jerk:
    288 deg/s at its peak, over the so-arm100's 270), read in whole encoder steps every
    2.35 ms or so, the newest read sent every 10 ms, stamped with its read time and arriving up
    to 1 ms later; the phases and the jitter from `seed`."""
    rng = random.Random(seed)
    step = 360.0 / 4096
    start = 0.1 + 0.3 * rng.random()  # (the hand at rest until then)

    def leader(t: float) -> float:
        f = min(1.0, max(0.0, (t - start) / 0.13))
        return round(20.0 * f**3 * (10 - 15 * f + 6 * f * f) / step) * step

    reads, t = [], rng.random() * 0.00235
    while t < start + 0.5:
        reads.append(t)
        t += 0.00235 * (1 + 0.1 * (rng.random() - 0.5))
    schedule, last, k = [], -1.0, 0
    while k < len(reads):
        at = max(reads[k], last + 0.01)
        while k + 1 < len(reads) and reads[k + 1] <= at:
            k += 1
        last = at
        schedule.append((at + rng.random() * 0.001, {"Rotation": leader(reads[k])}, reads[k]))
        k += 1
    return schedule


def test_a_flick_is_followed_without_carrying_the_arm_past_where_the_hand_stopped() -> None:
    # Trailing a flick at the velocity cap, the stream's goals were approached relative to
    # their last velocity: when the hand stopped, the ticks carried the arm on at that velocity
    # past it (2.0 degrees in the worst of these plays). A held-back joint now heads for its
    # goal, never past it nor away from it; what the limits cannot stop in time they carry on,
    # as little as they allow (0.7 degrees at worst here).
    worst = 0.0
    for seed in range(30):
        emitted = drive(fast_core(), flick_schedule(seed), until=1.5)
        assert_within_limits(emitted, MODEL)
        assert emitted[-1][1]["Rotation"] == pytest.approx(20.0, abs=0.1)
        worst = max(worst, max(targets["Rotation"] for _, targets in emitted) - 20.0)
    assert worst <= 1.0, f"the arm went {worst:.2f} degrees past where the hand stopped"


def test_a_step_after_a_rest_starts_from_rest_now() -> None:
    # A move that ended (its last three targets still a decelerating line), a rest of seconds,
    # another step: it was planned from those targets' divided differences dated at their
    # time, so sampled now it was already past its end: the whole step in one target (an
    # intervening master's 60-degree move back was one target).
    core = fast_core()
    emitted = drive(core, [(0.0, {"Rotation": -60.0}), (3.0, {"Rotation": 0.0})], until=5.0)
    assert_within_limits(emitted, MODEL)
    assert emitted[-1][1]["Rotation"] == 0.0
    # (the divided differences across the rest see a jump as a slow move: each step is
    # bounded as well, by the velocity limit over a tick)
    cap = MODEL.joints[0].max_velocity * core.tick_interval * (1 + TOL)
    values = [targets["Rotation"] for _, targets in emitted]
    assert all(abs(b - a) <= cap for a, b in itertools.pairwise(values))


def test_a_command_speed_caps_the_trajectory() -> None:
    core = fast_core()
    emitted = drive(core, [(0.0, {"Rotation": 30.0})], until=5.0, speed=20.0)
    v, _, _ = derivatives(emitted, "Rotation")
    assert max(v) <= 20.0 * (1 + TOL)
    assert emitted[-1][1]["Rotation"] == 30.0


def test_an_estop_freezes_at_once_mid_motion() -> None:
    from arena.robot import safety as sm

    core = fast_core()
    emitted = drive(core, [(0.0, {"Rotation": 90.0})], until=0.2)
    held = emitted[-1][1]
    core.handle(sm.EStop("test"), 0.2)
    assert core.motion.goals == held and not core.motion.moving
    assert core.tick(0.21) is None and core.next_tick(0.21) is None


def test_the_issues_move_runs_the_straight_line_the_guard_checked() -> None:
    # Issue 57: from zero to Rotation -45, Pitch 30, Elbow 30, Wrist_Pitch -40 is accepted with
    # nothing clamped; with joints at their own pace the arm left the checked line and the
    # guard stopped it part-way. Joints in step: every target on the line, and it arrives.
    core = fast_core()
    goal = {"Rotation": -45.0, "Pitch": 30.0, "Elbow": 30.0, "Wrist_Pitch": -40.0}
    emitted = drive(core, [(0.0, goal)], until=5.0)
    assert core.collision_stops == 0
    assert {name: emitted[-1][1][name] for name in goal} == goal
    for _, targets in emitted:
        share = targets["Rotation"] / goal["Rotation"]
        for name, value in goal.items():
            assert targets[name] == pytest.approx(share * value, abs=1e-9)
    assert_within_limits(emitted, MODEL)


def test_a_state_ruckig_finds_no_profile_for_is_planned_all_the_same() -> None:
    # Ruckig 0.19 raises on this state (met in tests/test_collision.py's burst), with any
    # synchronization; the same with the acceleration a millionth lower it solves.
    from ruckig import Trajectory

    from arena.robot.motion import MotionLimiter

    limiter = MotionLimiter(MODEL, 0.0)
    # (at the limits it was met with: 200.5 deg/s, full speed in 33 ms, full acceleration in
    # 40 ms)
    velocity = math.degrees(3.5)
    limiter._speeds = [velocity] * 6
    limiter._input.max_acceleration = [30.0 * velocity] * 6
    limiter._input.max_jerk = [25.0 * 30.0 * velocity] * 6
    trajectory = Trajectory(6)
    p = [17.78371797337839, 0, 0, 0, 0, 0]
    v = [-46.41630668564321, 0, 0, 0, 0, 0]
    a = [-5760.374432796545, 0, 0, 0, 0, 0]
    assert limiter._solve(trajectory, p, v, a, [16.1, 0, 0, 0, 0, 0], None)
    assert limiter.fallbacks >= 1
    assert trajectory.at_time(trajectory.duration)[0][0] == pytest.approx(16.1)


def test_a_robot_at_rest_costs_no_plan_and_no_tick() -> None:
    # The fleet's commands (a joint at rest moved 0.001 degree) were planned and then ticked
    # three times each; a goal where the joint is costs nothing at all.
    core = fast_core()
    start = core.motion.positions["Rotation"]
    emitted = drive(
        core, [(0.1 * k, {"Rotation": start + 0.001 * (k % 2)}) for k in range(20)], 2.1
    )
    assert core.motion.plans == 0
    assert core.motion.jumps == 19  # each move (the first command moves nothing): one target
    assert [t["Rotation"] for _, t in emitted[1:]] == [start + 0.001, start] * 9 + [start + 0.001]
    assert core.next_tick(2.1) is None and core.tick(2.1) is None
    here = core.motion.positions["Rotation"]  # a goal where the joint rests: nothing to do
    result, step = core.command(None, Command.of({"Rotation": here}), 2.2)
    assert result.accepted and step.targets is None and core.next_tick(2.2) is None
    assert core.motion.plans == 0 and core.motion.jumps == 19


def test_a_stream_that_stops_comes_to_rest_on_its_last_goal() -> None:
    # A stream followed at its own velocity coasts past its last goal until the next is
    # overdue, then comes back and rests exactly on it, within the limits.
    core = fast_core()
    schedule = [(k / 100, {"Rotation": 1.0 * k}) for k in range(1, 31)]  # 100 deg/s, then stops
    emitted = drive(core, schedule, until=2.0)
    assert_within_limits(emitted, MODEL)
    assert emitted[-1][1]["Rotation"] == 30.0
    assert not core.motion.moving
    overshoot = max(t["Rotation"] for _, t in emitted) - 30.0
    assert 0.0 <= overshoot < 5.0  # at most the braking of a 100 deg/s stop


def ticked_every_interval(
    core: RobotCore, schedule: list[tuple[float, dict[str, float]]], until: float
) -> tuple[list[tuple[float, dict[str, float]]], int]:
    """`drive` with a tick every interval from each command while anything moves (the actor
    before `reschedule`): the targets and how many ticks ran."""
    emitted = [(0.0, core.motion.positions)]
    pending, ticks, tick = list(schedule), 0, None
    while True:
        at = min(pending[0][0] if pending else math.inf, math.inf if tick is None else tick)
        if at > until:
            return emitted, ticks
        if pending and pending[0][0] <= at:
            now, goals = pending.pop(0)
            targets = core.command(None, Command.of(goals), now)[1].targets
            tick = tick if tick is not None else core.next_tick(now)
        else:
            now, ticks = at, ticks + 1
            targets = core.tick(now)
            tick = now + core.tick_interval if core.motion.moving else None
        if targets is not None:
            emitted.append((core.motion.sampled, targets))


def counting_ticks(core: RobotCore) -> list[float]:
    """The times `core` is ticked from now on (its `tick` wrapped)."""
    ticks: list[float] = []
    tick = core.tick

    def counted(now: float) -> dict[str, float] | None:
        ticks.append(now)
        return tick(now)

    core.tick = counted  # type: ignore[method-assign]
    return ticks


@pytest.mark.parametrize("rate", [50.0, 30.0, 100.0])
def test_a_stream_on_time_is_not_ticked_and_its_targets_are_the_same(rate: float) -> None:
    # A tick in a stream on time sent nothing (the next command moves it on): the actor now
    # plans none until the stream is overdue. The targets are those of ticking every interval.
    schedule = [
        (k / rate, {"Rotation": 20.0 * math.sin(k / rate * 3.0), "Elbow": 10.0 * k / rate})
        for k in range(1, int(rate) + 1)
    ]
    core = fast_core()
    ticks = counting_ticks(core)
    emitted = drive(core, schedule, until=3.0)
    every, ticked = ticked_every_interval(fast_core(), schedule, until=3.0)
    last = schedule[-1][0]
    stream_end = last + core.tick_interval  # (what the last command's target stands for)
    during = [(t, p) for t, p in emitted if t <= stream_end]
    assert during == [(t, p) for t, p in every if t <= stream_end]
    # Ticked only while its start from rest held it back (was: one or two every command).
    assert all(t < 0.1 for t in ticks if t < last) and ticked >= len(schedule)
    # Overdue (OVERDUE intervals after its last goal), it comes to rest on its last goal.
    assert min(t for t in ticks if t >= last) == pytest.approx(last + OVERDUE / rate)
    assert_within_limits(emitted, MODEL)
    assert emitted[-1][1] == pytest.approx({**core.motion.goals, **schedule[-1][1]})
    assert not core.motion.moving


def test_a_goal_left_for_the_next_tick_gets_it_whatever_tick_was_planned() -> None:
    # A stream on time plans its next tick when it would be overdue; a command in the middle
    # of a burst leaves its goal to the next tick, which must then be a tick away.
    core = fast_core()  # a 10 Hz stream (a slow policy's actions)
    drive(core, [(k / 10, {"Rotation": 1.0 * k}) for k in range(1, 11)], until=1.0)
    planned = core.next_tick(1.0)
    assert planned == pytest.approx(1.0 + OVERDUE / 10)
    result, step = core.command(None, Command.of({"Rotation": 11.0}), 1.1, in_burst=True)
    assert result.accepted and step.targets is None  # (moving: the next tick takes it)
    assert core.motion.quiet_until is None
    due = core.reschedule(planned, 1.1)
    assert due == pytest.approx(1.1 + core.tick_interval)
    assert core.tick(due) is not None  # and it moves on to it


@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize("stamped", [False, True])
def test_a_jittered_stream_keeps_the_limits_with_its_ticks_put_off(
    seed: int, stamped: bool
) -> None:
    # Off the tick grid (20 +- 6 ms apart), a tick after a command held back starts from that
    # command, so the targets sample other times than ticking every interval: the limits and
    # the rest on the last goal hold all the same.
    rng = random.Random(seed)
    schedule: list[tuple[float, dict[str, float], float]] = []
    t = 0.0
    for _ in range(80):
        t += 0.02 + rng.uniform(-0.006, 0.006)
        goals = {"Rotation": 25.0 * math.sin(2.5 * t), "Elbow": 15.0 * math.cos(1.7 * t) - 15}
        schedule.append((t + rng.uniform(0.0, 0.003), goals, t))
    runs = [(at, goals, read) if stamped else (at, goals) for at, goals, read in schedule]
    core = fast_core()
    ticks = counting_ticks(core)
    emitted = drive(core, runs, until=schedule[-1][0] + 2.0)
    assert_within_limits(emitted, MODEL)
    assert emitted[-1][1] == pytest.approx({**core.motion.goals, **schedule[-1][1]})
    assert len([t for t in ticks if t < schedule[-1][0]]) < len(schedule) // 2  # (was 2 each)
