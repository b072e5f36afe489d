"""The policy master's timing and rules on trio's MockClock, with a stand-in for the worker
process (tests/test_policy_server.py runs the real one): commands at the policy's fps, the
watchdog, the e-stop, the step limit, a non-finite action, a worker that dies."""

from __future__ import annotations

import itertools
import math
import sys
from collections.abc import Callable
from pathlib import Path

import pytest
import trio
from trio.testing import MockClock

from arena.policy.master import PolicyMaster, PolicySettings, Shot
from arena.policy.process import LOAD_TIMEOUT, PolicyProcess, WorkerError, WorkerGone
from arena.policy.wire import Chunk, Feature, Loaded, Observe
from arena.protocol.errors import ArenaError, ErrorCode, Severity
from arena.robot.events import (
    CommandHandled,
    FaultReported,
    JointStatesReceived,
    PolicyInferred,
    RobotEvent,
    TargetsSent,
)
from arena.robot.handle import Robot
from arena.robot.mailbox import EventQueue
from arena.robot.manager import RobotManager
from arena.robot.model import load_robot_model
from arena.robot.motion import Command, CommandResult
from tests.conftest import RecordingSlave

IDENTITY = "policy:act:0123456789ab"
MODEL = load_robot_model("so-arm100")
FPS = 30.0
PERIOD = 1 / FPS
Actions = Callable[[Observe], list[tuple[float, ...]]]


def hold(observation: Observe) -> list[tuple[float, ...]]:
    """Ten actions that keep every joint where it is."""
    return [observation.state] * 10


class FakeWorker:
    """Answers each observation with `actions(observation)` after `latency` seconds of trio
    time; `kill()` ends it as a dead process would."""

    def __init__(self, actions: Actions = hold, latency: float = 0.05) -> None:
        self.actions = actions
        self.latency = latency
        self.observations: list[tuple[float, Observe]] = []
        self.dead = trio.Event()
        self.closed = False
        self.refuse: str | None = None  # answer every observation with this refusal

    async def load(self, path: Path) -> Loaded:
        return Loaded(
            "act",
            "0123456789ab",
            (
                Feature("observation.state", "STATE", (6,)),
                Feature("observation.images.front", "VISUAL", (3, 32, 32)),
            ),
            (Feature("action", "ACTION", (6,)),),
            10,
            0.0,
        )

    async def act(self, observation: Observe) -> Chunk:
        self.observations.append((trio.current_time(), observation))
        with trio.move_on_after(self.latency):
            await self.dead.wait()
        if self.dead.is_set() or self.closed:
            raise WorkerGone("the worker has exited (code -9)")
        if self.refuse is not None:
            raise WorkerError(self.refuse)
        return Chunk(observation.timestep, tuple(self.actions(observation)), self.latency)

    def kill(self) -> None:
        self.dead.set()

    async def close(self) -> None:
        self.closed = True


#: How old each camera frame is when an observation takes it (seconds of trio time).
FRAME_AGE = 0.02


def frames(cameras: tuple[str, ...]) -> Callable[[], dict[str, Shot | None]]:
    """The robot's cameras, each with a frame captured FRAME_AGE ago."""
    return lambda: dict.fromkeys(cameras, Shot(b"jpeg", trio.current_time() - FRAME_AGE))


async def attach(
    robot: Robot, worker: FakeWorker, cameras: tuple[str, ...] = ("front",), **settings: float
) -> PolicyMaster:
    async def start() -> FakeWorker:
        return worker

    master = PolicyMaster(
        PolicySettings(Path("unused"), task="wave", fps=FPS, **settings),  # type: ignore[arg-type]
        robot.model,
        frames(cameras),
        start,
    )
    await master.prepare()
    await robot.attach_master(master, master_id=master.master_id)
    return master


async def arm(manager: RobotManager) -> tuple[Robot, RecordingSlave]:
    robot = await manager.create_robot("so-arm100", robot_id="arm")
    slave = RecordingSlave()
    await robot.attach_slave(slave)
    return robot, slave


def handled(events: EventQueue[RobotEvent]) -> list[CommandHandled]:
    return [e for e in events.drain() if isinstance(e, CommandHandled)]


async def test_commands_flow_at_the_policys_fps_with_its_identity(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot, _ = await arm(manager)
    worker = FakeWorker()
    with robot.subscribe(kinds=[CommandHandled]) as events:
        master = await attach(robot, worker)
        assert robot.snapshot().master is not None
        assert robot.snapshot().master.kind == "policy"
        assert robot.snapshot().master.peer_id == IDENTITY
        await trio.sleep(2.0)
        commands = handled(events)
    # The first chunk comes 50 ms after the start, and its first action belongs to the step the
    # observation was taken at (gone by then): one command a period after that.
    assert 55 <= len(commands) <= 60
    assert all(c.result.accepted for c in commands)
    assert {c.source for c in commands} == {IDENTITY}
    assert {c.command.source for c in commands} == {IDENTITY}
    gaps = [b.time - a.time for a, b in itertools.pairwise(commands)]
    assert min(gaps) == pytest.approx(PERIOD) and max(gaps) == pytest.approx(PERIOD)
    # LeRobot's async inference: a new observation whenever half a chunk (5 of 10) is left.
    assert master.counters.inferences >= 10
    assert all(o.task == "wave" and o.images == {"front": b"jpeg"} for _, o in worker.observations)


async def test_the_watchdog_holds_the_robot_after_two_empty_periods(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot, _ = await arm(manager)
    worker = FakeWorker()
    with robot.subscribe(kinds=[CommandHandled, FaultReported]) as events:
        master = await attach(robot, worker)
        await trio.sleep(0.5)
        worker.latency = 2.0  # inference now takes 60 periods: the queue runs dry
        await trio.sleep(1.0)
        seen = events.drain()
    faults = [e for e in seen if isinstance(e, FaultReported)]
    commands = [e for e in seen if isinstance(e, CommandHandled)]
    assert [(f.code, f.severity, f.peer_id) for f in faults] == [
        (ErrorCode.POLICY_STALLED, Severity.WARNING, IDENTITY)
    ]
    # The fault comes two periods after the last command, and nothing is sent after it.
    assert faults[0].time - commands[-1].time == pytest.approx(2 * PERIOD)
    assert "holds where it is" in faults[0].message
    assert master.counters.stalls == 1 and robot.snapshot().owner == IDENTITY
    # Once a chunk comes again, the policy drives again.
    with robot.subscribe(kinds=[CommandHandled]) as events:
        await trio.sleep(2.0)
        assert handled(events)


async def test_a_dead_worker_trips_the_watchdog_and_the_robot_is_handed_back(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot, _ = await arm(manager)
    worker = FakeWorker()
    with robot.subscribe(kinds=[CommandHandled, FaultReported]) as events:
        await attach(robot, worker)
        await trio.sleep(0.5)
        worker.kill()
        killed = trio.current_time()
        await trio.sleep(1.0)
        seen = events.drain()
    faults = [e for e in seen if isinstance(e, FaultReported) and not e.cleared]
    assert [f.code for f in faults] == [ErrorCode.POLICY_STALLED]
    assert "exited" in faults[0].message
    # the master's fault, shown on it while it lasted, ends as it leaves
    ended = [e for e in seen if isinstance(e, FaultReported) and e.cleared]
    assert [(f.code, f.peer_id) for f in ended] == [(ErrorCode.POLICY_STALLED, IDENTITY)]
    # The queue held at most a chunk (10 actions) when the worker died.
    assert faults[0].time - killed <= 12 * PERIOD
    assert robot.snapshot().master is None and worker.closed


async def test_a_policy_that_refuses_every_observation_trips_the_watchdog_saying_why(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot, _ = await arm(manager)
    worker = FakeWorker()
    worker.refuse = "RuntimeError: mat1 and mat2 shapes cannot be multiplied"
    with robot.subscribe(kinds=[CommandHandled, FaultReported]) as events:
        master = await attach(robot, worker)
        await trio.sleep(1.0)
        seen = events.drain()
    assert [type(e) for e in seen] == [FaultReported]
    assert seen[0].code == ErrorCode.POLICY_STALLED and "mat1 and mat2" in seen[0].message
    # Refused observations are retried once a period, never in a busy loop.
    assert len(worker.observations) <= FPS + 1 and master.counters.sent == 0
    assert robot.snapshot().owner == IDENTITY


async def test_an_estop_stops_the_commands_at_once_and_the_inference(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot, slave = await arm(manager)
    worker = FakeWorker()
    with robot.subscribe(kinds=[CommandHandled]) as events:
        await attach(robot, worker)
        await trio.sleep(0.5)
        assert handled(events)
        await robot.estop("test")
        stopped = trio.current_time()
        asked = len(worker.observations)
        await trio.sleep(1.0)
        assert handled(events) == []
    assert worker.closed and len(worker.observations) == asked
    assert robot.snapshot().master is None
    assert all(at <= stopped for at, _ in slave.targets)


def jump(by: float) -> Actions:
    """Ten actions that turn the base `by` degrees from where it is (a move far from the
    floor and the arm's own links)."""
    return lambda o: [(o.state[0] + by, *o.state[1:])] * 10


async def test_the_step_limit_clamps_each_target_near_the_measured_position(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot, _ = await arm(manager)
    worker = FakeWorker(jump(50.0))
    start = {j.name: j.virtual_value for j in robot.snapshot().joints}
    with robot.subscribe(kinds=[CommandHandled, TargetsSent]) as events:
        master = await attach(robot, worker, max_relative_target=4.0)
        await trio.sleep(1.0)
        seen = events.drain()
    virtual, commands = dict(start), 0
    for event in seen:
        if isinstance(event, TargetsSent):
            virtual.update(event.joints)
        elif isinstance(event, CommandHandled) and event.result.accepted:
            commands += 1
            for goal in event.command.joints:
                assert abs(goal.value - virtual[goal.name]) <= 4.0 + 1e-9
    assert commands > 20 and master.counters.clamped >= commands
    # Without the limit the same policy asks for 50 degrees at once.
    worker2 = FakeWorker(jump(50.0))
    await robot.detach_master(IDENTITY)
    with robot.subscribe(kinds=[CommandHandled]) as events:
        await attach(robot, worker2, max_relative_target=None)  # type: ignore[arg-type]
        await trio.sleep(0.2)
        first = handled(events)[0]
    here = {j.name: j.virtual_value for j in robot.snapshot().joints}
    assert max(abs(g.value - here[g.name]) for g in first.command.joints) > 4.0


async def test_an_action_that_is_not_finite_is_never_sent(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot, slave = await arm(manager)
    worker = FakeWorker(lambda o: [(*o.state[:5], math.nan)] * 10)
    with robot.subscribe(kinds=[CommandHandled, FaultReported]) as events:
        master = await attach(robot, worker)
        await trio.sleep(1.0)
        seen = events.drain()
    assert not [e for e in seen if isinstance(e, CommandHandled)]
    faults = [e for e in seen if isinstance(e, FaultReported)]
    assert [(f.code, f.severity) for f in faults] == [
        (ErrorCode.POLICY_OUTPUT_INVALID, Severity.ERROR)
    ]
    assert "Jaw" in faults[0].message
    assert master.counters.invalid >= 25 and master.counters.sent == 0
    assert all(math.isfinite(v) for _, t in slave.targets for v in t.values())


async def test_a_policy_the_robot_cannot_feed_is_refused_naming_the_feature(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot, _ = await arm(manager)
    worker = FakeWorker()
    with pytest.raises(ArenaError) as refused:
        await attach(robot, worker, cameras=("wrist",))
    assert refused.value.code is ErrorCode.POLICY_INVALID
    assert "observation.images.front" in refused.value.message
    assert "wrist" in refused.value.message
    assert worker.closed and robot.snapshot().master is None


async def test_each_inference_is_reported_with_its_latency_chunk_and_frame_age(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot, _ = await arm(manager)
    worker = FakeWorker(latency=0.05)
    with robot.subscribe(kinds=[PolicyInferred, CommandHandled]) as events:
        master = await attach(robot, worker)
        await trio.sleep(1.0)
        seen = events.drain()
    inferences = [e for e in seen if isinstance(e, PolicyInferred)]
    assert len(inferences) == master.counters.inferences >= 5
    for event, (asked, observation) in zip(inferences, worker.observations, strict=False):
        assert event.policy == IDENTITY and event.robot_id == "arm"
        assert event.timestep == observation.timestep
        assert event.chunk_size == 10 and 1 <= event.kept <= 10
        # The round trip is the worker's 50 ms; the frame was 20 ms old when it was sent.
        assert event.latency == pytest.approx(0.05) and event.inference == pytest.approx(0.05)
        assert event.frame_age == pytest.approx(FRAME_AGE)
        assert event.time == pytest.approx(asked + 0.05)
    # Nothing had been taken when the first chunk came: all of it is kept. A later one answers
    # an observation of the step last taken, which has passed when it comes: not kept.
    assert inferences[0].kept == 10
    assert all(1 <= e.kept < 10 for e in inferences[1:])


async def test_a_worker_that_never_loads_is_refused_once_its_time_is_up(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot, _ = await arm(manager)
    worker = FakeWorker()
    hang = trio.Event()

    async def never(path: Path) -> Loaded:
        await hang.wait()
        raise AssertionError("unreachable")

    worker.load = never  # type: ignore[method-assign]
    started = trio.current_time()
    with pytest.raises(ArenaError) as refused:
        await attach(robot, worker, load_timeout=30.0)
    assert refused.value.code is ErrorCode.POLICY_NOT_READY
    assert "within 30 s" in refused.value.message
    assert trio.current_time() - started == pytest.approx(30.0)
    assert worker.closed and robot.snapshot().master is None


async def test_a_worker_process_that_never_answers_is_stopped_and_refused(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    """A real child process that never answers: the bound (the default, 180 s of virtual
    time) ends the wait, and the process is killed."""
    robot, _ = await arm(manager)
    started: list[PolicyProcess] = []

    async def start() -> PolicyProcess:
        hangs = [sys.executable, "-c", "import time; time.sleep(600)"]
        started.append(await PolicyProcess.start(hangs))
        return started[0]

    master = PolicyMaster(PolicySettings(Path("unused")), robot.model, frames(()), start)
    began = trio.current_time()
    with pytest.raises(ArenaError) as refused:
        await master.prepare()
    assert refused.value.code is ErrorCode.POLICY_NOT_READY
    assert trio.current_time() - began >= LOAD_TIMEOUT
    (process,) = started
    assert await process.child.process.wait() == -9 and process not in PolicyProcess.live


async def test_a_worker_that_exits_while_loading_is_refused_saying_so() -> None:
    """On the real clock: the worker's exit (its pipe's end) answers long before the bound."""

    async def start() -> PolicyProcess:
        return await PolicyProcess.start([sys.executable, "-c", "raise SystemExit(3)"])

    master = PolicyMaster(PolicySettings(Path("unused")), MODEL, frames(()), start)
    with pytest.raises(ArenaError) as refused:
        await master.prepare()
    assert refused.value.code is ErrorCode.POLICY_NOT_READY
    assert "exited (code 3)" in refused.value.message


async def test_with_the_physics_twin_commands_flow_at_fps_and_an_estop_stops_them_at_once(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    """The MuJoCo arm as the slave (stepped in trio time): the policy sees its lagging joints,
    turns the base at its fps, and an e-stop ends the commands and the targets in the same
    step; the arm then holds where it is."""
    from arena.drivers.physics import PhysicsSettings, PhysicsSlave

    robot = await manager.create_robot("so-arm100", robot_id="sim")
    await robot.attach_slave(PhysicsSlave(PhysicsSettings(realtime=False)))
    await trio.sleep(0.5)  # settled on its table
    # The base turns 3 degrees a step from where it is; the arm's joints stay at their
    # targets (the measured ones sag under gravity: held there, the guard would refuse).
    rest = [j.virtual_value for j in robot.snapshot().joints]  # (degrees: LeRobot's too)
    worker = FakeWorker(lambda o: [(o.state[0] + 3.0, *rest[1:5], o.state[5])] * 10)
    with robot.subscribe(kinds=[CommandHandled, TargetsSent, JointStatesReceived]) as events:
        await attach(robot, worker, max_relative_target=2.0)
        await trio.sleep(1.0)
        moving = events.drain()
        await robot.estop("test")
        stopped = trio.current_time()
        turned = joint_value(robot, "Rotation")
        await trio.sleep(1.0)
        after = events.drain()
    commands = [e for e in moving if isinstance(e, CommandHandled)]
    assert len(commands) >= 25 and {c.source for c in commands} == {IDENTITY}
    gaps = [b.time - a.time for a, b in itertools.pairwise(commands)]
    assert min(gaps) == pytest.approx(PERIOD) and max(gaps) == pytest.approx(PERIOD)
    # It observed the twin's measured joints, which lag behind its targets, and each step
    # is limited from where the arm is (a position measured since its last command, or the
    # one before), not from where it was told to go.
    observed = [o.state[0] for _, o in worker.observations]
    assert observed[-1] > observed[0] + 5.0
    seen: list[float] = [0.0]
    for event in moving:
        if isinstance(event, JointStatesReceived):
            seen.append(event.joints["Rotation"])
        elif isinstance(event, CommandHandled):
            goal = next(g.value for g in event.command.joints if g.name == "Rotation")
            assert min(abs(goal - value) for value in seen) <= 2.0 + 1e-9
            seen = seen[-1:]
    assert all(c.result.accepted for c in commands)
    assert not [e for e in after if isinstance(e, CommandHandled | TargetsSent)]
    assert robot.snapshot().master is None and worker.closed
    held = [e.joints["Rotation"] for e in after if isinstance(e, JointStatesReceived)]
    assert held and all(abs(value - turned) < 2.0 for value in held)
    assert all(e.time <= stopped for e in moving)


def joint_value(robot: Robot, name: str) -> float:
    """The joint's measured value."""
    value = next(j for j in robot.snapshot().joints if j.name == name).real_value
    assert value is not None
    return value


async def test_an_observation_goes_only_while_the_queue_is_low(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    """LeRobot's rule: an observation leaves when the queue holds at most half a chunk. The
    control loop's wake-ups during an inference must not send another the moment its chunk
    has refilled the queue."""
    robot, _ = await arm(manager)
    worker = FakeWorker(latency=0.05)
    await attach(robot, worker)
    await trio.sleep(2.0)
    steps = [o.timestep for _, o in worker.observations]
    # An observation at step t is answered 1.5 periods later with actions for t..t+9, of
    # which t+2..t+9 are still to come: 8, down to half a chunk (5) at step t+4.
    gaps = [b - a for a, b in itertools.pairwise(steps)]
    assert len(gaps) >= 10 and all(gap >= 4 for gap in gaps), steps


class SlowArm:
    """An `Arm` whose fifth command takes 1.8 periods to be answered (a busy robot)."""

    def __init__(self) -> None:
        self.started: list[float] = []

    def measured(self) -> tuple[float, ...]:
        return (0.0,) * 5 + (MODEL.joints[5].lower,)

    async def command(self, command: Command) -> CommandResult:
        self.started.append(trio.current_time())
        if len(self.started) == 5:
            await trio.sleep(1.8 * PERIOD)
        return CommandResult(True)

    def fault(self, source: str, code: ErrorCode, message: str, severity: Severity) -> None:
        raise AssertionError(message)

    def inferred(self, source: str, inference: object) -> None:
        pass

    paused = False  # never paused
    pauses = 0

    async def wait_resumed(self) -> None:
        pass


async def test_a_late_step_is_not_made_up_with_a_burst(autojump_clock: MockClock) -> None:
    """A step that ends late is followed a full period later, as LeRobot's loop does: never
    two commands in quick succession to catch up."""
    master = PolicyMaster(PolicySettings(Path("unused"), fps=FPS), MODEL, frames(("front",)))
    worker = FakeWorker()

    async def start() -> FakeWorker:
        return worker

    master.start_worker = start
    await master.prepare()
    arm = SlowArm()
    with trio.move_on_after(1.0):
        await master.drive(arm)
    gaps = [b - a for a, b in itertools.pairwise(arm.started)]
    assert len(gaps) > 20
    assert gaps[4] == pytest.approx(1.8 * PERIOD)  # the slow one, then at once the late step
    assert min(gaps) == pytest.approx(PERIOD)


# -- seams (issue 57) --------------------------------------------------------------------------


def disagreeing(observation: Observe) -> list[tuple[float, ...]]:
    """Ten actions a chunk, Rotation on a ramp that starts 2 degrees to one side of the
    measured pose, the next chunk's to the other: every seam disagrees on purpose."""
    side = 2.0 if int(observation.timestep) % 2 == 0 else -2.0
    start = observation.state[0] + side
    return [(start + 0.5 * k, *observation.state[1:]) for k in range(10)]


def seam_figures(targets: list[TargetsSent]) -> tuple[float, float, float]:
    """Of Rotation's targets after the first half second (the arm's move from rest onto the
    first chunk, which has no plan before it to blend from): the largest step (degrees) between
    consecutive ones, the largest speed and acceleration (deg/s, deg/s^2) by divided
    differences of targets at least 5 ms apart (two a hair apart would only measure
    rounding)."""
    kept: list[tuple[float, float]] = []
    for event in targets:
        if event.time < targets[0].time + 0.5:
            continue
        if kept and event.time - kept[-1][0] < 0.005:
            kept.pop()
        kept.append((event.time, event.joints["Rotation"]))
    step = max(abs(b[1] - a[1]) for a, b in itertools.pairwise(kept))
    speeds = [
        ((a[0] + b[0]) / 2, (b[1] - a[1]) / (b[0] - a[0])) for a, b in itertools.pairwise(kept)
    ]
    speed = max(abs(v) for _, v in speeds)
    accel = max(abs(v2 - v1) / (t2 - t1) for (t1, v1), (t2, v2) in itertools.pairwise(speeds))
    return step, speed, accel


async def run_seams(
    manager: RobotManager, **settings: float
) -> tuple[tuple[float, float, float], int]:
    robot, _ = await arm(manager)
    worker = FakeWorker(disagreeing)
    with robot.subscribe(kinds=[TargetsSent, CommandHandled]) as events:
        master = await attach(robot, worker, max_relative_target=None, **settings)
        await trio.sleep(3.0)
        got = events.drain()
    await robot.detach_master(master.master_id)
    targets = [e for e in got if isinstance(e, TargetsSent)]
    commands = [e for e in got if isinstance(e, CommandHandled)]
    assert master.counters.inferences >= 10  # many seams
    return seam_figures(targets), len(commands)


async def test_disagreeing_chunks_are_blended_and_interpolated_within_the_limits(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    limit = MODEL.joint("Rotation")
    assert limit is not None
    stepped = await run_seams(manager, blend_steps=0)
    await manager.delete("arm")
    blended = await run_seams(manager, blend_steps=3)
    await manager.delete("arm")
    interpolated = await run_seams(manager, blend_steps=3, interpolation_multiplier=3)
    # Every seam inside the trajectory's limits either way (0.1 % for rounding)...
    for (_, speed, accel), _ in (stepped, blended, interpolated):
        assert speed <= limit.max_velocity * 1.001
        assert accel <= limit.max_acceleration * 1.001
    # ...and the blend asks less of the arm at the seams than a chunk stepped to (measured:
    # largest step 1.66 -> 0.98 degrees, speed 49.7 -> 29.3 deg/s, acceleration 1,041 -> 313
    # deg/s^2)...
    assert blended[0][0] < 0.7 * stepped[0][0]
    assert blended[0][2] < 0.5 * stepped[0][2]
    # ...and the multiplier splits each step in three (0.33 degrees; a 90 Hz stream of a 30 fps
    # policy: three commands a step).
    assert interpolated[0][0] < 0.5 * blended[0][0]
    assert interpolated[1] >= 2.5 * blended[1]
