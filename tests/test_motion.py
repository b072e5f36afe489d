"""Motion safety and the pure robot core: validation, clamping, velocity, interpolation, rates."""

from __future__ import annotations

import dataclasses
import itertools
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from arena.protocol.errors import ArenaError, ErrorCode
from arena.robot import safety as sm
from arena.robot.core import RobotCore
from arena.robot.model import RobotModel, load_robot_model
from arena.robot.motion import (
    Command,
    JoinRamp,
    JointGoal,
    MotionLimiter,
    RateLimiter,
    resolve_command,
)

MODEL = load_robot_model("so-arm100")
V = MODEL.joints[0].max_velocity  # deg/s, the same for every so-arm100 joint
LEAD = 1.0 / MODEL.safety.control_rate  # targets stand for a tick ahead of their send


def unlimited_core(model: RobotModel = MODEL) -> RobotCore:
    """A core with the command rate limit out of the way."""
    return RobotCore(
        model, 0.0, dataclasses.replace(model.safety, command_rate=1e9, command_burst=10**9)
    )


# --- validation -------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("command", "code"),
    [
        (Command(()), ErrorCode.EMPTY_COMMAND),
        (Command.of({"Shoulder": 1.0}), ErrorCode.UNKNOWN_JOINT),
        (Command.of({"Rotation": math.nan}), ErrorCode.INVALID_VALUE),
        (Command.of({"Rotation": math.inf}), ErrorCode.INVALID_VALUE),
        (Command.of({"Rotation": -math.inf}), ErrorCode.INVALID_VALUE),
        (Command((JointGoal("Rotation", True),)), ErrorCode.INVALID_VALUE),
        (Command((JointGoal("Rotation", "45"),)), ErrorCode.INVALID_VALUE),  # type: ignore[arg-type]
        (
            Command((JointGoal("Rotation", 1.0), JointGoal("shoulder_pan", 2.0))),
            ErrorCode.INVALID_VALUE,
        ),
        (Command((JointGoal("Rotation", 1.0, speed=0.0),)), ErrorCode.INVALID_VALUE),
        (Command((JointGoal("Rotation", 1.0, speed=math.nan),)), ErrorCode.INVALID_VALUE),
        (Command.of({"Rotation": 1.0}, duration=-1.0), ErrorCode.INVALID_VALUE),
        (Command.of({"Rotation": 1.0}, duration=math.inf), ErrorCode.INVALID_VALUE),
    ],
)
def test_bad_commands_are_refused_with_a_code(command: Command, code: ErrorCode) -> None:
    with pytest.raises(ArenaError) as info:
        resolve_command(MODEL, command)
    assert info.value.code is code
    assert info.value.message


def test_aliases_resolve_to_protocol_names_and_clamps_are_reported() -> None:
    goals, clamps = resolve_command(MODEL, Command.of({"shoulder_pan": 500.0, "gripper": 10.0}))
    assert [(g.name, g.value) for g in goals] == [
        ("Rotation", MODEL.joints[0].upper),
        ("Jaw", 10.0),
    ]
    assert len(clamps) == 1
    assert clamps[0].joint == "Rotation" and clamps[0].requested == 500.0
    assert clamps[0].applied == MODEL.joints[0].upper


def test_speed_can_only_lower_the_velocity_limit() -> None:
    goals, _ = resolve_command(
        MODEL, Command((JointGoal("Rotation", 1, speed=50), JointGoal("Pitch", 1, speed=5000)))
    )
    assert [g.speed for g in goals] == [50.0, V]


# --- the limiter ------------------------------------------------------------------------------


def test_a_command_speed_slows_the_move() -> None:
    core = unlimited_core()
    _, step = core.command(None, Command((JointGoal("Rotation", 10.0, speed=10.0),)), 0.0)
    assert step.targets is not None and 0.0 < step.targets["Rotation"] < 10.0 * 0.01
    now = 0.0
    while (due := core.next_tick(now)) is not None:
        now = due
        core.tick(now)
    # 10 degrees at no more than 10 deg/s: a second, plus a little to speed up and slow down.
    assert 1.0 <= now <= 1.1
    assert core.motion.positions["Rotation"] == 10.0


def test_freeze_stops_every_joint_where_it_is() -> None:
    limiter = MotionLimiter(MODEL, 0.0)
    goals, _ = resolve_command(MODEL, Command.of({"Rotation": 90.0, "Elbow": -50.0}))
    limiter.set_goals(goals, None, 0.0)
    limiter.advance(0.0)
    limiter.advance(0.1)
    limiter.freeze()
    assert not limiter.moving
    assert limiter.goals == limiter.positions
    assert limiter.advance(1.0) is None


def test_rate_limiter_allows_the_burst_then_the_rate() -> None:
    limiter = RateLimiter(100.0, 10, 0.0)
    assert all(limiter.allow(0.0) for _ in range(10))
    assert not limiter.allow(0.0)
    assert not limiter.allow(0.005)
    assert limiter.allow(0.0101)
    assert sum(limiter.allow(1.0 + i * 0.01) for i in range(100)) == 100  # steady 100/s passes


def test_the_core_answers_the_excess_with_rate_limited() -> None:
    core = RobotCore(MODEL, 0.0)
    answers = [core.command(None, Command.of({"Rotation": 0.1 * i}), 0.0)[0] for i in range(12)]
    assert [a.accepted for a in answers] == [True] * 10 + [False] * 2
    assert answers[-1].code is ErrorCode.RATE_LIMITED
    assert "100" in answers[-1].message


def test_rate_limits_are_per_master() -> None:
    core = RobotCore(MODEL, 0.0)
    core.handle(sm.MasterAttach("alice"), 0.0)
    for _ in range(10):
        core.command("alice", Command.of({"Rotation": 1.0}), 0.0)
    assert core.command("alice", Command.of({"Rotation": 1.0}), 0.0)[0].code is (
        ErrorCode.RATE_LIMITED
    )
    core.handle(sm.MasterAttach("bob", takeover=True), 0.0)
    assert core.command("bob", Command.of({"Rotation": 1.0}), 0.0)[0].accepted


def test_estop_freezes_and_reset_moves_nothing() -> None:
    core = unlimited_core()
    core.command(None, Command.of({"Rotation": 90.0}), 0.0)
    core.tick(0.01)
    step = core.handle(sm.EStop("test"), 0.02)
    assert step.targets is None
    frozen = core.motion.positions
    assert core.next_tick(0.02) is None
    assert core.tick(0.5) is None
    result, step = core.command(None, Command.of({"Rotation": 0.0}), 0.6)
    assert not result.accepted and result.code is ErrorCode.ESTOPPED and step.targets is None
    step = core.handle(sm.Reset(), 1.0)
    assert step.targets is None and core.next_tick(1.0) is None
    assert core.motion.positions == frozen
    result, step = core.command(None, Command.of({"Rotation": frozen["Rotation"] - 1}), 1.1)
    assert result.accepted and step.targets is not None


# --- random operation sequences against the invariants -----------------------------------------

JOINT_NAMES = [*MODEL.joint_names, "shoulder_pan", "gripper", "Bogus"]
VALUES = st.one_of(st.floats(-400, 400), st.sampled_from([math.nan, math.inf, 0.0]))
GOALS = st.lists(
    st.builds(
        JointGoal, st.sampled_from(JOINT_NAMES), VALUES, st.one_of(st.none(), st.floats(1, 400))
    ),
    min_size=1,
    max_size=4,
)
SOURCES = st.sampled_from([None, "alice", "bob"])
OPS = st.one_of(
    st.tuples(
        st.just("command"),
        SOURCES,
        GOALS,
        st.one_of(st.none(), st.floats(0, 1.5)),
        st.booleans(),  # one of a master's burst
    ),
    st.tuples(st.just("attach"), st.sampled_from(["alice", "bob"]), st.booleans()),
    st.tuples(st.just("detach"), st.sampled_from(["alice", "bob"])),
    st.tuples(st.just("lost"), st.sampled_from(["alice", "bob"])),
    st.tuples(st.just("estop")),
    st.tuples(st.just("reset")),
    st.tuples(st.just("wait"), st.floats(0.0005, 0.3)),
)


def _event_for(op: tuple) -> sm.Event:  # type: ignore[type-arg]
    kind = op[0]
    if kind == "attach":
        return sm.MasterAttach(op[1], takeover=op[2])
    if kind == "detach":
        return sm.MasterDetach(op[1])
    if kind == "lost":
        return sm.MasterLost(op[1])
    return sm.EStop("test") if kind == "estop" else sm.Reset()


@settings(max_examples=300, deadline=None)
@given(st.lists(OPS, max_size=40))
def test_random_operations_keep_targets_safe(ops: list[tuple]) -> None:  # type: ignore[type-arg]
    core = unlimited_core()
    now = 0.0
    emitted: list[tuple[float, dict[str, float]]] = [(0.0, core.motion.positions)]

    def record(targets: dict[str, float] | None, estopped_before: bool) -> None:
        if targets is None:
            return
        assert not estopped_before, "a target was sent while e-stopped"
        assert core.state.mode is not sm.Mode.ESTOPPED
        emitted.append((now, dict(targets)))

    for op in ops:
        estopped = core.state.mode is sm.Mode.ESTOPPED
        kind = op[0]
        if kind == "command":
            _, source, goals, duration, in_burst = op
            owner_before = core.state.owner
            goals_before = core.motion.goals
            result, step = core.command(
                source, Command(tuple(goals), duration), now, in_burst=in_burst
            )
            if source is not None and source != owner_before:
                assert not result.accepted and step.targets is None
                assert core.motion.goals == goals_before, "a non-owner changed a target"
            if source is None and owner_before is not None:
                assert not result.accepted
            record(step.targets, estopped)
        elif kind == "wait":
            # Tick on a fixed grid whether or not the core asks for it: a tick that comes when
            # nothing should move must move nothing.
            end = now + op[1]
            while now + core.tick_interval <= end:
                now += core.tick_interval
                was_moving = core.motion.moving
                targets = core.tick(now)
                # The actor stops ticking when `moving` says so: it must never be stale.
                assert targets is None or was_moving, "a joint moved while not `moving`"
                record(targets, core.state.mode is sm.Mode.ESTOPPED)
            now = end
        else:
            event = _event_for(op)
            record(core.handle(event, now).targets, estopped)
        if core.motion.positions != core.motion.goals:
            assert core.motion.moving, "a joint short of its goal is not `moving`"
        # (a move made in one target sends its goals in their own order: the joints')
        assert list(core.motion.goals) == list(core.motion.positions) == list(MODEL.joint_names)

    for _, targets in emitted:
        for joint in MODEL.joints:
            assert joint.lower <= targets[joint.name] <= joint.upper
    for i, (t1, first) in enumerate(emitted):
        for t2, second in emitted[i + 1 :]:
            for joint in MODEL.joints:
                bound = joint.max_velocity * (t2 - t1 + LEAD) + 1e-6
                assert abs(second[joint.name] - first[joint.name]) <= bound


@settings(max_examples=100, deadline=None)
@given(
    st.lists(
        st.tuples(
            st.sampled_from(["aim", "advance", "stop_at", "freeze"]),
            st.sampled_from([j.name for j in MODEL.joints]),
            st.floats(-50.0, 50.0),
        ),
        max_size=30,
    )
)
def test_the_limiters_joints_stay_inside_their_limits_and_end_on_their_goals(
    steps: list[tuple[str, str, float]],
) -> None:
    # Whatever mix of goals (steps and streams), advances, stops and freezes: every target
    # inside the joint limits, and left alone the joints come to rest exactly on the goals.
    limiter = MotionLimiter(MODEL, 0.0)
    now = 0.0
    for action, name, value in steps:
        now += 0.01
        if action == "aim":
            limiter.set_goals(resolve_command(MODEL, Command.of({name: value}))[0], None, now)
        elif action == "advance":
            limiter.advance(now)
        elif action == "stop_at":
            limiter.stop_at(limiter.positions)
        else:
            limiter.freeze()
        for joint in MODEL.joints:
            assert joint.lower <= limiter.positions[joint.name] <= joint.upper
    for _ in range(1000):
        if not limiter.moving:
            break
        now += 0.01
        limiter.advance(now)
    assert not limiter.moving
    assert limiter.positions == limiter.goals


# --- joining ----------------------------------------------------------------------------------

DEGREES = st.floats(-90.0, 90.0, allow_nan=False)


@settings(max_examples=200, deadline=None)
@given(
    start=st.lists(DEGREES, min_size=6, max_size=6),
    steps=st.lists(
        st.tuples(st.floats(0.0, 0.5), st.lists(DEGREES, min_size=6, max_size=6)),
        min_size=1,
        max_size=30,
    ),
    speed=st.floats(0.5, 90.0),
)
def test_a_join_never_outruns_its_speed_and_arrives(
    start: list[float], steps: list[tuple[float, list[float]]], speed: float
) -> None:
    """Whatever the robot's targets do meanwhile, a joining slave's targets move at most
    `speed * dt` per joint from its measured start, and reach a robot pose that stays put."""
    names = MODEL.joint_names
    ramp = JoinRamp(MODEL, dict(zip(names, start, strict=True)), speed, 0.0)
    now, last = 0.0, dict(zip(names, start, strict=True))
    for dt, goal in steps:
        now += dt
        targets = ramp.advance(dict(zip(names, goal, strict=True)), now)
        if targets is None:
            continue
        for name in names:
            assert abs(targets[name] - last[name]) <= speed * dt + 1e-9
        last = targets
    final = dict(zip(names, steps[-1][1], strict=True))
    needed = max(abs(final[name] - last[name]) for name in names) / speed
    assert ramp.arrived(final) == (needed == 0.0)
    # (and the time to get to the speed at the acceleration limit; 1 us: the rounding)
    ramp.advance(final, now + needed + speed / MODEL.joints[0].max_acceleration + 1e-6)
    assert ramp.arrived(final)


@pytest.mark.parametrize(("speed", "distance"), [(90.0, 30.0), (15.0, 3.0), (90.0, 0.3)])
def test_a_join_starts_from_rest_and_lands_within_the_acceleration_limit(
    speed: float, distance: float
) -> None:
    # At the control ticks (100 Hz), from rest to rest on the robot's pose: no velocity change
    # between two ticks over the acceleration limit (velocity-limited only, the join went from
    # rest to 90 deg/s in one tick: 9,000 deg/s^2 where the so-arm100's limit is 8,100).
    names = MODEL.joint_names
    ramp = JoinRamp(MODEL, dict.fromkeys(names, 0.0), speed, 0.0)
    goal = {**dict.fromkeys(names, 0.0), "Rotation": distance}
    positions, now = [0.0, 0.0], 0.0
    while not ramp.arrived(goal):
        now += 0.01
        ramp.advance(goal, now)
        positions.append(ramp.positions["Rotation"])
        assert now < 5.0
    positions.append(distance)  # (at rest there)
    velocities = [(b - a) / 0.01 for a, b in itertools.pairwise(positions)]
    assert max(abs(v) for v in velocities) <= speed + 1e-9
    limit = MODEL.joints[0].max_acceleration
    for before, after in itertools.pairwise(velocities):
        assert abs(after - before) / 0.01 <= limit * (1 + 1e-9), velocities


def test_a_join_moves_no_joint_faster_than_its_own_velocity_limit() -> None:
    slow = dataclasses.replace(MODEL.joints[0], max_velocity=5.0)
    model = dataclasses.replace(MODEL, joints=(slow, *MODEL.joints[1:]))
    ramp = JoinRamp(model, dict.fromkeys(MODEL.joint_names, 0.0), 20.0, 0.0)
    targets = ramp.advance(dict.fromkeys(MODEL.joint_names, 50.0), 1.0)
    assert targets is not None
    assert targets["Rotation"] == 5.0 and targets["Pitch"] == 20.0


def test_a_timed_move_ends_exactly_on_its_goal_and_stops_ticking() -> None:
    # 67.2 + (-13.4 - 67.2) is -13.400000000000006 in floating point: the last target must be
    # the goal itself, or the limiter would go on ticking toward a goal it never reaches.
    limiter = MotionLimiter(MODEL, 0.0, {"Rotation": 67.2})
    goals, _ = resolve_command(MODEL, Command.of({"Rotation": -13.4}))
    limiter.set_goals(goals, 2.0, 0.0)
    for step in range(201):
        limiter.advance(2.0 * step / 200)
    assert limiter.positions["Rotation"] == -13.4
    assert not limiter.moving


def test_a_stop_leaves_nothing_moving() -> None:
    limiter = MotionLimiter(MODEL, 0.0)
    goals, _ = resolve_command(MODEL, Command.of({"Rotation": 90.0}))
    limiter.set_goals(goals, None, 0.0)
    limiter.advance(0.0)
    assert limiter.moving
    limiter.stop_at(limiter.positions)
    assert not limiter.moving
    assert limiter.advance(1.0) is None


def test_a_pose_learned_mid_move_keeps_the_commanded_goal_and_the_move_goes_on() -> None:
    limiter = MotionLimiter(MODEL, 0.0)
    goals, _ = resolve_command(MODEL, Command.of({"Rotation": 90.0}))
    limiter.set_goals(goals, None, 0.0)
    limiter.advance(0.0)  # Rotation trails its goal at the velocity limit
    taken = limiter.adopt({**limiter.positions, "Rotation": 5.0, "Elbow": -20.0})
    assert taken["Rotation"] == 5.0
    assert limiter.goals["Rotation"] == 90.0  # the command still stands
    assert limiter.goals["Elbow"] == -20.0  # a joint at rest stays where the arm is
    assert limiter.moving
    now = 0.0
    while limiter.moving and now < 5.0:
        now += 0.01
        limiter.advance(now)
    assert limiter.positions["Rotation"] == 90.0


def test_a_join_that_has_arrived_or_had_no_time_gives_no_target() -> None:
    ramp = JoinRamp(MODEL, dict.fromkeys(MODEL.joint_names, 0.0), 15.0, 0.0)
    goal = {**dict.fromkeys(MODEL.joint_names, 0.0), "Rotation": 3.0}
    assert ramp.advance(goal, 0.0) is None  # no time has passed: nothing may move
    assert ramp.advance(goal, 0.1) == {**goal, "Rotation": pytest.approx(1.5)}
    assert ramp.advance(goal, 0.1) is None
    assert ramp.advance(goal, 1.0) == goal
    assert ramp.advance(goal, 2.0) is None  # arrived: nothing more to send


def test_a_join_step_that_covers_the_rest_of_the_way_lands_on_the_goal() -> None:
    # |-3.9 - -11.4| is exactly 7.5, yet -11.4 + 7.5 is -3.9000000000000004.
    start = {**dict.fromkeys(MODEL.joint_names, 0.0), "Rotation": -11.4}
    goal = {**start, "Rotation": -3.9}
    ramp = JoinRamp(MODEL, start, 15.0, 0.0)
    ramp.advance(goal, 0.5)
    assert ramp.arrived(goal)


def test_a_timed_move_that_starts_later_follows_its_curve_from_its_own_start() -> None:
    limiter = MotionLimiter(MODEL, 5.0)
    goals, _ = resolve_command(MODEL, Command.of({"Rotation": 20.0}))
    limiter.set_goals(goals, 2.0, 5.0)  # from 5 s to 7 s
    now = 5.0
    while now < 6.0 - 1e-9:
        now += 0.01
        limiter.advance(now)
    assert limiter.positions["Rotation"] == pytest.approx(10.0, abs=1e-6)  # halfway at half time
