"""The robot actor and its manager, on trio's MockClock: ownership, e-stop, drivers, observers."""

from __future__ import annotations

import dataclasses
import math

import pytest
import trio
import trio.testing
from trio.testing import MockClock

from arena.drivers.mock_slave import MockSlave, MockSlaveConfig
from arena.drivers.sequence_master import SequenceMaster
from arena.drivers.sequences import get_sequence, parse_sequence
from arena.protocol.errors import ArenaError, ErrorCode, Severity
from arena.robot.events import (
    CommandHandled,
    FaultReported,
    JointStatesReceived,
    NoticeKind,
    PeerChanged,
    SlaveNotice,
    SlaveTarget,
    StateChanged,
    TargetsSent,
)
from arena.robot.handle import Robot
from arena.robot.inbox import DriverEndedMsg, Msg
from arena.robot.links import DETACHED_LINK, MasterLink, RobotView
from arena.robot.mailbox import EventQueue, LatestMailbox
from arena.robot.manager import RobotManager, estop_together
from arena.robot.model import LossPolicy, load_robot_model
from arena.robot.motion import Command, CommandResult
from arena.robot.safety import Mode
from tests.conftest import RecordingSlave

MODEL = load_robot_model("so-arm100")


async def new_robot(manager: RobotManager, robot_id: str = "arm", **policy: object) -> Robot:
    safety = dataclasses.replace(MODEL.safety, **policy) if policy else None  # type: ignore[arg-type]
    return await manager.create_robot("so-arm100", robot_id=robot_id, policy=safety)


def short_sequence(value: float = 20.0) -> SequenceMaster:
    sequence = parse_sequence(
        {
            "id": "short",
            "name": "Short",
            "total_duration": 3000,
            "commands": [
                {
                    "timestamp": 0,
                    "duration": 1000,
                    "joints": [{"name": "Rotation", "value": value}],
                },
                {"timestamp": 1500, "duration": 1000, "joints": [{"name": "Rotation", "value": 0}]},
            ],
        }
    )
    return SequenceMaster([sequence])


# --- commands and slaves ----------------------------------------------------------------------


async def test_a_command_reaches_the_slave_at_once(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot = await new_robot(manager)
    link = await robot.connect_slave("s1")
    before = trio.current_time()
    result = await robot.command(Command.of({"Rotation": 5.0, "gripper": 3.0}))
    assert result.accepted
    message = await link.receive()
    assert isinstance(message, SlaveTarget)
    # The trajectory's first step, both joints on their way together (a tick ahead).
    assert 0.0 < message.joints["Rotation"] < 5.0 and 0.0 < message.joints["Jaw"] < 3.0
    assert message.joints["Rotation"] / 5.0 == pytest.approx(message.joints["Jaw"] / 3.0)
    assert message.time == before == trio.current_time()  # no tick, no waiting


async def test_a_command_decided_in_the_callers_task_still_gets_its_motion_ticks(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    # `command_now` decides outside the actor; a long move then needs the actor to wake for
    # its motion ticks, which it would not if its wait were not brought forward.
    robot = await new_robot(manager)
    link = await robot.connect_master("alice")
    await trio.testing.wait_all_tasks_blocked()  # the actor is idle
    result = link.command_now(Command.of({"Rotation": 90.0}))
    assert result is not None and result.accepted
    assert robot.snapshot().joint("Rotation").goal == 90.0
    started = trio.current_time()
    while robot.snapshot().joint("Rotation").virtual_value < 90.0:
        await trio.sleep(0.05)
        assert trio.current_time() - started < 10, "the motion stopped advancing"
    assert trio.current_time() - started > 0.1  # it was limited, so ticks carried it


async def test_a_stream_on_time_wakes_the_actor_for_nothing_but_its_end(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    # Each tick of a stream on time sent nothing (its next command moves it on): the actor's
    # timer is put off to when the stream would be overdue, in the idle turn too (the actor
    # woke twice a command for nothing before).
    robot = await new_robot(manager)
    link = await robot.connect_master("alice")
    actor = robot._actor
    on_timers, woke, ended, after = actor._on_timers, [], trio.Event(), [math.inf]

    def counted(now: float) -> None:
        woke.append(now)
        on_timers(now)
        if now >= after[0] and robot.core.next_tick(now) is None:
            ended.set()  # (the stream's end taken, nothing left to tick)

    actor._on_timers = counted  # type: ignore[method-assign]
    for k in range(1, 51):  # 1 s at 50 Hz, 12 deg/s
        await trio.sleep(0.02)
        await trio.testing.wait_all_tasks_blocked()  # the robot idle: decided at once
        result = link.command_now(Command.of({"Rotation": 0.24 * k}))
        assert result is not None and result.accepted
    last = after[0] = trio.current_time()
    assert all(t < last - 0.9 for t in woke)  # only as it set off from rest
    await ended.wait()
    assert min(t for t in woke if t >= last) == pytest.approx(last + 0.03)  # overdue
    assert robot.snapshot().joint("Rotation").virtual_value == pytest.approx(12.0)
    assert robot.core.next_tick(trio.current_time()) is None  # at rest on its last goal


async def test_a_run_of_commands_is_decided_at_once_each_on_its_own(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    # A burst's commands in hand together: one call decides them all, each with its own
    # answer and event, in order; the slave's targets say a newer one follows, but the last's.
    robot = await new_robot(manager)
    alice = await robot.connect_master("alice")
    slave = await robot.connect_slave("s1")
    await trio.testing.wait_all_tasks_blocked()
    run = [
        Command.of({"Rotation": 1.0}),
        Command.of({"Nose": 2.0}),  # no such joint: refused, alone
        Command.of({"Rotation": 500.0}),  # clamped to the limit
        Command.of({"Rotation": 3.0}),
    ]
    with robot.subscribe(kinds=[CommandHandled]) as handled:
        results = alice.command_run_now(run)
        assert results is not None
        assert [r.accepted for r in results] == [True, False, True, True]
        assert results[1].code is ErrorCode.UNKNOWN_JOINT and results[2].clamped
        events = [handled.get_nowait() for _ in range(len(handled))]
    assert [e.command for e in events] == run  # type: ignore[attr-defined]
    assert [e.result for e in events] == results  # type: ignore[attr-defined]
    assert robot.snapshot().joint("Rotation").goal == 3.0
    newest = await slave.receive()  # the run's first step (the rest, at the same instant,
    assert isinstance(newest, SlaveTarget)  # move nothing more: a trajectory takes time)
    while robot.snapshot().joint("Rotation").virtual_value != 3.0:  # the arm arrives
        tick = await slave.receive()  # the ticks' targets, each at its tick (mock clock)
        assert isinstance(tick, SlaveTarget) and not tick.more_follow
    # With more of the burst still to come, even the last one's target says so.
    autojump_clock.jump(robot.core.tick_interval)  # (at the arrival's instant: no step)
    await trio.testing.wait_all_tasks_blocked()
    results = alice.command_run_now([Command.of({"Rotation": 2.0})], burst_goes_on=True)
    assert results is not None and results[0].accepted
    newest = await slave.receive()
    assert isinstance(newest, SlaveTarget) and newest.more_follow
    # A detached link refuses each (a busy actor: see the due timer below).
    await alice.detach()
    assert alice.command_run_now(run) == [DETACHED_LINK] * 4


async def test_a_due_timer_goes_before_a_command_decided_at_once(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    # The master's heartbeat deadline has passed but the actor has not run yet: `command_now`
    # must leave the command alone (deciding it would count as a heartbeat and keep a master
    # that has already timed out), and the actor drops the master first.
    robot = await new_robot(manager)
    alice = await robot.connect_master("alice", heartbeat_timeout=1.0)
    await trio.testing.wait_all_tasks_blocked()
    autojump_clock.jump(1.5)  # no task runs between this and the next line
    assert alice.command_now(Command.of({"Rotation": 5.0})) is None
    await trio.testing.wait_all_tasks_blocked()
    assert robot.snapshot().mode is Mode.ESTOPPED and robot.snapshot().owner is None
    assert not (await alice.command(Command.of({"Rotation": 5.0}))).accepted


async def test_the_mock_slave_follows_after_its_delays(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot = await new_robot(manager)
    slave = MockSlave(MockSlaveConfig(simulate_latency=50, response_delay=20))
    await robot.attach_slave(slave)
    start = trio.current_time()
    await robot.command(Command.of({"Elbow": -5.0}))
    await trio.sleep_until(start + 0.069)
    assert robot.snapshot().joint("Elbow").real_value == 0.0  # the arm starts at rest
    await trio.sleep_until(start + 0.071)
    assert robot.snapshot().joint("Elbow").real_value < 0.0  # the first target, on its way
    await robot.command(Command.of({"Rotation": 45.0, "Pitch": -30.0}))
    await trio.sleep(1.0)
    snapshot = robot.snapshot()
    for name, value in (("Rotation", 45.0), ("Pitch", -30.0), ("Elbow", -5.0)):
        joint = snapshot.joint(name)
        assert joint.virtual_value == joint.real_value == value


async def test_a_slow_slave_gets_only_the_newest_target(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot = await new_robot(manager, command_rate=1e6, command_burst=10**6)
    link = await robot.connect_slave("slow")
    for i in range(50):
        await robot.command(Command.of({"Rotation": (i + 1) * 0.1}))
        await trio.sleep(0.01)
    message = await link.receive()
    assert isinstance(message, SlaveTarget)
    assert link.mailbox.coalesced >= 49  # every target but the newest (ticks' included)
    with trio.fail_after(5):
        # The rest of the way (a stream's end is braked to rest on its last goal; the ticks
        # that find the arm on it, its velocity not yet zero, send nothing new).
        while message.joints["Rotation"] != 5.0 or robot.core.motion.moving:
            with trio.move_on_after(0.1):
                message = await link.receive()
                assert isinstance(message, SlaveTarget)
    with trio.move_on_after(1):
        await link.receive()
        pytest.fail("a backlog reached the slave")


async def test_joint_states_update_real_values(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot = await new_robot(manager)
    link = await robot.connect_slave("s1")
    with robot.subscribe() as events:
        await link.report_joint_states({"shoulder_pan": 12.5, "Bogus": 1.0, "Elbow": float("nan")})
        await trio.sleep(0.01)
        received = [e for e in [events.get_nowait()] if isinstance(e, JointStatesReceived)]
    assert received[0].joints == {"Rotation": 12.5}
    snapshot = robot.snapshot()
    assert snapshot.joint("Rotation").real_value == 12.5
    assert snapshot.joint("Elbow").real_value is None


async def test_an_observer_of_some_kinds_gets_only_those_and_the_others_get_all(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot = await new_robot(manager)
    link = await robot.connect_slave("s1")
    with robot.subscribe() as everything, robot.subscribe(kinds=[StateChanged]) as states:
        assert (await robot.command(Command.of({"Rotation": 1.0}))).accepted
        await link.report_joint_states({"Rotation": 1.0})
        await robot.estop("test")
        await trio.sleep(0.01)
        every = {type(everything.get_nowait()) for _ in range(len(everything))}
        only = [states.get_nowait() for _ in range(len(states))]
    assert {CommandHandled, TargetsSent, JointStatesReceived, StateChanged} <= every
    assert only and all(isinstance(event, StateChanged) for event in only)
    assert only[-1].mode is Mode.ESTOPPED
    # The routing follows subscribers that come and go.
    with robot.subscribe(kinds=[CommandHandled]) as commands:
        await robot.reset()
        assert (await robot.command(Command.of({"Rotation": 2.0}))).accepted
        await trio.sleep(0.01)
        assert len(commands) == 1 and isinstance(commands.get_nowait(), CommandHandled)


async def test_manual_commands_are_rate_limited(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot = await new_robot(manager)
    answers = [await robot.command(Command.of({"Rotation": i * 0.1})) for i in range(12)]
    assert [a.accepted for a in answers[:10]] == [True] * 10
    assert answers[10].code is ErrorCode.RATE_LIMITED
    await trio.sleep(0.05)
    assert (await robot.command(Command.of({"Rotation": 0.0}))).accepted


async def test_bad_commands_change_nothing(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot = await new_robot(manager)
    link = await robot.connect_slave("s1")
    before = robot.snapshot()
    for command in (Command.of({"Nope": 1.0}), Command.of({"Rotation": float("nan")}), Command(())):
        result = await robot.command(command)
        assert not result.accepted and result.code is not None and result.message
    assert robot.snapshot() == before
    with trio.move_on_after(1):
        await link.receive()
        pytest.fail("a refused command reached the slave")


async def test_clamped_values_are_reported(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot = await new_robot(manager)
    result = await robot.command(Command.of({"Jaw": 500.0}))
    assert result.accepted
    assert [(c.joint, c.requested, c.applied) for c in result.clamped] == [
        ("Jaw", 500.0, MODEL.joints[5].upper)
    ]
    await trio.sleep(1)
    assert robot.snapshot().joint("Jaw").virtual_value == MODEL.joints[5].upper


# --- masters ----------------------------------------------------------------------------------


async def test_one_master_at_a_time_and_takeover(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot = await new_robot(manager)
    alice = await robot.connect_master("alice")
    with pytest.raises(ArenaError) as info:
        await robot.connect_master("bob")
    assert info.value.code is ErrorCode.MASTER_ACTIVE
    manual = await robot.command(Command.of({"Rotation": 1.0}))
    assert manual.code is ErrorCode.MASTER_ACTIVE
    bob = await robot.connect_master("bob", takeover=True)
    assert robot.snapshot().owner == "bob"
    assert alice.detached.is_set()
    notices = [notice async for notice in alice.notices]
    assert notices[-1].kind == "detached" and notices[-1].code is ErrorCode.TAKEN_OVER
    refused = await alice.command(Command.of({"Rotation": 1.0}))
    assert refused.code is ErrorCode.NOT_OWNER
    assert (await bob.command(Command.of({"Rotation": 1.0}))).accepted


async def test_a_sequence_takes_over_and_plays_in_virtual_time(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot = await new_robot(manager)
    recorder = RecordingSlave()
    await robot.attach_slave(recorder)
    alice = await robot.connect_master("alice")
    start = trio.current_time()
    await robot.attach_master(SequenceMaster([get_sequence("tiny-flex")]))
    assert alice.detached.is_set()
    while robot.snapshot().master is not None:
        await trio.sleep(0.1)
    assert trio.current_time() - start == pytest.approx(8.0, abs=0.11)
    assert robot.snapshot().mode is Mode.IDLE
    final = recorder.targets[-1][1]
    assert all(value == 0.0 for value in final.values())
    assert all(abs(v) <= 25.0 for _, targets in recorder.targets for v in targets.values())


async def _trace_of_a_sequence() -> list[tuple[float, dict[str, float]]]:
    from arena.robot.manager import open_manager

    async with open_manager() as manager:
        robot = await new_robot(manager)
        recorder = RecordingSlave()
        await robot.attach_slave(recorder)
        start = trio.current_time()
        await robot.attach_master(SequenceMaster([get_sequence("gentle-wave")]))
        await trio.sleep(7)
    return [(round(t - start, 9), targets) for t, targets in recorder.targets]


def test_a_sequence_plays_the_same_way_every_run() -> None:
    runs = [
        trio.run(_trace_of_a_sequence, clock=trio.testing.MockClock(autojump_threshold=0))
        for _ in range(2)
    ]
    assert len(runs[0]) > 100
    assert runs[0] == runs[1]


async def test_estop_ends_a_sequence_for_good(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot = await new_robot(manager)
    recorder = RecordingSlave()
    await robot.attach_slave(recorder)
    master = SequenceMaster([get_sequence("small-scan")], loop=True)
    await robot.attach_master(master)
    await trio.sleep(1.0)
    await robot.estop("operator pressed the button")
    stopped_at = trio.current_time()
    snapshot = robot.snapshot()
    assert snapshot.mode is Mode.ESTOPPED and snapshot.owner is None
    assert snapshot.estop_reason == "operator pressed the button"
    frozen = {j.name: j.virtual_value for j in snapshot.joints}
    await trio.sleep(5.0)
    assert recorder.notices[-1][1].kind is NoticeKind.ESTOP
    assert all(t <= stopped_at for t, _ in recorder.targets), "a target after the e-stop"
    refused = await robot.command(Command.of({"Rotation": 0.0}))
    assert refused.code is ErrorCode.ESTOPPED
    with pytest.raises(ArenaError) as info:
        await robot.attach_master(short_sequence())
    assert info.value.code is ErrorCode.ESTOPPED
    await robot.reset()
    assert robot.snapshot().mode is Mode.IDLE
    await trio.sleep(20.0)
    assert all(t <= stopped_at for t, _ in recorder.targets), "the sequence came back"
    assert {j.name: j.virtual_value for j in robot.snapshot().joints} == frozen
    assert recorder.notices[-1][1].kind is NoticeKind.RESET
    assert (await robot.command(Command.of({"Rotation": 1.0}))).accepted


async def test_a_live_master_survives_estop_and_commands_after_reset(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot = await new_robot(manager)
    alice = await robot.connect_master("alice")
    await robot.estop()
    assert (await alice.command(Command.of({"Rotation": 1.0}))).code is ErrorCode.ESTOPPED
    outcome = await robot.reset()
    assert robot.snapshot().mode is Mode.MASTERED and outcome is not None
    assert (await alice.command(Command.of({"Rotation": 1.0}))).accepted
    states = alice.notices.drain()
    assert [n.mode for n in states if n.kind == "state"] == [Mode.ESTOPPED, Mode.MASTERED]


async def test_losing_the_master_estops(autojump_clock: MockClock, manager: RobotManager) -> None:
    robot = await new_robot(manager)
    alice = await robot.connect_master("alice")
    await alice.lost("socket closed")
    snapshot = robot.snapshot()
    assert snapshot.mode is Mode.ESTOPPED and snapshot.owner is None
    assert "alice" in (snapshot.estop_reason or "")


async def test_losing_the_master_holds_under_the_hold_policy(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot = await new_robot(manager, loss_policy=LossPolicy.HOLD)
    link = await robot.connect_slave("s1")
    alice = await robot.connect_master("alice")
    await alice.command(Command.of({"Rotation": 90.0}))
    await trio.sleep(0.1)
    await alice.lost("socket closed")
    snapshot = robot.snapshot()
    assert snapshot.mode is Mode.IDLE and snapshot.owner is None
    held = snapshot.joint("Rotation").virtual_value
    assert 0 < held < 90.0
    await trio.sleep(1.0)
    assert robot.snapshot().joint("Rotation").virtual_value == held
    messages = []
    with trio.move_on_after(0.1):
        while True:
            messages.append(await link.receive())
    assert any(isinstance(m, SlaveNotice) and m.kind is NoticeKind.HOLD for m in messages)


async def test_a_silent_master_is_dropped_after_its_heartbeat_timeout(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot = await new_robot(manager)
    alice = await robot.connect_master("alice", heartbeat_timeout=1.0)
    for _ in range(6):
        await trio.sleep(0.5)
        alice.alive()
    assert robot.snapshot().owner == "alice"
    silent_from = trio.current_time()
    await alice.detached.wait()
    assert trio.current_time() - silent_from == pytest.approx(1.0, abs=1e-6)
    assert robot.snapshot().mode is Mode.ESTOPPED
    notices = [n async for n in alice.notices]
    assert notices[-1].kind == "detached" and notices[-1].code is ErrorCode.MASTER_LOST


async def test_a_silent_slave_is_dropped_after_its_heartbeat_timeout(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot = await new_robot(manager)
    link = await robot.connect_slave("s1", heartbeat_timeout=2.0)
    await trio.sleep(1.5)
    await link.report_joint_states({"Rotation": 0.0})  # any message counts as a heartbeat
    await trio.sleep(1.5)
    assert robot.snapshot().slaves
    await trio.sleep(1.0)
    assert not robot.snapshot().slaves
    assert robot.snapshot().mode is Mode.ESTOPPED


async def test_a_slave_that_beats_stays_and_one_that_leaves_is_detached_not_lost(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot = await new_robot(manager)
    link = await robot.connect_slave("s1", heartbeat_timeout=1.0)
    with robot.subscribe(kinds=[PeerChanged]) as events:
        for _ in range(6):  # three seconds of heartbeats and nothing else
            await trio.sleep(0.5)
            link.alive()
        assert [s.peer_id for s in robot.snapshot().slaves] == ["s1"]
        await link.detach()
        seen = events.drain()
    assert not robot.snapshot().slaves
    assert robot.snapshot().mode is Mode.IDLE  # leaving is no loss: no e-stop
    assert [(e.role, e.peer_id, e.change, e.reason) for e in seen] == [
        ("slave", "s1", "detached", "slave left")
    ]


async def test_a_master_that_leaves_stops_the_arm_where_it_is_unless_it_lets_the_move_end(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    for finish in (False, True):
        robot = await new_robot(manager, f"arm-{finish}")
        master = await robot.connect_master("alice")
        with robot.subscribe(kinds=[PeerChanged]) as events:
            assert (await master.command(Command.of({"Rotation": 90.0}))).accepted
            await trio.sleep(0.1)  # on its way
            if finish:
                await master.detach(finish_motion=True)
            else:
                await master.detach()
            await trio.sleep(10.0)
            seen = events.drain()
        rotation = robot.snapshot().joint("Rotation")
        if finish:
            assert rotation.virtual_value == pytest.approx(90.0)
        else:
            assert 0.0 < rotation.virtual_value < 45.0  # held where it was at the detach
        assert robot.snapshot().owner is None and robot.snapshot().mode is Mode.IDLE
        assert [(e.role, e.peer_id, e.change, e.reason) for e in seen] == [
            ("master", "alice", "detached", "master left")
        ]


@dataclasses.dataclass
class PlannedSlave(RecordingSlave):
    """A slave driver that can leave its hardware as its settings say (as the usb-slave)."""

    planned: int = 0

    def planned_stop(self) -> None:
        self.planned += 1


async def test_a_planned_stop_reaches_every_slave_driver_however_it_was_attached(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot = await new_robot(manager)
    first, second, gone = PlannedSlave(), PlannedSlave(), PlannedSlave()
    await robot.attach_slave(first)
    await robot.attach_slave(second, "second")
    await robot.attach_slave(gone, "gone")
    await robot.attach_slave(RecordingSlave())  # a driver without the hook
    await robot.connect_slave("remote")  # a slave that runs elsewhere: nothing to tell
    await robot.detach_slave("gone")
    robot.plan_stop()
    assert (first.planned, second.planned, gone.planned) == (1, 1, 0)
    await manager.delete("arm")  # and the robot stops as it would have
    assert robot.stopped.is_set()


async def test_a_master_that_releases_the_robot_hands_it_back_as_released(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    for hold in (False, True):
        robot = await new_robot(manager, f"arm-{hold}")
        master = await robot.connect_master("alice")
        with robot.subscribe(kinds=[PeerChanged]) as events:
            assert (await master.command(Command.of({"Rotation": 90.0}))).accepted
            await trio.sleep(0.1)  # on its way
            await master.release(hold=hold)
            await trio.sleep(10.0)
            seen = events.drain()
        assert robot.snapshot().owner is None and robot.snapshot().mode is Mode.IDLE
        rotation = robot.snapshot().joint("Rotation").virtual_value
        reason = "released by the master"
        if hold:
            assert 0.0 < rotation < 45.0  # stopped where it was at the release
            reason += ", stopped where it was"
        else:
            assert rotation == pytest.approx(90.0)  # the accepted command completed
        assert [(e.role, e.peer_id, e.change, e.reason) for e in seen] == [
            ("master", "alice", "released", reason)
        ]
        await master.release()  # once let go, a link changes nothing
        assert robot.snapshot().joint("Rotation").virtual_value == rotation


async def test_a_command_decided_at_once_tells_the_slaves_whether_more_follow(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot = await new_robot(manager)
    slave = await robot.connect_slave("s1")
    master = await robot.connect_master("alice")
    follows = []
    # Moves so small that each is one step (a duration: steps, not a stream), a tick apart.
    for value, in_burst in ((0.001, None), (0.002, True), (0.003, False)):
        autojump_clock.jump(robot.core.tick_interval)
        await trio.testing.wait_all_tasks_blocked()  # the robot idle: decided at once
        command = Command.of({"Rotation": value}, duration=0.0)
        result = (
            master.command_now(command)
            if in_burst is None
            else master.command_now(command, in_burst=in_burst)
        )
        assert result is not None and result.accepted
        target = await slave.receive()
        assert isinstance(target, SlaveTarget)
        follows.append(target.more_follow)
    assert follows == [False, True, False]


async def test_a_slave_whose_hardware_drops_out_shows_it_and_says_why(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot = await new_robot(manager, loss_policy=LossPolicy.HOLD)
    link = await robot.connect_slave("s1")
    with robot.subscribe(kinds=[PeerChanged]) as events:
        await link.connection_lost("bus unplugged")
        await trio.testing.wait_all_tasks_blocked()
        assert robot.snapshot().slaves[0].connected is False
        assert robot.snapshot().slaves[0].last_error == "SLAVE_LOST: bus unplugged"
        await link.connection_restored()
        await trio.testing.wait_all_tasks_blocked()
        seen = events.drain()
    assert robot.snapshot().slaves[0].connected is True
    assert robot.snapshot().slaves[0].last_error is None  # the loss is over: no error shown
    assert [(e.peer_id, e.change, e.reason) for e in seen] == [
        ("s1", "disconnected", "bus unplugged"),
        ("s1", "reconnected", "reconnected"),
    ]


async def test_a_slave_reported_lost_is_let_go_and_the_loss_policy_applies(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot = await new_robot(manager)
    link = await robot.connect_slave("s1")
    with robot.subscribe(kinds=[PeerChanged]) as events:
        await link.lost()
        seen = events.drain()
    assert not robot.snapshot().slaves
    assert robot.snapshot().mode is Mode.ESTOPPED  # the default loss policy
    assert [(e.peer_id, e.change, e.reason) for e in seen] == [("s1", "lost", "connection lost")]


async def test_a_master_reported_lost_is_let_go_and_told_why(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot = await new_robot(manager)
    master = await robot.connect_master("alice")
    with robot.subscribe(kinds=[PeerChanged]) as events:
        await master.lost()
        seen = events.drain()
    assert robot.snapshot().owner is None
    assert robot.snapshot().mode is Mode.ESTOPPED  # the default loss policy
    assert [(e.peer_id, e.change, e.reason) for e in seen] == [("alice", "lost", "connection lost")]
    notices = [n async for n in master.notices]
    assert (notices[-1].kind, notices[-1].code) == ("detached", ErrorCode.MASTER_LOST)


class LeavingPort:
    """A robot port that only records who leaves through it: a link on its own."""

    def __init__(self, robot: RobotView) -> None:
        self.robot = robot
        self.left: list[tuple[str, str | None]] = []

    async def post(self, message: Msg) -> None:
        raise AssertionError("not expected")

    def alive(self, peer_id: str) -> None:
        raise AssertionError("not expected")

    async def leave(
        self,
        role: str,
        peer_id: str | None,
        *,
        lost: bool,
        reason: str,
        hold: bool = True,
        released: bool = False,
    ) -> None:
        self.left.append((role, peer_id))

    async def command(
        self, command: Command, master_id: str | None = None, *, in_burst: bool = False
    ) -> CommandResult:
        raise AssertionError("not expected")

    def command_run_now(
        self, commands: list[Command], master_id: str | None = None, *, burst_goes_on: bool = False
    ) -> list[CommandResult] | None:
        raise AssertionError("not expected")


async def test_a_master_link_leaves_in_its_own_name_only(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    # The robot lets go of whichever master it has when a leaving names none; a link whose
    # leaving is queued behind a takeover must not take the new master with it.
    port = LeavingPort(await new_robot(manager))
    link = MasterLink(port, "alice")
    await link.detach()
    await link.release()
    await link.lost()
    assert port.left == [("master", "alice")] * 3


# --- failing drivers --------------------------------------------------------------------------


class CrashingMaster:
    kind = "crashing-master"
    autonomous = True
    takes_over = False

    async def run(self, link: MasterLink) -> None:
        await link.command(Command.of({"Rotation": 1.0}))
        await trio.sleep(0.5)
        raise ValueError("bug in the master")


async def test_a_crashing_slave_is_detached_and_reported(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot = await new_robot(manager)
    other_robot = await new_robot(manager, "other")
    healthy, crashing = RecordingSlave(), RecordingSlave(fail_after=1)
    await robot.attach_slave(healthy, "healthy")
    await robot.attach_slave(crashing, "crashing")
    with robot.subscribe() as events:
        await robot.command(Command.of({"Rotation": 2.0}))
        await trio.sleep(0.1)
        seen = events.drain()
    faults = [e for e in seen if isinstance(e, FaultReported)]
    assert faults and faults[0].code == ErrorCode.DRIVER_FAILED
    assert "simulated driver crash" in faults[0].message
    lost = [e for e in seen if isinstance(e, PeerChanged) and e.change == "lost"]
    assert [e.peer_id for e in lost] == ["crashing"]
    snapshot = robot.snapshot()
    assert [s.peer_id for s in snapshot.slaves] == ["healthy"]
    assert snapshot.mode is Mode.ESTOPPED  # the default loss policy
    assert other_robot.snapshot().mode is Mode.IDLE
    assert (await other_robot.command(Command.of({"Rotation": 1.0}))).accepted
    await robot.reset()
    assert (await robot.command(Command.of({"Rotation": 3.0}))).accepted
    await trio.sleep(1.0)  # along the trajectory
    assert healthy.targets[-1][1]["Rotation"] == 3.0


async def test_a_crashing_master_applies_the_loss_policy(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot = await new_robot(manager)
    await robot.attach_master(CrashingMaster())
    await trio.sleep(1.0)
    snapshot = robot.snapshot()
    assert snapshot.master is None and snapshot.mode is Mode.ESTOPPED
    await robot.reset()
    assert (await robot.command(Command.of({"Rotation": 1.0}))).accepted


async def test_mock_slave_error_injection(autojump_clock: MockClock, manager: RobotManager) -> None:
    robot = await new_robot(manager, command_rate=1e6, command_burst=10**6)
    slave = MockSlave(MockSlaveConfig(simulate_errors=True, error_rate=0.5, seed=7))
    await robot.attach_slave(slave)
    with robot.subscribe(maxlen=10_000) as events:
        for i in range(200):
            if robot.snapshot().mode is Mode.ESTOPPED:
                await robot.reset()
            await robot.command(Command.of({"Rotation": (i % 10) * 0.5}))
            await trio.sleep(0.02)
        seen = events.drain()
    severities = {e.severity for e in seen if isinstance(e, FaultReported)}
    assert severities == set(Severity)
    assert slave.dropped_updates > 0
    estops = [e for e in seen if isinstance(e, StateChanged) and e.mode is Mode.ESTOPPED]
    criticals = [
        e for e in seen if isinstance(e, FaultReported) and e.severity is Severity.CRITICAL
    ]
    assert len(estops) == len(criticals) > 0


# --- observers --------------------------------------------------------------------------------


async def test_a_slow_observer_does_not_slow_the_robot(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot = await new_robot(manager, command_rate=1e6, command_burst=10**6)
    link = await robot.connect_slave("s1")
    with robot.subscribe(maxlen=5) as slow:
        start = trio.current_time()
        for i in range(100):
            assert (await robot.command(Command.of({"Rotation": i * 0.01}))).accepted
        assert trio.current_time() == start
        assert slow.dropped > 0 and len(slow) == 5
    rotation = 0.0
    with trio.fail_after(10):
        while rotation != pytest.approx(0.99):  # the first step, then the ticks' targets
            message = await link.receive()
            assert isinstance(message, SlaveTarget)
            rotation = message.joints["Rotation"]


async def test_a_queue_holding_wakes_wakes_its_reader_once_only_if_items_are_left() -> None:
    queue: EventQueue[int] = EventQueue()
    woken: list[int] = []

    async def reader() -> None:
        while True:
            woken.append(await queue.get())

    async with trio.open_nursery() as nursery:
        nursery.start_soon(reader)
        await trio.testing.wait_all_tasks_blocked()
        with queue.holding_wakes():
            queue.put(1)
            await trio.testing.wait_all_tasks_blocked()
            assert woken == [] and queue.drain() == [1]  # taken by the holder itself
        await trio.testing.wait_all_tasks_blocked()
        assert woken == []
        with queue.holding_wakes():
            queue.put(2)
            queue.put(3)
            assert queue.get_nowait() == 2
        await trio.testing.wait_all_tasks_blocked()
        assert woken == [3]  # what the holder left goes to the reader
        queue.put(4)
        await trio.testing.wait_all_tasks_blocked()
        assert woken == [3, 4]
        nursery.cancel_scope.cancel()


async def test_a_mailbox_hands_items_straight_to_an_idle_consumer_in_order() -> None:
    box: LatestMailbox[str, str] = LatestMailbox()
    handed: list[str] = []
    accept = True

    def deliver_now(item: str) -> bool:
        if accept:
            handed.append(item)
        return accept

    taken: list[str] = []

    async def reader() -> None:
        while True:
            taken.append(await box.get())
            await trio.sleep(1.0)  # busy with it: nothing is handed straight on meanwhile

    box.deliver_now = deliver_now
    box.put_target("before the reader waits")  # no reader waiting: queued
    async with trio.open_nursery() as nursery:
        nursery.start_soon(reader)
        await trio.testing.wait_all_tasks_blocked()
        assert taken == ["before the reader waits"] and handed == []
        await trio.sleep(1.5)  # the reader waits again
        box.put_target("t1")
        box.put_notice("estop", clears=True)
        await trio.testing.wait_all_tasks_blocked()
        assert handed == ["t1", "estop"] and taken == ["before the reader waits"]
        accept = False  # declined (a socket with no room): queued and the reader woken
        box.put_target("t2")
        await trio.testing.wait_all_tasks_blocked()
        assert taken[1:] == ["t2"]
        accept = True
        box.put_target("t3")  # the reader is busy with t2: t3 waits in the box
        box.put_target("t4")  # and t4 replaces it, as targets do
        await trio.sleep(1.5)
        assert taken[1:] == ["t2", "t4"] and handed == ["t1", "estop"] and box.coalesced == 1
        nursery.cancel_scope.cancel()


async def test_a_mailbox_hands_nothing_on_once_its_reader_stopped_waiting() -> None:
    box: LatestMailbox[str, str] = LatestMailbox()
    handed: list[str] = []
    box.deliver_now = lambda item: handed.append(item) is None  # (always accepts)
    async with trio.open_nursery() as nursery:
        nursery.start_soon(box.get)
        await trio.testing.wait_all_tasks_blocked()
        box.put_target("t1")  # the reader waits: straight through
        assert handed == ["t1"]
        nursery.cancel_scope.cancel()  # the reader gives up waiting (its connection closes)
    box.put_target("t2")  # no one waits now: kept for whoever reads next
    assert handed == ["t1"]
    assert await box.get() == "t2"


async def test_observers_see_state_changes_and_peers(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot = await new_robot(manager)
    with robot.subscribe() as events:
        await robot.attach_slave(MockSlave())
        await robot.estop("test")
        await robot.reset()
        seen = events.drain()
    assert [e.mode for e in seen if isinstance(e, StateChanged)] == [Mode.ESTOPPED, Mode.IDLE]
    assert [(e.role, e.change) for e in seen if isinstance(e, PeerChanged)] == [
        ("slave", "attached")
    ]


# --- the manager ------------------------------------------------------------------------------


async def test_manager_create_get_list_delete(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    first = await new_robot(manager, "first")
    second = await manager.create_robot("so-arm100", "Second arm")
    assert second.robot_id.startswith("robot-") and second.name == "Second arm"
    assert manager.get("first") is first
    assert [r.robot_id for r in manager.robots()] == ["first", second.robot_id]
    await manager.delete("first")
    assert [r.robot_id for r in manager.robots()] == [second.robot_id]
    with pytest.raises(ArenaError) as info:
        manager.get("first")
    assert info.value.code is ErrorCode.UNKNOWN_ROBOT
    assert info.value.message == "No robot with id 'first'."  # the sentence a client shows


@pytest.mark.parametrize(
    ("robot_type", "robot_id", "code"),
    [
        ("so-arm100", "taken", ErrorCode.ROBOT_EXISTS),
        ("so-arm100", "../etc", ErrorCode.INVALID_CONFIG),
        ("so-arm100", "", ErrorCode.INVALID_CONFIG),
        ("toaster", "t1", ErrorCode.UNKNOWN_ROBOT_TYPE),
    ],
)
async def test_manager_refusals(
    autojump_clock: MockClock,
    manager: RobotManager,
    robot_type: str,
    robot_id: str,
    code: ErrorCode,
) -> None:
    await new_robot(manager, "taken")
    with pytest.raises(ArenaError) as info:
        await manager.create_robot(robot_type, robot_id=robot_id)
    assert info.value.code is code


async def test_deleting_a_robot_under_load_stops_its_drivers(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot = await new_robot(manager, command_rate=1e6, command_burst=10**6)
    bystander = await new_robot(manager, "bystander")
    mock = MockSlave(MockSlaveConfig(simulate_latency=5))
    await robot.attach_slave(mock)
    external = await robot.connect_slave("external")
    await robot.attach_master(SequenceMaster([get_sequence("gentle-wave")], loop=True))
    flood_results: list[ErrorCode | None] = []

    async def flood() -> None:
        for i in range(10_000):
            try:
                result = await robot.command(Command.of({"Rotation": i % 5}))
            except ArenaError as exc:
                flood_results.append(exc.code)
                return
            flood_results.append(result.code)
            await trio.sleep(0.001)

    async with trio.open_nursery() as nursery:
        nursery.start_soon(flood)
        await trio.sleep(2.0)
        await manager.delete("arm")
    assert robot.stopped.is_set()
    assert flood_results[-1] is ErrorCode.ROBOT_STOPPED
    # The driver ended: at the shutdown notice, or cancelled where it was (between two
    # targets, the simulated latency), never left running.
    assert mock.received > 0 and not mock.running
    messages = []
    with pytest.raises(trio.EndOfChannel):
        while True:
            messages.append(await external.receive())
    assert isinstance(messages[-1], SlaveNotice) and messages[-1].kind is NoticeKind.SHUTDOWN
    with pytest.raises(ArenaError) as info:
        await robot.command(Command.of({"Rotation": 0.0}))
    assert info.value.code is ErrorCode.ROBOT_STOPPED
    assert [r.robot_id for r in manager.robots()] == ["bystander"]
    assert (await bystander.command(Command.of({"Rotation": 1.0}))).accepted


async def test_detach_slave(autojump_clock: MockClock, manager: RobotManager) -> None:
    robot = await new_robot(manager)
    link = await robot.connect_slave("s1")
    await robot.detach_slave("s1")
    message = await link.receive()
    assert isinstance(message, SlaveNotice) and message.kind is NoticeKind.SHUTDOWN
    assert robot.snapshot().mode is Mode.IDLE  # a voluntary detach is no loss
    with pytest.raises(ArenaError) as info:
        await robot.detach_slave("s1")
    assert info.value.code is ErrorCode.UNKNOWN_SLAVE


async def test_estop_all(autojump_clock: MockClock, manager: RobotManager) -> None:
    robots = [await new_robot(manager, f"r{i}") for i in range(3)]
    await manager.estop_all()
    assert all(r.snapshot().mode is Mode.ESTOPPED for r in robots)
    # What an operator reads on each robot: why it stopped.
    assert {r.snapshot().estop_reason for r in robots} == {"emergency stop (all robots)"}


async def test_a_deleted_robot_tells_its_master_and_slaves_why_they_were_let_go(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot = await new_robot(manager)
    closing = await new_robot(manager, "closing")
    masters = [await robot.connect_master("alice"), await closing.connect_master("bob")]
    for r in (robot, closing):
        await r.connect_slave("s1")
    with (
        robot.subscribe(kinds=[PeerChanged]) as events,
        closing.subscribe(kinds=[PeerChanged]) as closing_events,
    ):
        await manager.delete("arm")
        await manager.close()
        observed = [events.drain(), closing_events.drain()]
    for link, seen, reason in zip(
        masters, observed, ("robot deleted", "server shutting down"), strict=True
    ):
        notices = [n async for n in link.notices]
        assert (notices[-1].kind, notices[-1].code, notices[-1].message) == (
            "detached",
            ErrorCode.ROBOT_STOPPED,
            reason,
        )
        assert {(e.role, e.change, e.reason) for e in seen} == {
            ("master", "detached", reason),
            ("slave", "detached", reason),
        }
    assert manager.robots() == []


async def test_an_idle_robot_is_estopped_before_the_caller_yields(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot = await new_robot(manager)
    await trio.testing.wait_all_tasks_blocked()
    outcome = robot.estop_now("now")  # no await between this and the checks
    assert outcome is not None and robot.snapshot().mode is Mode.ESTOPPED
    assert robot.snapshot().estop_reason == "now"


async def test_an_estop_from_a_caller_being_cancelled_still_stops_an_idle_robot(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    # `estop` applies the stop before its first checkpoint, so even a caller whose scope is
    # already cancelled (a request whose client went away) stops the robot. Posted to the
    # actor instead, the cancellation would win before the message was sent.
    robot = await new_robot(manager)
    await trio.testing.wait_all_tasks_blocked()
    with trio.CancelScope() as scope:
        scope.cancel()
        await robot.estop("client gone")
    assert scope.cancelled_caught
    assert robot.snapshot().mode is Mode.ESTOPPED
    assert robot.snapshot().estop_reason == "client gone"


async def test_estop_all_stops_idle_robots_at_once_and_busy_ones_after_their_step(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    idle = [await new_robot(manager, f"idle{i}") for i in range(3)]
    busy = await new_robot(manager, "busy", loss_policy=LossPolicy.HOLD)
    await busy.connect_master("alice", heartbeat_timeout=1.0)
    slaves = {r.robot_id: await r.connect_slave("arm") for r in [*idle, busy]}
    await trio.testing.wait_all_tasks_blocked()
    autojump_clock.jump(1.5)  # the busy robot's heartbeat check is due, not yet run
    assert busy.estop_now("x") is None  # a due timer goes first
    await manager.estop_all("all stop")
    for robot in [*idle, busy]:
        assert robot.snapshot().mode is Mode.ESTOPPED
        assert robot.snapshot().estop_reason == "all stop"
    # Each slave heard of it; the busy robot's after the hold for its silent master.
    for robot, expected in [(r, [NoticeKind.ESTOP]) for r in idle] + [
        (busy, [NoticeKind.HOLD, NoticeKind.ESTOP])
    ]:
        notices = [await slaves[robot.robot_id].receive() for _ in expected]
        assert [n.kind for n in notices if isinstance(n, SlaveNotice)] == expected


async def test_an_estop_of_several_robots_passes_over_one_that_has_stopped(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    # A robot deleted meanwhile (a group's member, say) moves nothing: the e-stop goes on to
    # the others, idle or busy, and does not fail.
    gone = await new_robot(manager, "gone")
    await manager.delete("gone")
    idle = await new_robot(manager, "idle")
    busy = await new_robot(manager, "busy", loss_policy=LossPolicy.HOLD)
    await busy.connect_master("alice", heartbeat_timeout=1.0)
    await trio.testing.wait_all_tasks_blocked()
    autojump_clock.jump(1.5)  # the busy robot's heartbeat check is due, not yet run
    assert busy.estop_now("x") is None
    await estop_together([gone, idle, busy, gone], "all stop")
    for robot in (idle, busy):
        assert robot.snapshot().mode is Mode.ESTOPPED
        assert robot.snapshot().estop_reason == "all stop"


async def test_a_drivers_end_is_not_overtaken_by_a_command_decided_at_once(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    # A master driver returns; its end goes to the actor's inbox. A manual command decided
    # right then in the caller's task (command_now) would still see the master as the owner
    # and be refused: it must wait its turn behind the end (None: use `command`).
    robot = await manager.create_robot("so-arm100", robot_id="arm")
    decided_at_once: list[object] = []
    inbox = robot._send

    class Inbox:
        """The actor's inbox, deciding a manual command right after the driver's end."""

        def __getattr__(self, name: str) -> object:
            return getattr(inbox, name)

        async def send(self, message: object) -> None:
            inbox.send_nowait(message)  # queued, the actor not yet run
            if isinstance(message, DriverEndedMsg):
                decided_at_once.append(robot.command_now(Command.of({"Rotation": 1.0})))
            await trio.lowlevel.checkpoint()

    robot._send = Inbox()  # type: ignore[assignment]

    class Brief:
        kind = "brief"
        autonomous = False
        takes_over = False

        async def run(self, link: MasterLink) -> None:
            await trio.sleep(1.0)

    await robot.attach_master(Brief())  # type: ignore[arg-type]
    await trio.sleep(2.0)
    assert decided_at_once == [None]
    result = await robot.command(Command.of({"Rotation": 1.0}))
    assert result.accepted and robot.snapshot().owner is None
