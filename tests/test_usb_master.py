"""The leader arm (usb-master) driving a follower (usb-slave): two simulated buses, real SDK."""

from __future__ import annotations

from collections.abc import Awaitable, Callable, Iterator
from pathlib import Path

import pytest
import trio
from trio.testing import MockClock

from arena.drivers.bus_bridge import BusBridge
from arena.drivers.usb_master import UsbMaster
from arena.feetech import registers as reg
from arena.protocol.rest import UsbMasterBody
from arena.robot.handle import Robot
from arena.robot.links import MasterLink
from arena.robot.manager import RobotManager
from arena.robot.model import load_robot_model
from arena.robot.motion import Command, CommandResult
from arena.robot.safety import Mode
from arena.server.drivers import usb_master_config
from arena.servo.calibration import Calibration, calibrate_rest
from arena.servo.health import HealthLimits
from arena.servo.sim_pty import PtySimBus
from arena.servo.worker import Reading, WorkerSettings
from tests.conftest import RunningServer, eventually
from tests.hardware import (
    open_test_bus,
    running_sim,
    servo_goals,
    servo_torque,
    usb_slave,
    wait_joined,
)

MODEL = load_robot_model("so-arm100")
JOINTS = {j.name: j.servo_id for j in MODEL.joints}
LEADER_REST = {1: 1000, 2: 1500, 3: 2500, 4: 3000, 5: 100, 6: 2048}
FOLLOWER_REST = {1: 2100, 2: 900, 3: 3500, 4: 2000, 5: 4000, 6: 1500}
STEP = 360 / 4096  # degrees an encoder step


@pytest.fixture
def leader(tmp_path: Path) -> Iterator[PtySimBus]:
    yield from running_sim(tmp_path / "leader")


@pytest.fixture
def follower(tmp_path: Path) -> Iterator[PtySimBus]:
    yield from running_sim(tmp_path / "follower")


def pose(sim: PtySimBus, raw: dict[int, int]) -> None:
    with sim.paused() as bus:
        for sid, value in raw.items():
            bus.servo(sid).move_by_hand(value)


def calibrated_at(raw: dict[int, int], path: Path) -> Path:
    """A calibration in which the pose `raw` is the twin's rest pose (every joint at 0)."""
    calibrate_rest(Calibration.identity(JOINTS), raw, dict.fromkeys(JOINTS, 0.0)).save(path)
    return path


def leader_arm(sim: PtySimBus, calibration: Path, **config: object) -> UsbMaster:
    body = UsbMasterBody(port=str(sim.link), **config)  # type: ignore[arg-type]
    settings = WorkerSettings(rate=200.0, limits=HealthLimits(lost_after=5))
    return UsbMaster(
        usb_master_config(body), MODEL, calibration, settings=settings, open_bus=open_test_bus
    )


def record_commands(master: UsbMaster, sent: list[Command]) -> None:
    """Keep in `sent` every command the leader arm sends its robot."""
    mirror = master._mirror

    async def recording(link: MasterLink, bridge: BusBridge) -> None:
        command = link.command

        async def recorded(what: Command, *, in_burst: bool = False) -> CommandResult:
            sent.append(what)
            return await command(what, in_burst=in_burst)

        link.command = recorded  # type: ignore[method-assign]
        await mirror(link, bridge)

    master._mirror = recording  # type: ignore[method-assign]


async def teleop(
    manager: RobotManager,
    leader: PtySimBus,
    follower: PtySimBus,
    tmp_path: Path,
    sent: list[Command] | None = None,
) -> tuple[Robot, UsbMaster]:
    """A robot with the follower as its slave and the leader arm as its master (`sent`: keep
    the commands the leader sends)."""
    pose(leader, LEADER_REST)
    pose(follower, FOLLOWER_REST)
    robot = await manager.create_robot("so-arm100", robot_id="arm")
    await robot.attach_slave(
        usb_slave(follower, MODEL, calibrated_at(FOLLOWER_REST, tmp_path / "arm.json"))
    )
    await eventually(lambda: all(servo_torque(follower).values()), what="follower torque")
    await wait_joined(robot)  # the robot has the follower's pose before the leader commands
    master = leader_arm(leader, calibrated_at(LEADER_REST, tmp_path / "arm-leader.json"))
    if sent is not None:
        record_commands(master, sent)
    await master.prepare()  # as the server does: the bus is up before the master claims
    await robot.attach_master(master)
    return robot, master


async def test_the_follower_mirrors_the_leader(
    manager: RobotManager, leader: PtySimBus, follower: PtySimBus, tmp_path: Path
) -> None:
    robot, _ = await teleop(manager, leader, follower, tmp_path)
    assert robot.snapshot().master is not None and robot.snapshot().master.kind == "usb-master"
    assert not any(servo_torque(leader).values())  # the leader stays limp
    # Both calibrated to the same rest pose: at rest, the follower holds its own rest.
    await eventually(lambda: servo_goals(follower) == FOLLOWER_REST, what="rest mirrored")
    moved = {3: LEADER_REST[3] + 300, 1: LEADER_REST[1] - 200}
    pose(leader, moved)
    expected = {**FOLLOWER_REST, 3: FOLLOWER_REST[3] + 300, 1: FOLLOWER_REST[1] - 200}
    await eventually(lambda: servo_goals(follower) == expected, what="the move mirrored")


class ActedOn:
    """The raw readings a leader arm's driver has acted on, in order (its `_pose` wrapped):
    what it saw, to wait for instead of for time."""

    def __init__(self, master: UsbMaster) -> None:
        self.raw: list[dict[int, int]] = []
        pose = master._pose

        def seen(reading: Reading) -> dict[str, float]:
            self.raw.append(dict(reading.positions))
            return pose(reading)

        master._pose = seen  # type: ignore[method-assign]

    async def past(self, servo: int, value: int) -> None:
        """Wait until the driver has acted on a reading of `servo` at `value` and taken the
        next reading: it is done with that one (and sent whatever it was going to)."""
        start = len(self.raw)

        def done() -> bool:
            hits = [k for k in range(start, len(self.raw)) if self.raw[k].get(servo) == value]
            return bool(hits) and len(self.raw) > hits[0] + 1

        await eventually(done, what=f"servo {servo} at {value} acted on")


async def test_a_leader_at_rest_sends_nothing(
    manager: RobotManager, leader: PtySimBus, follower: PtySimBus, tmp_path: Path
) -> None:
    _, master = await teleop(manager, leader, follower, tmp_path)
    acted = ActedOn(master)
    await eventually(lambda: master.sent >= 1, what="the first command")
    await acted.past(2, LEADER_REST[2])  # the rest pose mirrored, and done with
    before = master.sent
    for jitter in (2, -3, 1, 0, 3):  # a hand resting on the leader: under half a degree
        pose(leader, {2: LEADER_REST[2] + jitter})
        await acted.past(2, LEADER_REST[2] + jitter)
    # No stream: at most the one command of a pose held (`SETTLE_AFTER`, see below).
    assert master.sent - before <= 1
    before = master.sent
    pose(leader, {2: LEADER_REST[2] + 40})  # 3.5 degrees: a real move
    await eventually(lambda: master.sent >= before + 1, what="one command for the move")
    assert master.sent - before <= 2  # (and its settle, should it come already)


async def test_a_leader_s_slow_move_is_sent_from_its_start(
    manager: RobotManager, leader: PtySimBus, follower: PtySimBus, tmp_path: Path
) -> None:
    # Issue 57: a move went out only once it had left the 0.5 degree dead band (six encoder
    # steps); three steps the same way in a row are a move.
    sent: list[Command] = []
    _, master = await teleop(manager, leader, follower, tmp_path, sent)
    acted = ActedOn(master)
    await eventually(lambda: servo_goals(follower) == FOLLOWER_REST, what="rest mirrored")
    # A move, and a last bit of it inside the band: the leader rests where it settled.
    pose(leader, {2: LEADER_REST[2] + 40})
    await eventually(lambda: servo_goals(follower)[2] == FOLLOWER_REST[2] + 40, what="a move")
    pose(leader, {2: LEADER_REST[2] + 43})
    await eventually(lambda: servo_goals(follower)[2] == FOLLOWER_REST[2] + 43, what="settled")
    before = len(sent)
    for step in range(44, 54):  # then a slow move: a step a read or so, none held long
        pose(leader, {2: LEADER_REST[2] + step})
        await acted.past(2, LEADER_REST[2] + step)
    await eventually(lambda: servo_goals(follower)[2] == FOLLOWER_REST[2] + 53, what="the end")
    pitches = [goal.value for c in sent[before:] for goal in c.joints if goal.name == "Pitch"]
    first = next(value for value in pitches if value != pytest.approx(43 * STEP))
    assert 0 < first - 43 * STEP < 0.5  # before the band: at its third step, or the fourth


async def test_the_follower_settles_where_the_leader_settled(
    manager: RobotManager, leader: PtySimBus, follower: PtySimBus, tmp_path: Path
) -> None:
    # Issue 57: a last move inside the leader's dead band (0.5 degrees) left the follower up
    # to the band short of the leader for good. A pose held is sent once.
    robot, _ = await teleop(manager, leader, follower, tmp_path)
    await eventually(lambda: servo_goals(follower) == FOLLOWER_REST, what="rest mirrored")
    pose(leader, {1: LEADER_REST[1] + 40})  # a real move (3.5 degrees)...
    await eventually(
        lambda: servo_goals(follower)[1] == FOLLOWER_REST[1] + 40, what="the move mirrored"
    )
    pose(leader, {1: LEADER_REST[1] + 45})  # ...that ends 0.44 degrees on: inside the band
    await eventually(
        lambda: servo_goals(follower)[1] == FOLLOWER_REST[1] + 45, what="the follower settled"
    )
    # (the servo's step is 0.088 degrees: the trajectory may still be settling onto the goal)
    await eventually(
        lambda: robot.joint_values()[0]["Rotation"] == pytest.approx(45 * 360 / 4096),
        what="the robot's target on the leader's pose",
    )


async def test_estop_freezes_the_follower_for_good(
    manager: RobotManager, leader: PtySimBus, follower: PtySimBus, tmp_path: Path
) -> None:
    robot, _ = await teleop(manager, leader, follower, tmp_path)
    await eventually(lambda: servo_goals(follower) == FOLLOWER_REST)
    await robot.estop("test")
    assert robot.snapshot().master is None  # an e-stop ends the leader's command
    pose(leader, {3: LEADER_REST[3] + 400})
    await robot.reset()
    # A move of another joint by hand goes out after the leader's: once the follower has it,
    # the leader's would have been there too. (A leader still in command would also have the
    # hand's move refused.)
    assert (await robot.command(Command.of({"Wrist_Roll": 10.0}))).accepted
    await eventually(lambda: servo_goals(follower)[5] != FOLLOWER_REST[5], what="the hand's move")
    assert servo_goals(follower)[3] == FOLLOWER_REST[3]  # and it does not resume by itself
    assert robot.snapshot().master is None


async def test_unplugging_the_leader_estops_the_robot(
    manager: RobotManager, leader: PtySimBus, follower: PtySimBus, tmp_path: Path
) -> None:
    robot, _ = await teleop(manager, leader, follower, tmp_path)
    await eventually(lambda: servo_goals(follower) == FOLLOWER_REST)
    leader.unplug()
    await eventually(lambda: robot.snapshot().mode is Mode.ESTOPPED, what="e-stop")
    assert "leader arm bus" in (robot.snapshot().estop_reason or "")
    assert robot.snapshot().master is None


StartServer = Callable[..., Awaitable[RunningServer]]


async def test_leader_over_rest_claims_the_robot_and_frees_its_port(
    start_server: StartServer, leader: PtySimBus, tmp_path: Path
) -> None:
    server = await start_server(calibration_dir=str(tmp_path / "calibration"))
    config = {"type": "usb-master", "port": str(leader.link)}
    async with server.client() as http:
        await http.post("/api/robots", json={"id": "arm"})
        first = await http.post("/api/robots/arm/master", json=config)
        assert first.status_code == 201, first.text
        assert (await http.get("/api/robots/arm")).json()["master"]["type"] == "usb-master"
        second = await http.post("/api/robots/arm/master", json=config)
        assert (second.status_code, second.json()["error"]["code"]) == (409, "MASTER_ACTIVE")
        await http.delete("/api/robots/arm/master")
        again = await http.post("/api/robots/arm/master", json=config)
        assert again.status_code == 201, again.text  # the port was freed both times
        bad = await http.post("/api/robots/arm/master", json={**config, "deadband": -1})
        assert bad.json()["error"]["code"] == "INVALID_BODY"
    with leader.paused() as bus:
        assert all(s.peek(reg.TORQUE_ENABLE) == 0 for s in bus.servos.values())


# -- The mirror's rules on trio's MockClock: a real BusBridge fed readings at the leader's rate
# (250 Hz), a stand-in for the robot's link that records what the leader commands and when.

READ = 1 / 250  # seconds between the leader's reads


class RecordingLink:
    """A master link that accepts every command and records (trio time, pose)."""

    paused = False

    def __init__(self) -> None:
        self.commands: list[tuple[float, dict[str, float]]] = []

    async def command(self, command: Command) -> CommandResult:
        self.commands.append((trio.current_time(), {g.name: g.value for g in command.joints}))
        return CommandResult(accepted=True)

    async def lost(self, reason: str) -> None:
        raise AssertionError(reason)


async def mirrored(raws: list[int]) -> list[tuple[float, dict[str, float]]]:
    """Run a leader's mirror on servo 1's raw readings `raws`, one a read (the other joints
    still at 2048, 0 degrees uncalibrated); the commands it sent, with their trio times."""
    master = UsbMaster(usb_master_config(UsbMasterBody(port="/dev/null")), MODEL)
    link = RecordingLink()
    bridge = BusBridge()
    async with trio.open_nursery() as nursery:
        nursery.start_soon(master._mirror, link, bridge)
        for raw in raws:
            bridge.reading(Reading({**dict.fromkeys(JOINTS.values(), 2048), 1: raw}, time=0.0))
            await trio.sleep(READ)
        await trio.sleep(1.0)
        nursery.cancel_scope.cancel()
    return link.commands


def minimum_jerk(start: float, end: float, seconds: float) -> list[int]:
    """Servo 1's raw readings (a read every `READ`) along a minimum-jerk move in degrees."""
    reads = round(seconds / READ)
    out = []
    for k in range(reads + 1):
        t = k / reads
        degrees = start + (end - start) * (10 * t**3 - 15 * t**4 + 6 * t**5)
        out.append(2048 + round(degrees / STEP))
    return out


async def test_a_slow_move_reaches_the_follower_from_its_start(autojump_clock: MockClock) -> None:
    # Issue 57: a move was sent only once it had left the 0.5 degree dead band, 10-25 ms after
    # its first visible step; three steps the same way in a row are a move, sent at once.
    rest = [2048] * 100
    there = minimum_jerk(0.0, 30.0, 1.0)  # a slow move, then back after a rest
    back = minimum_jerk(30.0, 0.0, 1.0)
    raws = rest + there + [there[-1]] * 125 + back + [back[-1]] * 125
    commands = await mirrored(raws)
    for move, origin in ((there, 100), (back, 100 + len(there) + 125)):
        first_step = origin + next(k for k, raw in enumerate(move) if raw != move[0])
        began = first_step * READ  # trio time of the read that shows the first step
        value = next(pose["Rotation"] for at, pose in commands if at >= began - 1e-9)
        # Three steps on (0.26 degrees), four should the robot's rate limit hold it a read.
        assert 0 < abs(value - (move[0] - 2048) * STEP) < 0.5
        # Each move ends where the leader stopped.
        assert any(
            pose["Rotation"] == pytest.approx((move[-1] - 2048) * STEP) for _, pose in commands
        )
    assert commands[-1][1]["Rotation"] == pytest.approx(0.0)  # and settles where it stopped


@pytest.mark.parametrize(
    ("flicker", "hold"),
    [
        ((0, 1, 0, -1, 1, -1, 0, 1, 1, 0, -1, -1), 2),  # +-1 step, two reads each
        ((0, 2, -1, 1, -2, 0, 2, 1, -2, -1, 1, -1, 2, 0, -2), 1),  # +-2, back and forth
    ],
)
async def test_a_resting_leader_s_flicker_sends_nothing(
    autojump_clock: MockClock, flicker: tuple[int, ...], hold: int
) -> None:
    # A leader at rest whose encoder flickers (an STS3215's or XL330's reading toggling by a
    # step or two) must not command the follower all the time: for three seconds, nothing
    # after the first settled pose.
    raws = [2048 + value for value in flicker for _ in range(hold)] * 60
    assert len(raws) * READ >= 3.5
    commands = await mirrored(raws)
    assert [at for at, _ in commands if at > 0.5] == []
