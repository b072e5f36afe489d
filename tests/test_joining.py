"""No surprise motion when a slave joins: the real usb-slave on the simulated bus, on MockClock.

An arm that joins a robot with no master gives the robot its pose (nothing moves); one that
joins a robot that is elsewhere is brought there at the joining speed, never at full speed.
The bus runs in threads of its own, in real time: the tests wait for the robot's events (never
for a time to pass), and a real-time watchdog ends a test whose event never comes.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path

import pytest
import trio
from trio.testing import MockClock

from arena.feetech import registers as reg
from arena.feetech.sim import SimBus
from arena.robot.events import (
    JointStatesReceived,
    PeerChanged,
    RobotEvent,
    SlaveTarget,
    TargetsSent,
)
from arena.robot.links import SlaveLink
from arena.robot.mailbox import EventQueue
from arena.robot.manager import RobotManager
from arena.robot.model import load_robot_model
from arena.robot.motion import Command
from arena.robot.safety import Mode
from arena.servo.sim_pty import PtySimBus
from tests.conftest import RecordingSlave
from tests.hardware import running_sim, usb_slave

MODEL = load_robot_model("so-arm100")
STEPS_PER_DEGREE = 4096 / 360
REST = {"Pitch": 48.5, "Elbow": -48.0}  # where the arm of the defect rested
#: Seconds of trio time a test without hardware may wait for an event: on MockClock a wait
#: that nothing will end reaches it at once (a fail, not a hang).
VIRTUAL = 60.0


@pytest.fixture
def sim(tmp_path: Path) -> Iterator[PtySimBus]:
    yield from running_sim(tmp_path)


def steps(degrees: float) -> int:
    """Raw steps of an uncalibrated servo for `degrees` from neutral."""
    return round(degrees * STEPS_PER_DEGREE) + 2048


def degrees(raw: int) -> float:
    """What an uncalibrated servo at `raw` steps reports, in degrees."""
    return (raw - 2048) / STEPS_PER_DEGREE


def rest_the_arm(sim: PtySimBus, pose: Mapping[str, float]) -> dict[int, int]:
    """Put the simulated arm at `pose` by hand (torque off) and start logging every write.
    Returns every servo's present position."""
    with sim.paused() as bus:
        for joint in MODEL.joints:
            bus.servo(joint.servo_id).move_by_hand(steps(pose.get(joint.name, 0.0)))
        bus.write_log = []
        return {sid: servo.present for sid, servo in bus.servos.items()}


def goals_written(sim: PtySimBus) -> dict[int, list[int]]:
    """Every Goal_Position the simulated servos received, in order, by servo id."""
    with sim.paused() as bus:
        log = list(bus.write_log or ())
    goals: dict[int, list[int]] = {sid: [] for sid in range(1, 7)}
    for _, sid, address, data in log:
        if address == reg.GOAL_POSITION.address:
            goals[sid].append(reg.GOAL_POSITION.decode(data[: reg.GOAL_POSITION.size]))
    return goals


@contextlib.contextmanager
def watchdog(seconds: float = 30.0) -> Iterator[None]:
    """Fail the test if it has not left this block after `seconds` of real time: only a
    broken feature gets there (an event that never comes), never a slow machine."""
    token = trio.lowlevel.current_trio_token()
    with trio.CancelScope() as scope:
        timer = threading.Timer(seconds, lambda: token.run_sync_soon(scope.cancel))
        timer.start()
        try:
            yield
        finally:
            timer.cancel()
    if scope.cancelled_caught:
        raise AssertionError(f"no progress in {seconds} s of real time")


async def sim_reaches(sim: PtySimBus, condition: Callable[[SimBus], bool]) -> None:
    """Wait until the simulated bus satisfies `condition` (it runs in a thread of its own: a
    job that wrote to it has returned once its bytes left, maybe before the bus took them).
    Polled in a thread, so that no trio deadline is involved; 30 s of real time at most."""

    def poll() -> bool:
        deadline = time.monotonic() + 30.0
        while time.monotonic() < deadline:
            with sim.paused() as bus:
                if condition(bus):
                    return True
            time.sleep(0.001)
        return False

    assert await trio.to_thread.run_sync(poll), "the simulated bus never got there"


def torque_off(bus: SimBus) -> bool:
    return not any(servo.peek(reg.TORQUE_ENABLE) for servo in bus.servos.values())


async def next_event(
    events: EventQueue[RobotEvent], wanted: Callable[[RobotEvent], bool]
) -> RobotEvent:
    """The next event for which `wanted` holds (earlier ones are skipped)."""
    while True:
        event = await events.get()
        if wanted(event):
            return event


def peer_change(change: str) -> Callable[[RobotEvent], bool]:
    return lambda event: isinstance(event, PeerChanged) and event.change == change


async def test_an_arm_joining_a_robot_with_no_master_gives_it_its_pose_and_nothing_moves(
    autojump_clock: MockClock, manager: RobotManager, sim: PtySimBus
) -> None:
    resting = rest_the_arm(sim, REST)
    robot = await manager.create_robot("so-arm100", robot_id="arm")
    twin = RecordingSlave()
    await robot.attach_slave(twin)
    with robot.subscribe() as events, watchdog():
        await robot.attach_slave(usb_slave(sim, MODEL))
        # The robot decides on the arm's first report, as it publishes it.
        await next_event(events, lambda event: isinstance(event, JointStatesReceived))
        snapshot = robot.snapshot()
        for joint in snapshot.joints:
            measured = degrees(resting[joint.servo_id])
            assert joint.real_value == pytest.approx(measured), joint.name
            assert joint.virtual_value == pytest.approx(measured), joint.name
            assert joint.goal == pytest.approx(measured), joint.name
        assert snapshot.joint("Pitch").virtual_value == pytest.approx(48.5, abs=0.1)
        assert not snapshot.slaves[1].joining  # it follows the robot's targets already
        # One joint commanded: only that joint moves.
        result = await robot.command(Command.of({"Rotation": 20.0}))
        assert result.accepted, result
        await next_event(
            events,
            lambda event: (
                isinstance(event, JointStatesReceived)
                and abs(event.joints["Rotation"] - degrees(steps(20.0))) < 0.01
            ),
        )
    # The twin was brought to the arm's pose (a twin jumps; the arm does not move).
    assert twin.targets[0][1]["Elbow"] == pytest.approx(degrees(resting[3]))
    assert twin.targets[-1][1]["Rotation"] == 20.0
    written = goals_written(sim)
    for sid in range(2, 7):  # every goal any other servo received is where it rests
        assert set(written[sid]) == {resting[sid]}, sid
    rotation = written[1]
    assert rotation[0] == resting[1] and rotation[-1] == steps(20.0)
    assert rotation == sorted(rotation)  # on its way to 20 degrees, never elsewhere
    with sim.paused() as bus:
        assert {sid: bus.servo(sid).present for sid in range(2, 7)} == {
            sid: resting[sid] for sid in range(2, 7)
        }


async def test_an_arm_joining_a_mastered_robot_is_brought_to_its_pose_at_the_joining_speed(
    autojump_clock: MockClock, manager: RobotManager, sim: PtySimBus
) -> None:
    pose = {"Rotation": 10.0, "Pitch": -30.0, "Elbow": 40.0, "Wrist_Pitch": 5.0}
    robot = await manager.create_robot("so-arm100", robot_id="arm")
    master = await robot.connect_master("operator")
    assert (await master.command(Command.of(pose))).accepted
    await trio.sleep(5)  # (virtual) the robot is there
    assert robot.snapshot().joint("Elbow").virtual_value == 40.0
    resting = rest_the_arm(sim, REST)
    speed = 20.0  # deg/s, asked for in the attach body (the robot type's is 15)
    driver = usb_slave(sim, MODEL, joinSpeed=speed)
    await driver.prepare()  # as attaching over REST does: the bus is open
    assert driver.worker is not None
    handed: list[tuple[float, dict[int, int]]] = []  # (trio time, goals) given to the bus
    set_goals = driver.worker.set_goals

    def log_goals(goals: Mapping[int, int]) -> None:
        handed.append((trio.current_time(), dict(goals)))
        set_goals(goals)

    driver.worker.set_goals = log_goals  # type: ignore[method-assign]
    with robot.subscribe() as events, watchdog():
        await robot.attach_slave(driver)
        joining = await next_event(events, peer_change("joining"))
        assert robot.snapshot().slaves[0].joining
        assert robot.snapshot().joint("Elbow").virtual_value == 40.0  # the robot stays put
        # The master goes on commanding meanwhile: its targets are not this arm's yet.
        assert (await master.command(Command.of({"Rotation": 12.0}))).accepted
        pose["Rotation"] = 12.0
        joined = await next_event(events, peer_change("joined"))
        assert not robot.snapshot().slaves[0].joining
        await next_event(
            events,
            lambda event: (
                isinstance(event, JointStatesReceived)
                and abs(event.joints["Elbow"] - degrees(steps(40.0))) < 0.01
                and abs(event.joints["Pitch"] - degrees(steps(-30.0))) < 0.01
            ),
        )
    target = {j.servo_id: steps(pose.get(j.name, 0.0)) for j in MODEL.joints}
    # Every goal handed to the bus, from the measured pose on, within the joining speed.
    assert handed and handed[-1][1] == target  # it arrived
    budget = speed * STEPS_PER_DEGREE
    previous_time, previous = joining.time, resting
    for at, goals in handed:
        for sid, goal in goals.items():
            allowed = budget * (at - previous_time) + 1  # + 1: rounding to whole steps
            assert abs(goal - previous[sid]) <= allowed, (sid, at, goal, previous[sid])
        previous_time, previous = at, goals
    # Elbow's 88 degrees at 20 deg/s take 4.4 s (of trio time).
    assert joined.time - joining.time == pytest.approx(88.0 / speed, abs=0.02)
    # The bus wrote nothing else: the goals it held the arm with at connect, then these.
    written = goals_written(sim)
    for sid in range(1, 7):
        sequence = [resting[sid]] + [goals[sid] for _, goals in handed]
        assert is_subsequence(written[sid], sequence), sid


def is_subsequence(items: list[int], of: list[int]) -> bool:
    """Whether `items` appear in `of` in the same order (the bus writes the newest goals)."""
    rest = iter(of)
    return all(any(item == candidate for candidate in rest) for item in items)


async def test_a_twin_never_waits_and_a_measuring_slave_joining_while_estopped_waits(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    """Core rules without hardware: a twin (mock, physics) gets targets at once; a measuring
    slave's join waits out an e-stop and is decided at the reset."""
    robot = await manager.create_robot("so-arm100", robot_id="arm")
    master = await robot.connect_master("operator")
    assert (await master.command(Command.of({"Elbow": 30.0}))).accepted
    await trio.sleep(2)
    twin = RecordingSlave()
    await robot.attach_slave(twin)
    assert (await master.command(Command.of({"Rotation": 1.0}))).accepted
    await trio.sleep(0.1)
    assert twin.targets and twin.targets[-1][1]["Elbow"] == 30.0
    await robot.estop("test")
    arm = MeasuringSlave({"Elbow": -10.0})
    with robot.subscribe(kinds=[PeerChanged, TargetsSent]) as events, trio.fail_after(VIRTUAL):
        await robot.attach_slave(arm)
        await trio.sleep(5)
        assert arm.targets == []  # stopped: nothing moves, not even to join
        assert robot.snapshot().slaves[1].joining
        assert robot.snapshot().mode is Mode.ESTOPPED
        await robot.reset()
        await trio.sleep(5)
        assert arm.targets == []  # leaving the e-stop moves nothing
        attached = peer_change("attached")
        assert [event for event in events.drain() if not attached(event)] == []
        # The next accepted command starts its way (and moves the robot as it asks).
        assert (await master.command(Command.of({"Rotation": 2.0}))).accepted
        joining = await next_event(events, peer_change("joining"))
        joined = await next_event(events, peer_change("joined"))
        await trio.sleep(0.1)  # (virtual) the slave takes its last target
    assert joined.time - joining.time == pytest.approx(40.0 / MODEL.safety.join_speed, abs=0.02)
    assert arm.targets[-1][1]["Elbow"] == 30.0
    assert arm.targets[-1][1]["Rotation"] == 2.0


class MeasuringSlave(RecordingSlave):
    """A slave that measures: it reports where its arm rests before any target comes."""

    def __init__(self, resting: Mapping[str, float]) -> None:
        super().__init__(kind="measuring-slave", measures=True)
        self.resting = {name: resting.get(name, 0.0) for name in MODEL.joint_names}

    async def run(self, link: object) -> None:
        from arena.robot.links import SlaveLink

        assert isinstance(link, SlaveLink)
        await link.report_joint_states(self.resting)
        await super().run(link)


async def test_the_first_arm_sets_the_pose_and_the_next_one_joins_it(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot = await manager.create_robot("so-arm100", robot_id="arm")
    speed = MODEL.safety.join_speed
    jaw_limit = MODEL.joint("Jaw").upper  # 63.03 degrees
    first = MeasuringSlave({"Pitch": 48.5, "Elbow": -48.0, "Jaw": 70.0})  # Jaw: beyond 63
    with robot.subscribe(kinds=[PeerChanged]) as events, trio.fail_after(VIRTUAL):
        await robot.attach_slave(first)
        await next_event(events, peer_change("adopted"))
        # The robot takes the pose inside the limits; the jaw is brought in, slowly.
        snapshot = robot.snapshot()
        assert snapshot.joint("Pitch").virtual_value == 48.5
        assert snapshot.joint("Jaw").virtual_value == jaw_limit
        joining = await next_event(events, peer_change("joining"))
        joined = await next_event(events, peer_change("joined"))
        assert joined.time - joining.time == pytest.approx((70.0 - jaw_limit) / speed, abs=0.02)
        await trio.sleep(0.1)  # the slave takes its last target
        jaw = [targets["Jaw"] for _, targets in first.targets]
        assert jaw == sorted(jaw, reverse=True) and jaw[0] < 70.0 and jaw[-1] == jaw_limit
        assert {targets["Pitch"] for _, targets in first.targets} == {48.5}
        sent_to_first = len(first.targets)
        # A second arm elsewhere: the robot has a pose already (the first arm holds it).
        second = MeasuringSlave({"Pitch": 18.5, "Elbow": -48.0})
        await robot.attach_slave(second)
        joining = await next_event(events, peer_change("joining"))
        joined = await next_event(events, peer_change("joined"))
        await trio.sleep(0.1)
    assert joined.time - joining.time == pytest.approx(jaw_limit / speed, abs=0.02)  # the jaw
    assert second.targets[-1][1] == {j.name: j.virtual_value for j in robot.snapshot().joints}
    assert len(first.targets) == sent_to_first  # the first arm was not moved meanwhile
    assert robot.snapshot().joint("Pitch").virtual_value == 48.5


async def test_an_estop_stops_a_join_and_the_next_command_resumes_it_from_where_the_arm_is(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot = await manager.create_robot("so-arm100", robot_id="arm")
    speed = MODEL.safety.join_speed
    master = await robot.connect_master("operator")
    assert (await master.command(Command.of({"Elbow": 30.0}))).accepted
    await trio.sleep(1)
    arm = MeasuringSlave({"Elbow": -30.0})
    with robot.subscribe(kinds=[PeerChanged]) as events, trio.fail_after(VIRTUAL):
        await robot.attach_slave(arm)
        started = await next_event(events, peer_change("joining"))
        await trio.sleep(1.0)  # a quarter of its way (60 degrees at 15 deg/s take 4 s)
        await robot.estop("test")
        await trio.sleep(0.1)
        stopped_at = arm.targets[-1]
        assert stopped_at[1]["Elbow"] == pytest.approx(-30.0 + speed * 1.0, abs=speed * 0.02)
        await trio.sleep(5)
        await robot.reset()
        await trio.sleep(5)
        assert arm.targets[-1] == stopped_at  # nothing moved while stopped, nor at the reset
        assert robot.snapshot().slaves[0].joining
        assert (await master.command(Command.of({"Rotation": 1.0}))).accepted
        resumed = await next_event(events, peer_change("joining"))
        joined = await next_event(events, peer_change("joined"))
        await trio.sleep(0.1)
    after = [(time, targets) for time, targets in arm.targets if time > stopped_at[0]]
    first_time, first = after[0]
    assert abs(first["Elbow"] - stopped_at[1]["Elbow"]) <= speed * (first_time - resumed.time)
    left = 30.0 - stopped_at[1]["Elbow"]
    assert joined.time - resumed.time == pytest.approx(left / speed, abs=0.02)
    assert started.time < stopped_at[0] < resumed.time
    assert arm.targets[-1][1]["Elbow"] == 30.0 and arm.targets[-1][1]["Rotation"] == 1.0


async def test_an_arm_that_leaves_holds_nothing_and_the_next_one_sets_the_pose_again(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot = await manager.create_robot("so-arm100", robot_id="arm")
    first = MeasuringSlave({"Pitch": 20.0})
    with robot.subscribe(kinds=[PeerChanged]) as events, trio.fail_after(VIRTUAL):
        first_id = await robot.attach_slave(first)
        await next_event(events, peer_change("joined"))
        await robot.detach_slave(first_id)
        second = MeasuringSlave({"Pitch": -40.0})
        await robot.attach_slave(second)
        await next_event(events, peer_change("adopted"))
        await next_event(events, peer_change("joined"))
    assert robot.snapshot().joint("Pitch").virtual_value == -40.0


async def test_a_command_under_way_when_the_arm_reports_goes_on_for_its_joints_only(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot = await manager.create_robot("so-arm100", robot_id="arm")
    assert (await robot.command(Command.of({"Rotation": 40.0}, duration=2.0))).accepted
    await trio.sleep(0.5)  # on its way (virtually: no arm yet)
    arm = MeasuringSlave({"Pitch": 30.0, "Rotation": -10.0})
    with robot.subscribe(kinds=[PeerChanged]) as events, trio.fail_after(VIRTUAL):
        await robot.attach_slave(arm)
        await next_event(events, peer_change("joined"))
        snapshot = robot.snapshot()
        # Where the arm is, with Rotation's goal kept: the command asked for that joint.
        assert snapshot.joint("Pitch").virtual_value == snapshot.joint("Pitch").goal == 30.0
        assert snapshot.joint("Rotation").virtual_value == -10.0
        assert snapshot.joint("Rotation").goal == 40.0
        await trio.sleep(2)
    rotation = [targets["Rotation"] for _, targets in arm.targets]
    assert rotation == sorted(rotation) and rotation[-1] == 40.0
    assert {targets["Pitch"] for _, targets in arm.targets} == {30.0}  # never commanded


async def test_an_arm_calibrated_anew_joins_again_where_it_was_left(
    autojump_clock: MockClock, manager: RobotManager, sim: PtySimBus
) -> None:
    rest_the_arm(sim, {})
    robot = await manager.create_robot("so-arm100", robot_id="arm")
    driver = usb_slave(sim, MODEL)
    with robot.subscribe(kinds=[PeerChanged, JointStatesReceived]) as events, watchdog():
        await robot.attach_slave(driver)
        await next_event(events, peer_change("joined"))
        await driver.calibration_start({})  # torque off: posed like the twin (0 degrees)
        await sim_reaches(sim, torque_off)
        posed = rest_the_arm(sim, dict.fromkeys(MODEL.joint_names, 20.0))
        await driver.calibration_capture()  # raw steps(20) now read 0 degrees
        # The range capture: the person moves Rotation through 35 degrees and back, and the
        # elbow to 44 degrees, where it leaves it.
        with sim.paused() as bus:
            bus.servo(1).move_by_hand(posed[1] + 400)
            bus.servo(3).move_by_hand(posed[3] + 500)
        await next_event(
            events,
            lambda e: (
                isinstance(e, JointStatesReceived)
                and e.joints["Rotation"] > 30.0
                and e.joints["Elbow"] > 40.0
            ),
        )
        with sim.paused() as bus:
            bus.servo(1).move_by_hand(posed[1])
        await next_event(
            events, lambda e: isinstance(e, JointStatesReceived) and e.joints["Rotation"] < 1.0
        )
        await driver.calibration_finish()
        await next_event(events, peer_change("adopted"))
        elbow = robot.snapshot().joint("Elbow")
        assert elbow.virtual_value == pytest.approx(500 / STEPS_PER_DEGREE)
        assert elbow.goal == elbow.virtual_value
        with sim.paused() as bus:
            bus.write_log = []
        assert (await robot.command(Command.of({"Rotation": 10.0}))).accepted
        await next_event(
            events,
            lambda e: isinstance(e, JointStatesReceived) and abs(e.joints["Rotation"] - 10) < 0.1,
        )
    written = goals_written(sim)
    assert set(written[3]) == {posed[3] + 500}  # the elbow stays where it was left
    assert written[1][-1] == posed[1] + round(10 * STEPS_PER_DEGREE)


async def test_an_arm_moved_by_hand_in_a_cancelled_calibration_joins_again(
    autojump_clock: MockClock, manager: RobotManager, sim: PtySimBus
) -> None:
    rest_the_arm(sim, {})
    robot = await manager.create_robot("so-arm100", robot_id="arm")
    driver = usb_slave(sim, MODEL)
    with robot.subscribe(kinds=[PeerChanged]) as events, watchdog():
        await robot.attach_slave(driver)
        await next_event(events, peer_change("joined"))
        await driver.calibration_start({})  # torque off
        await sim_reaches(sim, torque_off)
        posed = rest_the_arm(sim, {"Pitch": -35.0})  # moved by hand, then given up
        await driver.calibration_cancel()
        await next_event(events, peer_change("adopted"))
    assert robot.snapshot().joint("Pitch").virtual_value == pytest.approx(degrees(posed[2]))


async def test_an_arm_moved_while_its_torque_was_off_for_an_estop_is_not_pulled_back(
    autojump_clock: MockClock, manager: RobotManager, sim: PtySimBus
) -> None:
    rest_the_arm(sim, {})
    robot = await manager.create_robot("so-arm100", robot_id="arm")
    with robot.subscribe(kinds=[PeerChanged, JointStatesReceived]) as events, watchdog():
        await robot.attach_slave(usb_slave(sim, MODEL, estop="torque-off"))
        await next_event(events, peer_change("joined"))
        await robot.estop("test")
        await sim_reaches(sim, torque_off)
        moved = rest_the_arm(sim, {"Elbow": 45.0})  # someone moves the limp arm aside
        await next_event(events, peer_change("adopted"))
        # The robot's pose follows the limp arm (no target goes out while stopped).
        await next_event(
            events,
            lambda e: isinstance(e, JointStatesReceived) and abs(e.joints["Elbow"] - 45) < 0.1,
        )
        assert robot.snapshot().joint("Elbow").virtual_value == pytest.approx(degrees(moved[3]))
        await robot.reset()
        assert robot.snapshot().joint("Elbow").virtual_value == pytest.approx(degrees(moved[3]))
        assert (await robot.command(Command.of({"Rotation": 10.0}))).accepted
        await next_event(
            events,
            lambda e: isinstance(e, JointStatesReceived) and abs(e.joints["Rotation"] - 10) < 0.1,
        )
    assert set(goals_written(sim)[3]) == {moved[3]}  # the elbow stays where it was put


async def targets_of(link: SlaveLink, into: list[dict[str, float]]) -> None:
    """Keep every target a slave connected over the network is sent (it runs elsewhere)."""
    async for message in link.messages():
        if isinstance(message, SlaveTarget):
            into.append(dict(message.joints))


async def test_a_network_slave_that_reports_every_joint_joins_and_one_that_never_does_follows(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    """A slave that runs elsewhere (driver None: /ws/slave) is not known to measure until it
    reports: one that never does, or only some joints, gets the robot's targets from the next
    command, as a twin; one that reports every joint has said where its arm is, and joins."""
    robot = await manager.create_robot("so-arm100", robot_id="arm")
    speed = MODEL.safety.join_speed
    master = await robot.connect_master("operator")
    assert (await master.command(Command.of({"Rotation": 60.0}))).accepted
    await trio.sleep(1)
    twin, arm = await robot.connect_slave("twin"), await robot.connect_slave("arm")
    to_twin: list[dict[str, float]] = []
    to_arm: list[dict[str, float]] = []
    with robot.subscribe(kinds=[PeerChanged]) as events, trio.fail_after(VIRTUAL):
        async with trio.open_nursery() as nursery:
            nursery.start_soon(targets_of, twin, to_twin)
            nursery.start_soon(targets_of, arm, to_arm)
            await twin.report_joint_states({"Rotation": 0.0})  # some joints: not a pose
            await arm.report_joint_states({name: 0.0 for name in MODEL.joint_names})
            joining = await next_event(events, peer_change("joining"))
            assert joining.peer_id == "arm"  # (the twin's report came first)
            assert [s.joining for s in robot.snapshot().slaves] == [False, True]
            assert (await master.command(Command.of({"Jaw": 5.0}))).accepted
            await trio.sleep(0.1)
            assert to_twin and to_twin[0]["Rotation"] == 60.0  # at once, as before
            joined = await next_event(events, peer_change("joined"))
            await trio.sleep(0.1)  # it takes its last target
            way = list(to_arm)
            # Joined, it reports as arms do: that changes nothing, it follows.
            await arm.report_joint_states(dict(to_arm[-1]))
            assert (await master.command(Command.of({"Rotation": 50.0}))).accepted
            await trio.sleep(1)
            assert to_arm[-1]["Rotation"] == 50.0
            assert [e.change for e in events.drain()] == []
            nursery.cancel_scope.cancel()
    assert joined.time - joining.time == pytest.approx(60.0 / speed, abs=0.02)
    rotation = [targets["Rotation"] for targets in way]
    assert rotation == sorted(rotation) and rotation[0] < 1.0 and rotation[-1] == 60.0
    assert way[-1]["Jaw"] == 5.0
    assert [s.joining for s in robot.snapshot().slaves] == [False, False]


async def test_a_network_slave_reporting_to_a_robot_nobody_holds_gives_it_its_pose(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot = await manager.create_robot("so-arm100", robot_id="arm")
    twin = RecordingSlave()
    await robot.attach_slave(twin, "twin")
    with robot.subscribe(kinds=[PeerChanged]) as events, trio.fail_after(VIRTUAL):
        # One that leaves before it said where it is leaves nothing behind: a twin run here
        # under its id reports what it is told, and stays a twin.
        gone = await robot.connect_slave("arm")
        await gone.report_joint_states({"Elbow": -48.0})
        assert robot.snapshot().joint("Elbow").virtual_value == 0.0  # not every joint yet
        await gone.detach()
        again = RecordingSlave()
        await robot.attach_slave(again, "arm")
        assert (await robot.command(Command.of({"Rotation": 10.0}))).accepted
        await trio.sleep(1)
        assert again.targets and again.targets[-1][1]["Rotation"] == 10.0
        changes = [event.change for event in events.drain()]
        assert changes == ["attached", "detached", "attached"]
        await robot.detach_slave("arm")
        # One that reports every joint to a robot no master or arm holds: it gives its pose.
        link = await robot.connect_slave("arm")
        await link.report_joint_states({name: REST.get(name, 0.0) for name in MODEL.joint_names})
        await next_event(events, peer_change("adopted"))
        await next_event(events, peer_change("joined"))
    assert robot.snapshot().joint("Pitch").virtual_value == 48.5
    assert robot.snapshot().joint("Rotation").virtual_value == 0.0  # where the arm is
    await trio.sleep(0.1)
    assert twin.targets[-1][1]["Pitch"] == 48.5  # the twin goes where the arm is
