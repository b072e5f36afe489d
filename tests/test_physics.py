"""The physics slave: MuJoCo's arm follows with a lag, holds against gravity, falls with its
torque off, and says when it touches its table. On trio's MockClock the simulation runs
faster than real time and the same way every time: stepped inside trio (`realtime` off) on an
autojumping clock, or in its worker thread (the default) on a clock the test moves."""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Awaitable, Callable, Iterator

import trio
from trio.testing import MockClock, wait_all_tasks_blocked

from arena.drivers.physics import ArmSimulation, PhysicsSettings, PhysicsSlave
from arena.protocol.rest import PhysicsSlaveBody
from arena.robot.events import JointStatesReceived
from arena.robot.handle import Robot
from arena.robot.manager import RobotManager
from arena.robot.model import load_robot_model
from arena.robot.motion import Command
from arena.robot.snapshot import JointSnapshot
from arena.robot.workspace import Workspace
from arena.server.drivers import make_slave
from tests.conftest import RunningServer

MODEL = load_robot_model("so-arm100")


async def twin(
    manager: RobotManager, robot_id: str = "sim", estop: str = "hold"
) -> tuple[Robot, PhysicsSlave]:
    """A robot with a physics slave stepping on trio's (virtual) clock."""
    robot = await manager.create_robot("so-arm100", robot_id=robot_id)
    slave = PhysicsSlave(PhysicsSettings(realtime=False, estop=estop))
    await robot.attach_slave(slave)
    return robot, slave


def joint(robot: Robot, name: str) -> JointSnapshot:
    return next(j for j in robot.snapshot().joints if j.name == name)


async def test_it_follows_with_a_lag_and_holds_against_gravity(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot, slave = await twin(manager)
    await trio.sleep(1.0)
    result = await robot.command(Command.of({"Rotation": 30.0}))
    assert result.accepted
    await trio.sleep(0.03)
    rotation = joint(robot, "Rotation")
    assert rotation.virtual_value > 0.0  # the targets are on their way (velocity-limited)
    assert rotation.real_value is not None  # the arm lags behind them
    assert rotation.real_value < rotation.virtual_value - 1.0
    await trio.sleep(2.0)
    later = joint(robot, "Rotation")
    assert later.real_value is not None and abs(later.real_value - 30.0) < 1.0
    # held out against gravity: the shoulder sags a little below its target, no more
    assert (await robot.command(Command.of({"Pitch": 15.0}))).accepted
    await trio.sleep(3.0)
    pitch = joint(robot, "Pitch")
    assert pitch.real_value is not None and 0.05 < abs(pitch.real_value - 15.0) < 5.0
    assert slave.contacts_reported == []


async def test_torque_off_lets_it_fall_hold_keeps_it(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    fallen: dict[str, float] = {}
    for policy in ("hold", "torque-off"):
        robot, _ = await twin(manager, f"sim-{policy}", policy)
        assert (await robot.command(Command.of({"Pitch": -30.0}))).accepted  # leaning back
        await trio.sleep(3.0)
        before = {j.name: j.real_value or 0.0 for j in robot.snapshot().joints}
        await robot.estop("drop test")
        await trio.sleep(2.0)
        after = {j.name: j.real_value or 0.0 for j in robot.snapshot().joints}
        fallen[policy] = max(abs(after[name] - before[name]) for name in after)
    # holding (goal = where it is) it sags by its servos' error again, a few degrees; limp, it
    # falls all the way onto its table
    assert fallen["hold"] < 5.0
    assert fallen["torque-off"] > 30.0


async def test_driven_into_its_table_it_reports_the_contact(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot, slave = await twin(manager)
    await robot.set_workspace(Workspace(floor=None))  # the guard would refuse this move
    faults = []
    with robot.subscribe() as events:
        result = await robot.command(Command.of({"Pitch": 60.0}))
        assert result.accepted
        await trio.sleep(4.0)
        faults = [e for e in events.drain() if type(e).__name__ == "FaultReported"]
    assert any(f.code == "CONTACT" and "table" in f.message for f in faults)
    assert any("table" in pair for pair in slave.contacts_reported)


def test_the_step_rate_sets_the_timestep_and_an_arm_held_at_rest_stays_there() -> None:
    simulation = ArmSimulation(MODEL, PhysicsSettings(rate=1000.0))
    assert simulation.model.opt.timestep == 1 / 1000
    simulation.set_pose({"Pitch": -20.0})
    simulation.step(2000)
    settled = simulation.positions()
    simulation.hold()
    simulation.step(1000)
    assert simulation.steps == 3000
    assert all(abs(v - settled[n]) < 5.0 for n, v in simulation.positions().items())


async def test_attached_over_rest(start_server: Callable[..., Awaitable[RunningServer]]) -> None:
    server = await start_server()
    async with server.client() as http:
        await http.post("/api/robots", json={"id": "sim", "robot_type": "so-arm100"})
        made = await http.post("/api/robots/sim/slaves", json={"type": "physics-slave"})
        assert made.status_code == 201 and made.json()["type"] == "physics-slave"
        bad = await http.post("/api/robots/sim/slaves", json={"type": "physics-slave", "rate": 10})
        assert bad.status_code == 422
    assert isinstance(make_slave(PhysicsSlaveBody(realtime=False)), PhysicsSlave)


@contextlib.contextmanager
def watchdog(seconds: float) -> Iterator[None]:
    """Fail the block if it has not ended after `seconds` of real time: on a clock that only
    the test moves, a twin that never reports would otherwise hang the test. (A bound only a
    broken twin reaches; it decides nothing else.)"""
    token = trio.lowlevel.current_trio_token()
    scope = trio.CancelScope()
    ended = threading.Event()

    def watch() -> None:
        if not ended.wait(seconds):
            with contextlib.suppress(trio.RunFinishedError):
                trio.from_thread.run_sync(scope.cancel, trio_token=token)

    threading.Thread(target=watch, daemon=True).start()
    try:
        with scope:
            yield
    finally:
        ended.set()
    assert not scope.cancelled_caught, "the real-time twin stopped reporting"


async def test_the_real_time_twin_steps_as_trio_clock_moves_and_follows(
    mock_clock: MockClock, manager: RobotManager
) -> None:
    # The default, real-time twin (each interval's steps in a worker thread), on a clock only
    # this test moves: it steps its interval's worth (5 steps of 2 ms) each time the clock
    # passes 10 ms, none while the clock stands, and the arm follows the command.
    robot = await manager.create_robot("so-arm100", robot_id="sim")
    slave = PhysicsSlave()
    assert slave.settings.realtime and slave.settings.report_interval == 0.01
    with watchdog(30.0), robot.subscribe(kinds=[JointStatesReceived]) as reports:
        await robot.attach_slave(slave)
        await reports.get()  # compiled (in its thread) and at rest
        await wait_all_tasks_blocked()  # its loop waits for the clock
        assert slave.simulation is not None and slave.simulation.steps == 0
        assert (await robot.command(Command.of({"Rotation": 30.0}))).accepted
        for interval in range(1, 201):  # two seconds, 10 ms (and a hair) at a time
            mock_clock.jump(0.01 + 1e-9)
            await reports.get()
            assert slave.simulation.steps == 5 * interval
        await wait_all_tasks_blocked()
        assert slave.simulation.steps == 1000 and len(reports) == 0  # the clock stands: so does it
    rotation = joint(robot, "Rotation")
    assert rotation.real_value is not None and abs(rotation.real_value - 30.0) < 1.0
