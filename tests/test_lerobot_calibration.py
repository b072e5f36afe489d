"""The SO-101 and LeRobot's calibration files: LeRobot's own code against the simulated bus and
Arena reading the same servos through the same file, a real server driving the arm with an
e-stop, refusals before any torque, `arena calibrate --format lerobot`."""

from __future__ import annotations

import itertools
import json
import math
from collections.abc import Awaitable, Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
import trio

from arena.feetech import registers as reg
from arena.feetech.bus import FEETECH
from arena.protocol.errors import ArenaError
from arena.robot.model import load_robot_model
from arena.servo.lerobot_calibration import (
    from_lerobot,
    is_lerobot_reference,
    lerobot_calibration_dir,
    resolve,
)
from arena.servo.lerobot_format import LeRobotJoint, LeRobotMotor
from arena.servo.sim_pty import PtySimBus
from arena.servo.terminal import calibrate_interactively
from tests.conftest import RunningServer
from tests.hardware import (
    TEST_TIMEOUT_MARGIN,
    eventually,
    open_test_bus,
    running_sim,
    servo_goals,
    servo_torque,
)
from tests.lerobot_arms import (
    NAMES,
    STEP,
    all_read,
    assert_reads_as,
    attach_arm,
    joined,
    lerobot_observes,
    place_arm,
    real_values,
)

lerobot_motors = pytest.importorskip("lerobot.motors")
import scservo_sdk as scs  # noqa: E402
from lerobot.motors import Motor, MotorCalibration, MotorNormMode  # noqa: E402
from lerobot.motors.feetech import FeetechMotorsBus  # noqa: E402
from lerobot.robots.so_follower import SOFollower, SOFollowerRobotConfig  # noqa: E402

StartServer = Callable[..., Awaitable[RunningServer]]
SO101 = load_robot_model("so-101")
#: A calibration as LeRobot's `calibrate()` leaves it: homing offsets, swept ranges (the wrist
#: roll a whole turn), drive mode 0.
CALIBRATION = {
    "shoulder_pan": MotorCalibration(1, 0, -310, 760, 3320),
    "shoulder_lift": MotorCalibration(2, 0, 1180, 870, 3210),
    "elbow_flex": MotorCalibration(3, 0, -905, 900, 3100),
    "wrist_flex": MotorCalibration(4, 0, 40, 860, 3250),
    "wrist_roll": MotorCalibration(5, 0, 1500, 0, 4095),
    "gripper": MotorCalibration(6, 0, -1200, 2030, 3450),
}
#: Where the arm stands, as steps the servos report before LeRobot writes its homing.
ACTUAL = {1: 1800, 2: 3400, 3: 1100, 4: 2200, 5: 600, 6: 1250}


@pytest.fixture
def sim(tmp_path: Path) -> Iterator[PtySimBus]:
    yield from running_sim(tmp_path)


def lerobot_follower(sim: PtySimBus, folder: Path) -> SOFollower:
    """LeRobot's own SO follower (degrees mode) on the simulated bus, its calibration folder
    `folder`. Its port waits for the simulator as Arena's test buses do: a loaded machine
    cannot make its servos look silent."""
    config = SOFollowerRobotConfig(
        port=str(sim.link), id="arm", calibration_dir=folder, use_degrees=True
    )
    robot = SOFollower(config)
    bus = robot.bus
    bus.port_handler = sim.paced_port(TEST_TIMEOUT_MARGIN)
    bus.sync_reader = scs.GroupSyncRead(bus.port_handler, bus.packet_handler, 0, 0)
    bus.sync_writer = scs.GroupSyncWrite(bus.port_handler, bus.packet_handler, 0, 0)
    return robot


def lerobot_reads(sim: PtySimBus, folder: Path) -> dict[str, float]:
    """What LeRobot reads: its follower writes the calibration file and the servos' registers,
    as its `connect()` does when the user keeps the file, then observes the arm."""
    return lerobot_observes(lerobot_follower(sim, folder), CALIBRATION, configure=False)


async def attach_so101(http: Any, sim: PtySimBus, calibration: str) -> None:
    """Robot `arm` of type so-101, its usb-slave on the simulated bus with `calibration`."""
    attached = await attach_arm(http, sim, "so-101", calibration)
    assert attached.status_code == 201, attached.text


@pytest.mark.parametrize("registers", ["written", "fresh"])
async def test_arena_reads_the_servos_as_lerobot_does(
    start_server: StartServer,
    sim: PtySimBus,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    registers: str,
) -> None:
    """`fresh`: the same arm, but its servos' registers back to a new servo's (no homing, whole
    range): Arena applies the file's offsets itself and still reads what LeRobot read."""
    place_arm(sim, ACTUAL)
    folder = tmp_path / "hf" / "robots" / "so_follower"
    expected = await trio.to_thread.run_sync(lerobot_reads, sim, folder)
    assert (folder / "arm.json").is_file()
    if registers == "fresh":
        with sim.paused() as bus:
            for servo in bus.servos.values():
                actual = servo.actual
                servo.poke(reg.HOMING_OFFSET, 0)
                servo.poke(reg.MIN_POSITION_LIMIT, 0)
                servo.poke(reg.MAX_POSITION_LIMIT, 4095)
                servo.move_by_hand(actual)  # (homing 0: present = actual) it has not moved
    monkeypatch.setenv("HF_LEROBOT_CALIBRATION", str(tmp_path / "hf"))
    server = await start_server()
    async with server.client() as http:
        await attach_so101(http, sim, "lerobot:arm")
        await eventually(lambda: all_read(http), what="joint states from the bus")
        read = await real_values(http)
    assert_reads_as(read, expected, CALIBRATION)


async def test_so101_driven_through_a_server_with_an_estop(
    start_server: StartServer, sim: PtySimBus, tmp_path: Path
) -> None:
    place_arm(sim, ACTUAL)
    path = tmp_path / "arm.json"
    await trio.to_thread.run_sync(lerobot_reads, sim, tmp_path)  # writes arm.json
    server = await start_server()
    async with server.client() as http:
        await attach_so101(http, sim, str(path))
        await eventually(lambda: joined(http), what="the arm joined")
        status = (await http.get("/api/robots/arm/calibration")).json()
        assert status["calibrated"] is True and status["file"] == str(path)
        refused = await http.post("/api/robots/arm/calibration/start")
        assert refused.status_code == 409  # Arena never writes over the LeRobot file
        assert str(path) in refused.json()["error"]["message"]
        move = {
            "joints": [{"name": "shoulder_pan", "value": 12.0}, {"name": "gripper", "value": 60}]
        }
        answer = await http.put("/api/robots/arm/joints", json=move)
        assert answer.status_code == 200, answer.text

        async def arrived() -> bool:
            read = await real_values(http)
            pan, grip = read["shoulder_pan"], read["gripper"]
            return pan is not None and grip is not None and abs(pan - 12) < 1 and abs(grip - 60) < 1

        await eventually(arrived, what="the arm at shoulder_pan 12, gripper 60")
        # The goal LeRobot itself would write for those values (its `_unnormalize`).
        goals = servo_goals(sim)
        pan = CALIBRATION["shoulder_pan"]
        assert abs(goals[1] - (12 * 4095 / 360 + (pan.range_min + pan.range_max) / 2)) <= 1
        grip = CALIBRATION["gripper"]
        assert abs(goals[6] - (0.6 * (grip.range_max - grip.range_min) + grip.range_min)) <= 1
        stopped = await http.post("/api/robots/arm/estop", json={"reason": "test"})
        assert stopped.status_code == 200

        def holding() -> bool:  # "hold" writes goal = present from the bus thread, soon after
            with sim.paused() as bus:
                servos = bus.servos.values()
                return all(
                    s.peek(reg.GOAL_POSITION) == s.peek(reg.PRESENT_POSITION) for s in servos
                )

        await eventually(holding, what="every servo held where it is")
        held = servo_goals(sim)
        refused = await http.put(
            "/api/robots/arm/joints", json={"joints": [{"name": "shoulder_pan", "value": -20}]}
        )
        assert refused.status_code >= 400
        assert (await http.get("/api/robots/arm/status")).json()["state"] == "estopped"
        assert set(servo_torque(sim).values()) == {1}  # "hold": torque kept, goal = present
        assert servo_goals(sim) == held


@pytest.mark.parametrize(
    ("change", "words"),
    [
        ({"elbow_flex": {"id": 7}}, ["elbow_flex", "id 7"]),
        ({"wrist_flex": {"range_max": 5000}}, ["wrist_flex", "range_max 5000"]),
        ({"gripper": {"homing_offset": -3000}}, ["gripper", "homing_offset -3000"]),
        ({"shoulder_pan": {"range_min": 3320}}, ["shoulder_pan", "range_min 3320"]),
        ({"wrist_roll": None}, ["no entry for wrist_roll"]),
        ({"tail": {"id": 9}}, ["motor 'tail'"]),
    ],
)
async def test_a_file_that_does_not_fit_is_refused_before_any_torque(
    start_server: StartServer,
    sim: PtySimBus,
    tmp_path: Path,
    change: dict[str, dict[str, int] | None],
    words: list[str],
) -> None:
    data = {name: vars(cal) for name, cal in CALIBRATION.items()}
    for name, fields in change.items():
        if fields is None:
            del data[name]
        else:
            data[name] = {**data.get(name, vars(CALIBRATION["gripper"])), **fields}
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(data))
    server = await start_server()
    async with server.client() as http:
        await http.post("/api/robots", json={"id": "arm", "robot_type": "so-101"})
        body = {"type": "usb-slave", "port": str(sim.link), "calibration": str(path)}
        reply = await http.post("/api/robots/arm/slaves", json=body)
        assert reply.status_code == 422, reply.text
        error = reply.json()["error"]
        assert error["code"] == "INVALID_CONFIG"
        for word in words:
            assert word in error["message"]
        assert (await http.get("/api/robots/arm")).json()["slaves"] == []
    assert set(servo_torque(sim).values()) == {0}


async def test_a_missing_lerobot_calibration_says_where_it_looked(
    start_server: StartServer, sim: PtySimBus, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("HF_LEROBOT_CALIBRATION", str(tmp_path / "hf"))
    server = await start_server()
    async with server.client() as http:
        await http.post("/api/robots", json={"id": "arm", "robot_type": "so-101"})
        body = {"type": "usb-slave", "port": str(sim.link), "calibration": "lerobot:nobody"}
        reply = await http.post("/api/robots/arm/slaves", json=body)
        assert reply.status_code == 422
        message = reply.json()["error"]["message"]
        assert "so_follower/nobody.json" in message and "so101_follower/nobody.json" in message
        for value in ("../x", "/etc/passwd", "lerobot:../x"):
            body["calibration"] = value
            reply = await http.post("/api/robots/arm/slaves", json=body)
            assert reply.status_code == 422 and reply.json()["error"]["code"] == "INVALID_BODY"
    assert set(servo_torque(sim).values()) == {0}


def test_lerobot_folder_names_old_and_new(tmp_path: Path) -> None:
    env = {"HF_LEROBOT_CALIBRATION": str(tmp_path)}
    old = tmp_path / "robots" / "so101_follower" / "arm.json"
    old.parent.mkdir(parents=True)
    old.write_text("{}")
    assert resolve("lerobot:arm", "so-101", FEETECH, leader=False, env=env) == old
    new = tmp_path / "robots" / "so_follower" / "arm.json"
    new.parent.mkdir(parents=True)
    new.write_text("{}")
    assert (
        resolve("lerobot:arm", "so-101", FEETECH, leader=False, env=env) == new
    )  # 0.4.3 and later
    with pytest.raises(ArenaError, match="so100_leader"):
        resolve(
            "lerobot:arm", "so-arm100", FEETECH, leader=True, env=env
        )  # leaders: teleoperators/
    leader = tmp_path / "teleoperators" / "so100_leader" / "arm.json"
    leader.parent.mkdir(parents=True)
    leader.write_text("{}")
    assert resolve("lerobot:arm", "so-arm100", FEETECH, leader=True, env=env) == leader
    assert lerobot_calibration_dir({"HF_HOME": "/h"}) == Path("/h/lerobot/calibration")
    assert (
        lerobot_calibration_dir({}) == Path("~/.cache/huggingface/lerobot/calibration").expanduser()
    )
    assert is_lerobot_reference("a/b.json") and is_lerobot_reference("lerobot:x")
    assert not is_lerobot_reference("arm") and not is_lerobot_reference(None)


def test_the_arithmetic_is_lerobots_even_when_the_servos_hold_other_offsets() -> None:
    """Against LeRobot's own `_normalize`/`_unnormalize`, every mode, both drive modes; the
    servos' registers holding other offsets than the file's (the file never written to them)."""
    for drive_mode, mode in itertools.product(
        (0, 1), (MotorNormMode.DEGREES, MotorNormMode.RANGE_0_100)
    ):
        cal = MotorCalibration(1, drive_mode, 300, 700, 3100)
        bus = FeetechMotorsBus("unused", {"j": Motor(1, "sts3215", mode)}, calibration={"j": cal})
        joint = LeRobotJoint(
            motor=LeRobotMotor(**vars(cal)),
            percent=mode is MotorNormMode.RANGE_0_100,
            register_homing=-150,
        )
        for actual in range(0, 4096, 37):
            homed = (actual - cal.homing_offset) % 4096  # what the servo reports once written
            present = (actual + 150) % 4096  # what it reports holding -150
            if not cal.range_min <= homed <= cal.range_max:
                continue
            assert joint.to_value(present) == pytest.approx(bus._normalize({1: homed})[1])
        for value in (0.0, 12.5, 33.3, 99.0) if joint.percent else (-80.0, -1.3, 0.0, 45.7):
            theirs = bus._unnormalize({1: value})[1]
            # the goal in the servo's frame, back to the file's: actual - homing_offset
            ours = (joint.to_steps(value) - 150 - cal.homing_offset) % 4096
            assert abs(ours - theirs) <= 1


def test_so101_is_lerobots_arm() -> None:
    assert SO101.joint_names == NAMES
    assert [j.servo_id for j in SO101.joints] == [1, 2, 3, 4, 5, 6]
    gripper = SO101.joint("gripper")
    assert gripper is not None and (gripper.lower, gripper.upper) == (0.0, 100.0)
    assert gripper.to_urdf(0) == pytest.approx(-0.174533)  # closed: the URDF's lower limit
    assert gripper.to_urdf(100) == pytest.approx(1.74533)
    assert gripper.from_urdf(gripper.to_urdf(37.0)) == pytest.approx(37.0)
    pan = SO101.joint("shoulder_pan")
    assert pan is not None and pan.to_urdf(0.0) == 0.0  # LeRobot's zero is the URDF's
    assert (pan.lower, pan.upper) == pytest.approx((-110.0, 110.0), abs=0.001)
    with pytest.raises(ArenaError, match="id 2"):
        from_lerobot({n: {**vars(c), "id": 2} for n, c in CALIBRATION.items()}, SO101, "f", FEETECH)


def test_calibrate_format_lerobot_reads_zero_at_rest_in_lerobot(
    sim: PtySimBus, tmp_path: Path
) -> None:
    """`arena calibrate --format lerobot` on a fresh arm; LeRobot reads the rest pose as 0 and
    gives unswept joints the robot type's limits."""
    rest = {1: 3000, 2: 1100, 3: 2500, 4: 700, 5: 3900, 6: 1500}  # a freshly built arm
    with sim.paused() as simulated:
        for sid, step in rest.items():
            simulated.servo(sid).move_by_hand(step)
    out = tmp_path / "robots" / "so_follower" / "arm.json"
    bus = open_test_bus(str(sim.link))
    bus.open()
    try:  # Enter at once: at rest, then no joint swept
        calibrate_interactively(
            bus,
            {j.name: j.servo_id for j in SO101.joints},
            out,
            robot_type="so-101",
            lerobot_model=SO101,
            ask=lambda _: "",
            say=lambda _: None,
        )
    finally:
        bus.close()
    data = json.loads(out.read_text())
    assert list(data) == list(NAMES)
    assert set(data["elbow_flex"]) == {
        "id",
        "drive_mode",
        "homing_offset",
        "range_min",
        "range_max",
    }
    robot = lerobot_follower(sim, out.parent)
    assert robot.calibration  # LeRobot loads the file itself
    robot.bus.connect()
    try:
        robot.bus.disable_torque()
        robot.bus.write_calibration(robot.calibration)
        read = robot.get_observation()
    finally:
        robot.bus.disconnect()
    for name in NAMES[:-1]:
        assert abs(read[f"{name}.pos"]) <= STEP, name
    elbow = robot.calibration["elbow_flex"]  # not swept: the so-101's limits, about 96.8 deg
    assert (elbow.range_max - elbow.range_min) / 2 * STEP == pytest.approx(96.83, abs=0.1)
    assert read["gripper.pos"] == pytest.approx(0.0, abs=0.1)  # rest at 0: closed
    assert math.isfinite(read["wrist_roll.pos"])


#: The SO-101 leader as LeRobot's `SOLeader` calibrates it (its STS3215s of mixed gear ratios
#: all answer as model 777; the ratio does not change what the encoder reads).
LEADER_CALIBRATION = {
    "shoulder_pan": MotorCalibration(1, 0, 120, 900, 3100),
    "shoulder_lift": MotorCalibration(2, 0, -400, 1000, 3000),
    "elbow_flex": MotorCalibration(3, 0, 0, 1100, 3000),
    "wrist_flex": MotorCalibration(4, 0, 300, 1000, 3100),
    "wrist_roll": MotorCalibration(5, 0, 0, 0, 4095),
    "gripper": MotorCalibration(6, 0, 0, 2000, 2900),
}
#: The leader's pose as its servos report it once calibrated (inside the so-101's limits).
LEADER_PRESENT = {1: 2200, 2: 1800, 3: 2150, 4: 2000, 5: 2048, 6: 2450}


def lerobot_calibrates_the_leader(sim: PtySimBus, folder: Path) -> None:
    """LeRobot's own `SOLeader` writes its calibration to the servos and its file to `folder`."""
    from lerobot.teleoperators.so_leader import SOLeader, SOLeaderTeleopConfig

    leader = SOLeader(SOLeaderTeleopConfig(port=str(sim.link), id="arm", calibration_dir=folder))
    bus = leader.bus
    bus.port_handler = sim.paced_port(TEST_TIMEOUT_MARGIN)
    bus.sync_reader = scs.GroupSyncRead(bus.port_handler, bus.packet_handler, 0, 0)
    bus.sync_writer = scs.GroupSyncWrite(bus.port_handler, bus.packet_handler, 0, 0)
    bus.connect()
    try:
        bus.disable_torque()
        bus.write_calibration(dict(LEADER_CALIBRATION))
        leader.calibration = dict(LEADER_CALIBRATION)
        leader._save_calibration()
    finally:
        bus.disconnect()


def leader_value(name: str, present: int) -> float:
    """What LeRobot reads (degrees mode; the gripper 0-100) for the leader at `present`."""
    cal = LEADER_CALIBRATION[name]
    if name == "gripper":
        return (present - cal.range_min) / (cal.range_max - cal.range_min) * 100
    return (present - (cal.range_min + cal.range_max) / 2) * 360 / 4095


async def test_the_so101_follower_mirrors_the_so101_leader(
    start_server: StartServer, sim: PtySimBus, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    place_arm(sim, ACTUAL)
    await trio.to_thread.run_sync(lerobot_reads, sim, tmp_path / "hf" / "robots" / "so_follower")
    with contextmanager(running_sim)(tmp_path / "leader") as leader:
        folder = tmp_path / "hf" / "teleoperators" / "so_leader"
        await trio.to_thread.run_sync(lerobot_calibrates_the_leader, leader, folder)
        with leader.paused() as bus:
            for sid, present in LEADER_PRESENT.items():
                bus.servo(sid).move_by_hand(present)
        monkeypatch.setenv("HF_LEROBOT_CALIBRATION", str(tmp_path / "hf"))
        server = await start_server()
        async with server.client() as http:
            await attach_so101(http, sim, "lerobot:arm")
            await eventually(lambda: joined(http), what="the follower joined")
            body = {"type": "usb-master", "port": str(leader.link), "calibration": "lerobot:arm"}
            master = await http.post("/api/robots/arm/master", json=body)
            assert master.status_code == 201, master.text
            wanted = {
                name: leader_value(name, LEADER_PRESENT[sid + 1]) for sid, name in enumerate(NAMES)
            }

            async def mirrored() -> bool:
                read = await real_values(http)
                return all(
                    (value := read[name]) is not None and abs(value - wanted[name]) < 1
                    for name in NAMES
                )

            await eventually(mirrored, what=f"the follower at the leader's pose {wanted}")
        with leader.paused() as bus:  # a leader is moved by hand: never torque on
            assert all(s.peek(reg.TORQUE_ENABLE) == 0 for s in bus.servos.values())
