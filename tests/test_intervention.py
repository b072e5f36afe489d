"""Pause, resume and intervention (specs/safety-state-machine.md): the pure table under random
event sequences, a real robot on the MockClock through every order of pause, resume,
intervene, release, e-stop and takeover, and a policy paused and resumed without a reload."""

from __future__ import annotations

import itertools
from pathlib import Path

import pytest
import trio
from hypothesis import given, settings
from hypothesis import strategies as st
from trio.testing import MockClock

from arena.drivers.sequence_master import SequenceMaster
from arena.drivers.sequences import get_sequence
from arena.policy.master import PolicyMaster, PolicySettings
from arena.policy.wire import Observe
from arena.protocol.errors import ArenaError, ErrorCode, Severity
from arena.robot import safety as sm
from arena.robot.events import CommandHandled, InterventionChanged, TargetsSent
from arena.robot.handle import CLOSE_PATIENCE, Robot
from arena.robot.links import MasterLink
from arena.robot.manager import RobotManager
from arena.robot.model import LossPolicy
from arena.robot.motion import Command, JointGoal
from tests.conftest import RecordingSlave
from tests.test_policy_master import FakeWorker, frames

# -- the pure table ------------------------------------------------------------------------------

PEERS = st.sampled_from(["alice", "bob", "seq"])
EVENTS = st.one_of(
    st.builds(sm.MasterAttach, PEERS, st.booleans(), st.booleans()),
    st.builds(sm.MasterDetach, PEERS),
    st.builds(sm.MasterLost, PEERS),
    st.builds(sm.MasterCommand, PEERS),
    st.just(sm.ManualCommand()),
    st.builds(sm.EStop, st.sampled_from(["a", "b"])),
    st.just(sm.Reset()),
    st.builds(sm.SlaveError, PEERS, st.sampled_from(list(Severity))),
    st.builds(sm.SlaveLost, PEERS),
    st.builds(sm.HeartbeatTimeout, PEERS),
    st.just(sm.MasterPause()),
    st.just(sm.MasterResume()),
    st.builds(sm.Intervene, PEERS, st.booleans()),
    st.builds(sm.InterventionEnd, st.booleans()),
)
DRIVEN = (sm.Mode.MASTERED, sm.Mode.PAUSED, sm.Mode.INTERVENED)


@settings(max_examples=600)
@given(st.sampled_from(list(LossPolicy)), st.lists(EVENTS, max_size=40))
def test_random_sequences_keep_pause_and_intervention_consistent(
    policy: LossPolicy, events: list[sm.Event]
) -> None:
    state = sm.SafetyState(loss_policy=policy)
    for event in events:
        before = state
        outcome = sm.transition(state, event)
        if isinstance(outcome, sm.Allowed):
            state = outcome.state
        effects = outcome.effects if isinstance(outcome, sm.Allowed) else ()
        # An owner exactly when a master drives (or a live one waits out an e-stop).
        assert (state.mode in DRIVEN) == (
            state.owner is not None and state.mode is not sm.Mode.ESTOPPED
        )
        # A master waits exactly while an intervention runs, and is never the one driving.
        assert (state.waiting is not None) == (state.mode is sm.Mode.INTERVENED)
        assert state.waiting is None or state.waiting != state.owner
        assert state.waiting is not None or not state.waiting_autonomous
        # Only the driving master's commands are applied: never a paused one's.
        if isinstance(event, sm.MasterCommand) and isinstance(outcome, sm.Allowed):
            assert before.mode in (sm.Mode.MASTERED, sm.Mode.INTERVENED)
            assert event.source == before.owner
        if isinstance(event, sm.MasterCommand) and before.mode is sm.Mode.PAUSED:
            assert isinstance(outcome, sm.Refused)
        # Pausing holds the robot; resuming is said to the very master that was paused.
        if any(isinstance(e, sm.PauseMaster) for e in effects):
            assert any(isinstance(e, sm.HoldPosition) for e in effects)
        for effect in effects:
            if isinstance(effect, sm.ResumeMaster):
                assert state.mode is sm.Mode.MASTERED and state.owner == effect.master_id
                assert effect.master_id in (before.owner, before.waiting)
        # An e-stop ends the intervention and the paused master both: nothing waits.
        if state.mode is sm.Mode.ESTOPPED and before.mode in (sm.Mode.PAUSED, sm.Mode.INTERVENED):
            assert state.owner is None and state.waiting is None
            gone = {e.master_id for e in effects if isinstance(e, sm.DetachMaster)}
            if isinstance(event, sm.MasterLost | sm.HeartbeatTimeout):  # it went by itself
                gone.add(event.master_id if isinstance(event, sm.MasterLost) else event.peer_id)
            assert {before.owner, before.waiting} - {None} <= gone
        # Nothing resumes by itself out of an e-stop.
        if before.mode is sm.Mode.ESTOPPED:
            assert not any(isinstance(e, sm.ResumeMaster) for e in effects)


def test_pause_resume_intervene_and_hand_back_in_the_table() -> None:
    mastered = sm.SafetyState(mode=sm.Mode.MASTERED, owner="policy", owner_autonomous=True)
    paused = sm.transition(mastered, sm.MasterPause())
    assert isinstance(paused, sm.Allowed) and paused.state.mode is sm.Mode.PAUSED
    assert paused.effects == (sm.HoldPosition(), sm.PauseMaster("policy"))
    refused = sm.transition(paused.state, sm.MasterCommand("policy"))
    assert isinstance(refused, sm.Refused) and refused.code is ErrorCode.MASTER_PAUSED
    intervened = sm.transition(mastered, sm.Intervene("leader", autonomous=True))
    assert isinstance(intervened, sm.Allowed)
    state = intervened.state
    assert (state.mode, state.owner, state.waiting) == (sm.Mode.INTERVENED, "leader", "policy")
    assert sm.PauseMaster("policy") in intervened.effects
    second = sm.transition(state, sm.Intervene("other"))
    assert isinstance(second, sm.Refused) and second.code is ErrorCode.INTERVENTION_ACTIVE
    for event in (sm.MasterPause(), sm.MasterResume()):
        blocked = sm.transition(state, event)
        assert isinstance(blocked, sm.Refused) and blocked.code is ErrorCode.INTERVENTION_ACTIVE
    back = sm.transition(state, sm.InterventionEnd())
    assert isinstance(back, sm.Allowed)
    assert (back.state.mode, back.state.owner) == (sm.Mode.MASTERED, "policy")
    assert back.state.owner_autonomous and sm.ResumeMaster("policy") in back.effects
    kept = sm.transition(state, sm.InterventionEnd(resume=False))
    assert isinstance(kept, sm.Allowed) and kept.state.mode is sm.Mode.PAUSED
    for event in (sm.MasterPause(), sm.Intervene("leader")):
        none = sm.transition(sm.SafetyState(), event)
        assert isinstance(none, sm.Refused) and none.code is ErrorCode.NO_MASTER
    nothing = sm.transition(mastered, sm.InterventionEnd())
    assert isinstance(nothing, sm.Refused) and nothing.code is ErrorCode.NO_INTERVENTION


# -- a real robot, every order -------------------------------------------------------------------

OPERATIONS = ("pause", "resume", "intervene", "release", "estop", "takeover")


class Scene:
    """A robot with a looping sequence as its master and a slave that records its targets."""

    def __init__(self, robot: Robot, slave: RecordingSlave, sequence: SequenceMaster) -> None:
        self.robot = robot
        self.slave = slave
        self.sequence = sequence
        self.intervener: MasterLink | None = None
        self.taker: MasterLink | None = None

    async def do(self, operation: str) -> None:
        robot = self.robot
        if operation == "pause":
            await robot.pause()
        elif operation == "resume":
            await robot.resume()
        elif operation == "intervene":
            try:
                self.intervener = await robot.connect_master("corrector", intervene=True)
            except ArenaError as refusal:
                assert refusal.code in (
                    ErrorCode.NO_MASTER,
                    ErrorCode.INTERVENTION_ACTIVE,
                    ErrorCode.ESTOPPED,
                    ErrorCode.MASTER_ACTIVE,
                )
        elif operation == "release":
            if self.intervener is not None and not self.intervener.detached.is_set():
                await self.intervener.release()
            else:
                await robot.end_intervention()
        elif operation == "estop":
            await robot.estop("test")
            await robot.reset()
        else:
            try:
                self.taker = await robot.connect_master("taker", takeover=True)
            except ArenaError as refusal:
                assert refusal.code is ErrorCode.MASTER_ACTIVE  # the taker holds it already

    def check(self) -> None:
        """What the snapshot, the links and the state say agree."""
        snapshot = self.robot.snapshot()
        state = self.robot.core.state
        mode = snapshot.mode
        assert (snapshot.master is not None) == (mode in DRIVEN), (mode, snapshot.master)
        assert (snapshot.paused_master is not None) == (mode is sm.Mode.INTERVENED)
        if snapshot.master is not None:
            assert snapshot.master.peer_id == state.owner
            assert snapshot.master.paused == (mode is sm.Mode.PAUSED)
        if snapshot.paused_master is not None:
            assert snapshot.paused_master.peer_id == state.waiting
            assert snapshot.paused_master.paused
        links = {"corrector": self.intervener, "taker": self.taker}
        for master_id, link in links.items():
            if link is not None and not link.detached.is_set():
                assert master_id in (state.owner, state.waiting)


async def scene(manager: RobotManager, robot_id: str) -> Scene:
    robot = await manager.create_robot("so-arm100", robot_id=robot_id)
    slave = RecordingSlave()
    await robot.attach_slave(slave)
    sequence = SequenceMaster([get_sequence("gentle-wave")], loop=True)
    await robot.attach_master(sequence)
    await trio.sleep(0.5)
    return Scene(robot, slave, sequence)


async def test_every_order_of_pause_resume_intervene_release_estop_and_takeover(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    orders = list(itertools.permutations(OPERATIONS))
    for number, order in enumerate(orders):
        current = await scene(manager, f"arm-{number}")
        for operation in order:
            await current.do(operation)
            await trio.sleep(0.2)
            current.check()
            mode = current.robot.snapshot().mode
            if mode in (sm.Mode.PAUSED, sm.Mode.INTERVENED):
                # The paused master sends nothing and the robot holds: no target for a second
                # (nobody drives the intervening master here).
                before = len(current.slave.targets)
                await trio.sleep(1.0)
                assert len(current.slave.targets) == before, (order, operation)
                assert current.sequence.playing is None or (
                    current.robot.snapshot().master is not None
                )
        await manager.delete(f"arm-{number}")


async def test_a_sequence_resumed_goes_on_where_it_stood(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    current = await scene(manager, "arm")
    robot = current.robot
    with robot.subscribe(kinds=[CommandHandled]) as events:
        await robot.pause()
        await trio.sleep(30)  # longer than the whole sequence: its clock stood still
        assert not events.drain()
        assert current.sequence.playing == "gentle-wave"
        await robot.resume()
        await trio.sleep(1.0)
        resumed = events.drain()
        assert resumed and all(e.result.accepted for e in resumed)


async def test_an_estop_ends_the_intervention_and_the_paused_master(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    current = await scene(manager, "arm")
    robot = current.robot
    with robot.subscribe(kinds=[InterventionChanged]) as events:
        link = await robot.connect_master("corrector", intervene=True)
        started = events.drain()
        assert [(e.change, e.master) for e in started] == [("started", "corrector")]
        accepted = await link.command(Command((JointGoal("Rotation", 5.0),)))
        assert accepted.accepted
        await robot.estop("test")
        snapshot = robot.snapshot()
        assert snapshot.master is None and snapshot.paused_master is None
        assert link.detached.is_set()
        await robot.reset()
        await trio.sleep(2)
        assert robot.snapshot().master is None  # nothing resumes by itself
        assert current.sequence.playing is None


# -- a policy paused and resumed -----------------------------------------------------------------


def slowly(observation: Observe) -> list[tuple[float, ...]]:
    """Ten actions that turn the base a degree a step from the observed state (Rotation only:
    the rest of the arm stays clear of the floor)."""
    first, *rest = observation.state
    return [(first + step, *rest) for step in range(1, 11)]


async def test_a_paused_policy_keeps_its_worker_and_starts_afresh_on_resume(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot = await manager.create_robot("so-arm100", robot_id="arm")
    await robot.attach_slave(RecordingSlave())
    worker = FakeWorker(slowly, latency=0.2)
    starts = 0

    async def start() -> FakeWorker:
        nonlocal starts
        starts += 1
        return worker

    master = PolicyMaster(
        PolicySettings(Path("unused"), task="wave", fps=30.0),
        robot.model,
        frames(("front",)),
        start,
    )
    await master.prepare()
    await robot.attach_master(master, master_id=master.master_id)
    with robot.subscribe(kinds=[CommandHandled]) as events:
        await trio.sleep(1.0)
        assert events.drain()
        # Pause while an inference is on its way: its chunk must never be used.
        while len(worker.observations) == 0 or master.queue is None or len(master.queue) > 5:
            await trio.sleep(1 / 30)
        asked = len(worker.observations)
        await robot.pause()
        # Counted where the pause is made: the figures say it before the control loop holds.
        assert master.figures()["pauses"] == 1
        paused_at = trio.current_time()
        await trio.sleep(5.0)
        assert not events.drain()  # paused: it sends nothing
        assert len(worker.observations) <= asked + 1  # no observation while paused
        assert robot.snapshot().master is not None and robot.snapshot().master.paused
        held, _ = robot.joint_values()  # where the robot holds: the twin measures it
        await robot.resume()
        resumed_at = trio.current_time()
        await trio.sleep(1.0)
        after = [e for e in events.drain() if e.result.accepted]
    assert after, "the policy commands again after the resume"
    # Its first step obeys the step limit (10 degrees) from the pose measured at the resume.
    for goal in after[0].command.joints:
        assert abs(goal.value - held[goal.name]) <= 10.0 + 1e-9
    # A fresh observation after the resume, and nothing computed before the pause was used.
    fresh = [t for t, _ in worker.observations if t >= resumed_at]
    assert fresh
    assert all(e.time >= fresh[0] + worker.latency for e in after)
    assert master.counters.dropped > 0 and master.counters.pauses == 1
    assert paused_at < resumed_at
    # The worker stayed loaded: started and loaded once, never closed.
    assert starts == 1 and master.counters.loads == 1 and not worker.closed


async def test_a_pause_is_counted_once_where_it_is_made(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    """The link counts a master's pauses (drivers and figures read it): a pause is one, an
    intervention that finds the master already paused is none more, a later one is one."""
    robot = await manager.create_robot("so-arm100", robot_id="arm")
    await robot.attach_slave(RecordingSlave())
    link = await robot.connect_master("program")
    session = await robot.connect_master("corrector", intervene=True)
    await session.release()
    assert link.pauses == 1  # the intervention paused it
    assert isinstance(await robot.pause(), sm.Allowed)
    assert link.pauses == 2 and link.paused
    assert not isinstance(await robot.pause(), sm.Allowed)  # paused already: not counted
    await trio.sleep(1.0)
    assert link.pauses == 2
    corrector = await robot.connect_master("corrector", intervene=True)
    assert link.pauses == 2  # still the same pause
    await robot.end_intervention(resume=False)
    assert link.pauses == 2 and link.paused and not corrector.paused
    assert isinstance(await robot.resume(), sm.Allowed)
    assert link.pauses == 2 and not link.paused
    notices = [n.kind for n in link.notices.drain()]
    assert notices.count("paused") == 2 and notices.count("resumed") == 2, notices


@pytest.mark.parametrize("resume", [True, False])
async def test_handing_back_resumes_the_paused_master_unless_asked_not_to(
    autojump_clock: MockClock, manager: RobotManager, resume: bool
) -> None:
    current = await scene(manager, "arm")
    robot = current.robot
    await robot.connect_master("corrector", intervene=True)
    assert robot.snapshot().paused_master is not None
    await robot.end_intervention(resume)
    snapshot = robot.snapshot()
    assert snapshot.paused_master is None
    assert snapshot.master is not None and snapshot.master.kind == "mock-sequence"
    assert snapshot.master.paused is not resume
    assert snapshot.mode is (sm.Mode.MASTERED if resume else sm.Mode.PAUSED)


# -- no jerk at the handover ---------------------------------------------------------------------


def fastest(targets: list[TargetsSent], joint: str, burst: float) -> float:
    """The highest speed (deg/s) of `joint` between consecutive targets; `burst`: seconds
    added to each interval (0: the trajectory has no burst allowance, specs/motion.md)."""
    speeds = []
    for before, after in itertools.pairwise(targets):
        step = abs(after.joints[joint] - before.joints[joint])
        if step:
            speeds.append(step / (after.time - before.time + burst))
    return max(speeds)


async def test_an_intervening_master_moves_the_arm_at_the_join_speed_until_they_agree(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    current = await scene(manager, "arm")
    robot = current.robot
    model = robot.model
    join, burst = model.safety.join_speed, 0.0
    full = model.joint("Rotation").max_velocity
    assert full > 2 * join  # else the test could not tell the two apart
    link = await robot.connect_master("corrector", intervene=True)
    start = robot.joint_values()[0]["Rotation"]
    far = start + 60.0 if start < 0 else start - 60.0
    with robot.subscribe(kinds=[TargetsSent]) as events:
        # The human's input is 60 degrees away from the arm: the arm travels there at the join
        # speed (a leader arm in a hand is wherever it is), never at full speed...
        assert (await link.command(Command((JointGoal("Rotation", far),)))).accepted
        await trio.sleep(60.0 / join + 1.0)
        eased = [e for e in events.drain() if isinstance(e, TargetsSent)]
        assert eased[-1].joints["Rotation"] == pytest.approx(far)
        assert fastest(eased, "Rotation", burst) <= join + 1e-6
        assert eased[-1].time - eased[0].time >= 60.0 / join - 0.1
        assert robot.core.easing is None  # they agree: its commands pass as they are
        # ...and once input and arm agree, the commands pass straight (at the joint's speed).
        assert (await link.command(Command((JointGoal("Rotation", start),)))).accepted
        await trio.sleep(60.0 / full + 1.0)
        straight = [e for e in events.drain() if isinstance(e, TargetsSent)]
        assert fastest(straight, "Rotation", burst) > 2 * join


class SlowToLetGo:
    """A master whose hardware takes `letting_go` seconds to let go (a leader arm's torque
    off and port closing): its `run` waits until stopped, then closes."""

    kind = "slow-leader"
    autonomous = True
    takes_over = False

    def __init__(self, letting_go: float) -> None:
        self.letting_go = letting_go
        self.closed = False

    async def run(self, link: MasterLink) -> None:
        try:
            await trio.sleep_forever()
        finally:
            with trio.CancelScope(shield=True):
                await trio.sleep(self.letting_go)
                self.closed = True


async def test_handing_back_and_detaching_answer_once_the_masters_hardware_let_go(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    current = await scene(manager, "arm")
    robot = current.robot
    leader = SlowToLetGo(2.0)
    await robot.attach_master(leader, intervene=True)
    await robot.end_intervention()  # a leader limp and its port free when the answer comes
    assert leader.closed
    master = robot.snapshot().master
    assert master is not None and master.kind == "mock-sequence"  # it drives again
    await robot.detach_master(master.peer_id, wait_closed=True)
    stuck = SlowToLetGo(60.0)  # a driver that does not let go holds the answer a bounded time
    await robot.attach_master(stuck)
    began = trio.current_time()
    await robot.detach_master(wait_closed=True)
    assert trio.current_time() - began == pytest.approx(CLOSE_PATIENCE)
    assert not stuck.closed
