"""The Koch arm on Dynamixel servos: LeRobot's own `DynamixelMotorsBus` (through its
`KochFollower`) against the simulated Dynamixel bus, Arena reading the same servos through the
same calibration file, a real server driving the arm with an e-stop, refusals before any
torque; the Protocol 2.0 codec against the SDK's own CRC and stuffing."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections.abc import Awaitable, Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
import trio
from trio.testing import MockClock

from arena.robot.manager import RobotManager
from arena.servo.sim_pty import PtySimBus
from tests.conftest import RunningServer
from tests.hardware import TEST_TIMEOUT_MARGIN, eventually, running_sim
from tests.lerobot_arms import (
    NAMES,
    STEP,
    all_read,
    assert_reads_as,
    attach_arm,
    joined,
    lerobot_observes,
    one_step,
    place_arm,
    real_values,
)

dxl = pytest.importorskip("dynamixel_sdk")
pytest.importorskip("lerobot.motors.dynamixel")
from lerobot.motors import MotorCalibration  # noqa: E402
from lerobot.robots.koch_follower import KochFollower, KochFollowerConfig  # noqa: E402

from arena.dynamixel import packets  # noqa: E402
from arena.dynamixel import registers as reg  # noqa: E402
from arena.dynamixel.sim import SimBus  # noqa: E402

StartServer = Callable[..., Awaitable[RunningServer]]
sim_on = contextmanager(running_sim)  # a second simulated bus in one test
#: A calibration as LeRobot's Koch `calibrate()` leaves it: half-turn homings (present 2047 at
#: the middle pose), the pan and the wrist roll a whole turn, the others swept.
CALIBRATION = {
    "shoulder_pan": MotorCalibration(1, 0, 247, 0, 4095),
    "shoulder_lift": MotorCalibration(2, 0, -1353, 1060, 3010),
    "elbow_flex": MotorCalibration(3, 0, 947, 1100, 3000),
    "wrist_flex": MotorCalibration(4, 0, -153, 900, 3150),
    "wrist_roll": MotorCalibration(5, 0, 1447, 0, 4095),
    "gripper": MotorCalibration(6, 0, 547, 1990, 2950),
}
#: Where the arm stands, as steps the servos report before LeRobot writes its homing.
ACTUAL = {1: 1900, 2: 3300, 3: 1000, 4: 2300, 5: 700, 6: 1500}


@pytest.fixture
def sim(tmp_path: Path) -> Iterator[PtySimBus]:
    yield from running_sim(tmp_path, bus=SimBus())


def lerobot_follower(sim: PtySimBus, folder: Path) -> KochFollower:
    """LeRobot's own Koch follower (degrees mode) on the simulated bus, its calibration folder
    `folder`; its port waits for the simulator as Arena's test buses do."""
    config = KochFollowerConfig(
        port=str(sim.link), id="arm", calibration_dir=folder, use_degrees=True
    )
    robot = KochFollower(config)
    bus = robot.bus
    bus.port_handler = sim.paced_port(TEST_TIMEOUT_MARGIN)
    bus.sync_reader = dxl.GroupSyncRead(bus.port_handler, bus.packet_handler, 0, 0)
    bus.sync_writer = dxl.GroupSyncWrite(bus.port_handler, bus.packet_handler, 0, 0)
    return robot


def peek(sim: PtySimBus, register: reg.Register) -> dict[int, int]:
    """One register of every simulated servo."""
    with sim.paused() as bus:
        return {sid: servo.peek(register) for sid, servo in bus.servos.items()}


def lerobot_reads(sim: PtySimBus, folder: Path) -> dict[str, float]:
    """What LeRobot reads: its follower saves the calibration file, connects (which writes the
    calibration to the servos and configures them, as when the user keeps the file), then
    observes the arm."""
    return lerobot_observes(lerobot_follower(sim, folder), CALIBRATION, configure=True)


def _steps(robot: KochFollower) -> dict[str, float]:
    """Each goal as LeRobot reads it back (its goal register, normalized)."""
    return robot.bus.sync_read("Goal_Position")


# -- LeRobot's DynamixelMotorsBus takes the simulated bus for the real one -----------------------


def test_lerobot_koch_follower_connects_calibrates_moves_and_lets_go(
    sim: PtySimBus, tmp_path: Path
) -> None:
    place_arm(sim, ACTUAL)
    robot = lerobot_follower(sim, tmp_path)
    robot.calibration = dict(CALIBRATION)
    robot.bus.connect()  # pings every servo: ids and model numbers must match
    try:
        robot.bus.disable_torque()
        robot.bus.write_calibration(robot.calibration)
        assert robot.bus.read_calibration() == CALIBRATION  # the round trip through the servos
        robot.configure()  # EEPROM writes (operating modes) with torque off
        assert peek(sim, reg.OPERATING_MODE) == {1: 4, 2: 4, 3: 4, 4: 4, 5: 4, 6: 5}
        # Dynamixel: present = actual + Homing_Offset.
        assert peek(sim, reg.PRESENT_POSITION) == {
            sid: ACTUAL[sid] + CALIBRATION[NAMES[sid - 1]].homing_offset for sid in ACTUAL
        }
        robot.bus.enable_torque()
        with pytest.raises(RuntimeError):  # EEPROM is refused while torque is on
            robot.bus.write("Homing_Offset", "elbow_flex", 0)
        assert robot.bus.read("Homing_Offset", "elbow_flex", normalize=False) == 947
        goal = {"shoulder_pan.pos": 20.0, "elbow_flex.pos": -15.0, "gripper.pos": 40.0}
        robot.send_action(goal)
        # The servos move on the wall clock (about 60 ms here); the deadline is one only a
        # servo that never arrives reaches.
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            seen = robot.get_observation()
            if not any(seen[f"{name}.pos"] != value for name, value in _steps(robot).items()):
                break
        seen = robot.get_observation()
        assert abs(seen["shoulder_pan.pos"] - 20.0) <= STEP
        assert abs(seen["elbow_flex.pos"] + 15.0) <= STEP
        assert abs(seen["gripper.pos"] - 40.0) <= one_step(CALIBRATION, "gripper")
    finally:
        robot.disconnect()  # torque off, as LeRobot's follower leaves the arm
    assert set(peek(sim, reg.TORQUE_ENABLE).values()) == {0}


# -- Arena reads the servos as LeRobot does, through LeRobot's file -----------------------------


async def attach_koch(http: Any, sim: PtySimBus, calibration: str, **more: Any) -> Any:
    """Robot `arm` of type koch, its usb-slave on the simulated bus with `calibration`."""
    return await attach_arm(http, sim, "koch", calibration, **more)


@pytest.mark.parametrize("registers", ["written", "fresh"])
async def test_arena_reads_the_koch_as_lerobot_does(
    start_server: StartServer,
    sim: PtySimBus,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    registers: str,
) -> None:
    """`fresh`: the same arm, its servos' registers back to a new servo's (no homing, whole
    range): Arena applies the file's homing itself and still reads what LeRobot read."""
    place_arm(sim, ACTUAL)
    folder = tmp_path / "hf" / "robots" / "koch_follower"
    expected = await trio.to_thread.run_sync(lerobot_reads, sim, folder)
    assert (folder / "arm.json").is_file()
    if registers == "fresh":
        with sim.paused() as bus:
            for servo in bus.servos.values():
                present = servo.present
                servo.poke(reg.HOMING_OFFSET, 0)
                servo.poke(reg.MIN_POSITION_LIMIT, 0)
                servo.poke(reg.MAX_POSITION_LIMIT, 4095)
                servo.poke(reg.OPERATING_MODE, reg.OperatingMode.POSITION)
                servo.move_by_hand(present - CALIBRATION[NAMES[servo.servo_id - 1]].homing_offset)
    monkeypatch.setenv("HF_LEROBOT_CALIBRATION", str(tmp_path / "hf"))
    server = await start_server()
    async with server.client() as http:
        attached = await attach_koch(http, sim, "lerobot:arm")
        assert attached.status_code == 201, attached.text
        await eventually(lambda: all_read(http), what="joint states from the bus")
        read = await real_values(http)
    assert_reads_as(read, expected, CALIBRATION)


async def test_koch_driven_through_a_server_with_an_estop(
    start_server: StartServer, sim: PtySimBus, tmp_path: Path
) -> None:
    place_arm(sim, ACTUAL)
    path = tmp_path / "arm.json"
    await trio.to_thread.run_sync(lerobot_reads, sim, tmp_path)  # writes arm.json
    server = await start_server()
    async with server.client() as http:
        attached = await attach_koch(http, sim, str(path), estop="torque-off")
        assert attached.status_code == 201, attached.text
        await eventually(lambda: joined(http), what="the arm joined")
        assert set(peek(sim, reg.TORQUE_ENABLE).values()) == {1}
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
        # The goals LeRobot itself would write for those values (its `_unnormalize`), in the
        # servo's frame (present = actual + Homing_Offset: no wrap, many turns).
        pan, grip = CALIBRATION["shoulder_pan"], CALIBRATION["gripper"]
        pan_goal = 12 * 4095 / 360 + (pan.range_min + pan.range_max) / 2
        grip_goal = 0.6 * (grip.range_max - grip.range_min) + grip.range_min

        def goals_written() -> bool:
            goals = peek(sim, reg.GOAL_POSITION)
            return abs(goals[1] - pan_goal) <= 1 and abs(goals[6] - grip_goal) <= 1

        await eventually(goals_written, what="LeRobot's own goals for those values")
        # Profile_Velocity: the robot's velocity limit, in the servo's 0.229 rpm units.
        assert set(peek(sim, reg.PROFILE_VELOCITY).values()) == {round(180 / 6 / 0.229)}
        stopped = await http.post("/api/robots/arm/estop", json={"reason": "test"})
        assert stopped.status_code == 200

        def limp() -> bool:
            return set(peek(sim, reg.TORQUE_ENABLE).values()) == {0}

        await eventually(limp, what="every servo's torque off")
        held = peek(sim, reg.GOAL_POSITION)  # goal = present, written before torque went off
        refused = await http.put(
            "/api/robots/arm/joints", json={"joints": [{"name": "shoulder_pan", "value": -20}]}
        )
        assert refused.status_code >= 400
        assert (await http.get("/api/robots/arm/status")).json()["state"] == "estopped"
        assert peek(sim, reg.GOAL_POSITION) == held  # nothing new was sent


@pytest.mark.parametrize(
    ("change", "words"),
    [
        ({"elbow_flex": {"id": 7}}, ["elbow_flex", "id 7"]),
        ({"gripper": {"homing_offset": 2_000_000}}, ["gripper", "homing_offset 2000000"]),
        ({"wrist_flex": {"range_max": 5000}}, ["wrist_flex", "range_max 5000"]),
    ],
)
async def test_a_koch_file_that_does_not_fit_is_refused_before_any_torque(
    start_server: StartServer,
    sim: PtySimBus,
    tmp_path: Path,
    change: dict[str, dict[str, int]],
    words: list[str],
) -> None:
    data = {name: vars(cal) for name, cal in CALIBRATION.items()}
    for name, fields in change.items():
        data[name] = {**data[name], **fields}
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(data))
    server = await start_server()
    async with server.client() as http:
        reply = await attach_koch(http, sim, str(path))
        assert reply.status_code == 422, reply.text
        error = reply.json()["error"]
        assert error["code"] == "INVALID_CONFIG"
        for word in words:
            assert word in error["message"]
        assert (await http.get("/api/robots/arm")).json()["slaves"] == []
    with sim.paused() as bus:
        assert [s.torque_enables for s in bus.servos.values()] == [0] * 6  # never on


async def test_an_arena_calibration_on_servos_that_count_turns_is_refused(
    start_server: StartServer, sim: PtySimBus, tmp_path: Path
) -> None:
    """A servo reading outside one turn (its Homing_Offset set by LeRobot) would get goals a
    turn away through Arena's own calibration: the attach is refused before any torque."""
    with sim.paused() as bus:
        bus.servo(2).poke(reg.HOMING_OFFSET, 3000)  # present = 2048 + 3000
    server = await start_server(calibration_dir=str(tmp_path / "cal"))
    async with server.client() as http:
        reply = await attach_koch(http, sim, "arm")
        assert reply.status_code == 422, reply.text
        assert "lerobot:ID" in reply.json()["error"]["message"]
        assert (await http.get("/api/robots/arm")).json()["slaves"] == []
    with sim.paused() as bus:
        assert [s.torque_enables for s in bus.servos.values()] == [0] * 6  # never on


# -- the codec, against the SDK's own arithmetic -----------------------------------------------


def test_crc_and_stuffing_match_the_sdk() -> None:
    handler = dxl.PacketHandler(2.0)
    params = bytes([0x74, 0x00, 0x04, 0x00, 0xFF, 0xFF, 0xFD, 0x01])
    frame = packets.encode(3, packets.Instruction.WRITE, params)
    assert b"\xff\xff\xfd\xfd" in frame[7:]  # the body's header-like bytes got their stuffing
    assert handler.updateCRC(0, list(frame[:-2]), len(frame) - 2) == int.from_bytes(
        frame[-2:], "little"
    )
    (parsed,) = packets.PacketParser().feed(b"\x00\xff" + frame)
    assert parsed == packets.Packet(3, packets.Instruction.WRITE, params)
    broken = frame[:-1] + bytes([frame[-1] ^ 1])
    (corrupt,) = packets.PacketParser().feed(broken)
    assert isinstance(corrupt, packets.Corrupt) and corrupt.servo_id == 3


def test_sim_bus_command_simulates_the_koch(tmp_path: Path) -> None:
    """`arena sim-bus --robot-type koch`: a Dynamixel bus whose servos answer Arena's own
    Dynamixel bus with the Koch's model numbers."""
    from arena.dynamixel.bus import DynamixelBus

    link = tmp_path / "ttyKOCH"
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    command = [sys.executable, "-m", "arena.cli", "sim-bus", "--link", str(link)]
    server = subprocess.Popen(
        [*command, "--robot-type", "koch"], stdout=subprocess.PIPE, text=True, env=env
    )
    try:
        assert server.stdout is not None
        banner = server.stdout.readline()
        assert "dynamixel bus: servos 1,2,3,4,5,6" in banner
        bus = DynamixelBus(str(link), timeout_margin=30.0)  # another process: a patient margin
        bus.open()
        try:
            assert [bus.ping(sid) for sid in range(1, 7)] == [1060, 1060, 1200, 1200, 1200, 1200]
        finally:
            bus.close()
    finally:
        server.terminate()
        server.wait(timeout=10)
    assert server.returncode == 0


async def test_a_servo_of_another_model_is_refused(
    start_server: StartServer, tmp_path: Path
) -> None:
    xl430, xl330 = reg.MODELS["xl430-w250"], reg.MODELS["xl330-m288"]
    wrong = SimBus({1: xl430, 2: xl430, 3: xl430, 4: xl330, 5: xl330, 6: xl330})
    with sim_on(tmp_path, bus=wrong) as sim:
        server = await start_server(calibration_dir=str(tmp_path / "cal"))
        async with server.client() as http:
            reply = await attach_koch(http, sim, "arm")
            assert reply.status_code == 422, reply.text
            error = reply.json()["error"]
            assert error["code"] == "SERVO_WRONG_MODEL"
            assert "Servo 3 is model 1060" in error["message"]
            assert "XL330-M288" in error["message"]
        with sim.paused() as bus:
            assert [s.torque_enables for s in bus.servos.values()] == [0] * 6  # never on


#: The Koch leader as LeRobot's `KochLeader` calibrates it: XL330-M077 servos, the elbow's
#: Drive_Mode inverted (drive_mode 1), homing 0 here.
LEADER_CALIBRATION = {
    "shoulder_pan": MotorCalibration(1, 0, 0, 0, 4095),
    "shoulder_lift": MotorCalibration(2, 0, 0, 1000, 3000),
    "elbow_flex": MotorCalibration(3, 1, 0, 1200, 3000),
    "wrist_flex": MotorCalibration(4, 0, 0, 1000, 3000),
    "wrist_roll": MotorCalibration(5, 0, 0, 0, 4095),
    "gripper": MotorCalibration(6, 0, 0, 2000, 2800),
}
#: The leader's pose as its servos report it once calibrated.
LEADER_PRESENT = {1: 2200, 2: 2100, 3: 2000, 4: 1900, 5: 2048, 6: 2400}


def lerobot_calibrates_the_leader(sim: PtySimBus, folder: Path) -> None:
    """LeRobot's own `KochLeader` writes its drive mode and calibration to the servos and its
    file to `folder`."""
    from lerobot.teleoperators.koch_leader import KochLeader, KochLeaderConfig

    leader = KochLeader(KochLeaderConfig(port=str(sim.link), id="arm", calibration_dir=folder))
    bus = leader.bus
    bus.port_handler = sim.paced_port(TEST_TIMEOUT_MARGIN)
    bus.sync_reader = dxl.GroupSyncRead(bus.port_handler, bus.packet_handler, 0, 0)
    bus.sync_writer = dxl.GroupSyncWrite(bus.port_handler, bus.packet_handler, 0, 0)
    bus.connect()  # its servos are XL330-M077s: a model check of the follower's would fail
    try:
        bus.disable_torque()
        bus.write("Drive_Mode", "elbow_flex", 1)
        bus.write_calibration(dict(LEADER_CALIBRATION))
        leader.calibration = dict(LEADER_CALIBRATION)
        leader._save_calibration()
    finally:
        bus.disconnect()


def leader_degrees(name: str, present: int) -> float:
    """What LeRobot reads (degrees mode) for the leader's joint `name` at `present`."""
    cal = LEADER_CALIBRATION[name]
    if name == "gripper":
        return (present - cal.range_min) / (cal.range_max - cal.range_min) * 100
    return (present - (cal.range_min + cal.range_max) / 2) * 360 / 4095


async def test_the_koch_follower_mirrors_the_koch_leader(
    start_server: StartServer, sim: PtySimBus, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    m077 = reg.MODELS["xl330-m077"]
    place_arm(sim, ACTUAL)
    await trio.to_thread.run_sync(lerobot_reads, sim, tmp_path / "hf" / "robots" / "koch_follower")
    with sim_on(tmp_path / "leader", bus=SimBus(dict.fromkeys(range(1, 7), m077))) as leader:
        folder = tmp_path / "hf" / "teleoperators" / "koch_leader"
        await trio.to_thread.run_sync(lerobot_calibrates_the_leader, leader, folder)
        with leader.paused() as bus:
            assert bus.servo(3).peek(reg.DRIVE_MODE) == 1
            for sid, present in LEADER_PRESENT.items():
                bus.servo(sid).move_by_hand(present)
        monkeypatch.setenv("HF_LEROBOT_CALIBRATION", str(tmp_path / "hf"))
        server = await start_server()
        async with server.client() as http:
            attached = await attach_koch(http, sim, "lerobot:arm")
            assert attached.status_code == 201, attached.text
            await eventually(lambda: joined(http), what="the follower joined")
            body = {"type": "usb-master", "port": str(leader.link), "calibration": "lerobot:arm"}
            master = await http.post("/api/robots/arm/master", json=body)
            assert master.status_code == 201, master.text
            wanted = {
                name: leader_degrees(name, LEADER_PRESENT[sid + 1])
                for sid, name in enumerate(NAMES)
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


def test_offsets_stay_in_the_file_for_servos_that_count_turns() -> None:
    from arena.dynamixel.bus import DYNAMIXEL
    from arena.protocol.errors import ArenaError
    from arena.servo.calibration import homing_offset_register

    with pytest.raises(ArenaError, match="count turns"):
        homing_offset_register(100, 0, DYNAMIXEL)


def test_calibrate_refuses_at_once_what_a_koch_cannot_keep(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    from arena import cli

    out = tmp_path / "never.json"
    command = ["calibrate", "--robot-type", "koch", "--port", "/nonexistent", "--out", str(out)]
    assert cli.main([*command, "--write-homing"]) == 2
    assert "count turns" in capsys.readouterr().err
    assert not out.exists()


def test_calibrate_format_lerobot_reads_zero_at_rest_in_lerobots_koch(
    sim: PtySimBus, tmp_path: Path
) -> None:
    """`arena calibrate --format lerobot` on a fresh Koch whose servos hold other homings;
    LeRobot's KochFollower loads the file, writes it to the servos and reads the rest pose as
    0 (the homing puts it at step 2048 exactly: these servos count turns)."""
    from arena.robot.model import load_robot_model
    from arena.servo.terminal import calibrate_interactively
    from tests.hardware import open_test_bus

    koch = load_robot_model("koch")
    with sim.paused() as bus:
        for sid, servo in bus.servos.items():
            servo.poke(reg.HOMING_OFFSET, 5000 * (sid % 2) - 300)  # turns away, either side
            servo.move_by_hand(servo.present)  # (Present_Position anew; the horn stays)
        rest = {sid: servo.present for sid, servo in bus.servos.items()}
    out = tmp_path / "robots" / "koch_follower" / "arm.json"
    bus = open_test_bus(str(sim.link))
    bus.open()
    try:  # Enter at once: at rest, then no joint swept
        calibrate_interactively(
            bus,
            {j.name: j.servo_id for j in koch.joints},
            out,
            robot_type="koch",
            lerobot_model=koch,
            ask=lambda _: "",
            say=lambda _: None,
        )
    finally:
        bus.close()
    data = json.loads(out.read_text())
    assert list(data) == list(NAMES)
    for name, sid in zip(NAMES, range(1, 7), strict=True):  # rest - register + homing = 2048
        assert rest[sid] - (5000 * (sid % 2) - 300) + data[name]["homing_offset"] == 2048
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
        assert abs(read[f"{name}.pos"]) <= STEP, (name, read)
    assert read["gripper.pos"] == pytest.approx(0.0, abs=one_step(CALIBRATION, "gripper"))


async def test_the_koch_twin_follows_its_commands(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    """The physics twin of the koch type (MuJoCo on its URDF: Menagerie's kinematics and
    masses, Arena's box meshes) follows a command on every joint, gripper included."""
    pytest.importorskip("mujoco")
    from arena.drivers.physics import PhysicsSettings, PhysicsSlave
    from arena.robot.motion import Command

    robot = await manager.create_robot("koch", robot_id="twin")
    slave = PhysicsSlave(PhysicsSettings(realtime=False))
    await robot.attach_slave(slave)
    await trio.sleep(1.0)
    goal = {"shoulder_pan": 30.0, "elbow_flex": -20.0, "wrist_roll": 45.0, "gripper": 60.0}
    assert (await robot.command(Command.of(goal))).accepted
    await trio.sleep(3.0)
    real = {j.name: j.real_value for j in robot.snapshot().joints}
    for name, value in goal.items():
        seen = real[name]
        assert seen is not None and abs(seen - value) < 3.0, (name, seen)
    assert slave.contacts_reported == []


def test_hardware_errors_reach_the_health_monitor_as_faults(sim: PtySimBus) -> None:
    """A Dynamixel says a hardware error with its status packets' alert bit; the bus reads
    Hardware_Error_Status with the telemetry and the monitor names the fault and the servo."""
    from arena.protocol.errors import ErrorCode, Severity
    from arena.servo.health import HealthMonitor
    from arena.servo.interface import FaultBit
    from tests.hardware import open_test_bus

    with sim.paused() as bus:
        bus.servo(4).faults.error_bits = FaultBit.OVERHEAT | FaultBit.VOLTAGE
    dynamixel = open_test_bus(str(sim.link))
    dynamixel.open()
    try:
        telemetry, result = dynamixel.read_telemetry(range(1, 7))
    finally:
        dynamixel.close()
    assert telemetry.voltages == {1: 12.0, 2: 12.0, 3: 5.0, 4: 5.0, 5: 5.0, 6: 5.0}
    assert result.errors[4] == FaultBit.OVERHEAT | FaultBit.VOLTAGE
    assert {sid for sid, bits in result.errors.items() if bits} == {4}
    faults = HealthMonitor(range(1, 7)).on_read(result)
    assert {(f.code, f.severity, f.servo_id) for f in faults} == {
        (ErrorCode.SERVO_OVERHEAT, Severity.CRITICAL, 4),
        (ErrorCode.SERVO_VOLTAGE, Severity.ERROR, 4),
    }


def test_prepare_refuses_a_servo_whose_mode_read_is_lost(sim: PtySimBus) -> None:
    """A servo left in velocity mode whose reply to the mode read is lost must not be skipped:
    torque would come on with its Goal_Velocity still in RAM."""
    from arena.protocol.errors import ArenaError, ErrorCode
    from tests.hardware import open_test_bus

    with sim.paused() as bus:
        bus.servo(3).poke(reg.OPERATING_MODE, reg.OperatingMode.VELOCITY)
        bus.servo(3).faults.drop = 1
    dynamixel = open_test_bus(str(sim.link))
    dynamixel.open()
    try:
        with pytest.raises(ArenaError) as refused:
            dynamixel.prepare(range(1, 7))
        assert refused.value.code is ErrorCode.SERVO_TIMEOUT
        assert "[3]" in refused.value.message
        dynamixel.prepare(range(1, 7))  # answering again: switched, and read back
    finally:
        dynamixel.close()
    assert peek(sim, reg.OPERATING_MODE)[3] == reg.OperatingMode.POSITION
    with sim.paused() as bus:
        assert [s.torque_enables for s in bus.servos.values()] == [0] * 6


def test_prepare_refuses_a_servo_that_keeps_its_velocity_mode(
    sim: PtySimBus, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The mode is read back after the change: a servo that acknowledged the write but still
    reads velocity mode is refused, naming it."""
    from arena.protocol.errors import ArenaError, ErrorCode
    from tests.hardware import open_test_bus

    with sim.paused() as bus:
        bus.servo(5).poke(reg.OPERATING_MODE, reg.OperatingMode.VELOCITY)
        bus.servo(5).poke(reg.GOAL_VELOCITY, 200)
    dynamixel = open_test_bus(str(sim.link))
    write = dynamixel.write  # type: ignore[attr-defined]

    def forgetful(servo_id: int, register: reg.Register, value: int) -> None:
        # The servo's firmware acknowledges the mode write and keeps its mode.
        write(servo_id, register, value)
        if register is reg.OPERATING_MODE and servo_id == 5:
            with sim.paused() as bus:
                bus.servo(5).poke(reg.OPERATING_MODE, reg.OperatingMode.VELOCITY)

    monkeypatch.setattr(dynamixel, "write", forgetful)
    dynamixel.open()
    try:
        with pytest.raises(ArenaError) as refused:
            dynamixel.prepare(range(1, 7))
    finally:
        dynamixel.close()
    assert refused.value.code is ErrorCode.INVALID_CONFIG
    assert "[5]" in refused.value.message
    with sim.paused() as bus:
        assert [s.torque_enables for s in bus.servos.values()] == [0] * 6


async def test_a_leader_of_a_model_outside_the_family_is_refused(
    start_server: StartServer, tmp_path: Path
) -> None:
    """A leader may be any 4096-step model of its family (the Koch leader's XL330-M077), but
    not a servo the family's table does not know (an MX-28, model 30): `SERVO_WRONG_MODEL`."""
    m077 = reg.MODELS["xl330-m077"]
    models = {**dict.fromkeys(range(1, 7), m077), 4: 30}
    with sim_on(tmp_path / "leader", bus=SimBus(models)) as leader:
        server = await start_server(calibration_dir=str(tmp_path / "cal"))
        async with server.client() as http:
            made = await http.post("/api/robots", json={"id": "arm", "robot_type": "koch"})
            assert made.status_code == 201, made.text
            body = {"type": "usb-master", "port": str(leader.link)}
            reply = await http.post("/api/robots/arm/master", json=body)
            assert reply.status_code == 422, reply.text
            error = reply.json()["error"]
            assert error["code"] == "SERVO_WRONG_MODEL"
            assert "Servo 4 is model 30" in error["message"]
            assert "XL330-M077 (1190)" in error["message"]


async def test_a_joint_turned_a_turn_away_is_refused_torque_at_attach(
    start_server: StartServer, sim: PtySimBus, tmp_path: Path
) -> None:
    """LeRobot's file, a joint turned by hand a whole turn further while limp (its servo counts
    turns): its goal, clamped into the file's range, would be a turn away. The attach is
    refused, naming the servo and its reading, before any torque."""
    place_arm(sim, ACTUAL)
    path = tmp_path / "arm.json"
    await trio.to_thread.run_sync(lerobot_reads, sim, tmp_path)  # writes arm.json
    with sim.paused() as bus:
        lift = bus.servo(2)
        turned = lift.present + 4096
        lift.move_by_hand(turned)
        before = [s.torque_enables for s in bus.servos.values()]
    server = await start_server()
    async with server.client() as http:
        reply = await attach_koch(http, sim, str(path))
        assert reply.status_code == 422, reply.text
        error = reply.json()["error"]
        assert error["code"] == "SERVO_OUT_OF_RANGE"
        lift_range = CALIBRATION["shoulder_lift"]
        frame = f"{lift_range.range_min - 256}..{lift_range.range_max + 256}"
        assert f"Servo 2 reads {turned} (its frame {frame})" in error["message"]
    with sim.paused() as bus:
        assert [s.torque_enables for s in bus.servos.values()] == before  # never on
        assert bus.servo(2).present == turned


async def test_a_reset_refuses_torque_to_a_joint_turned_a_turn_away(
    manager: RobotManager, sim: PtySimBus
) -> None:
    """Arena's own calibration (one turn, 0..4095) and a torque-off e-stop: a joint turned a
    whole turn by hand while limp keeps its torque off at the reset, a critical fault names
    it, and the robot stays stopped; turned back, the next reset brings torque back."""
    from arena.protocol.errors import ErrorCode, Severity
    from arena.robot.model import load_robot_model
    from arena.robot.safety import Mode
    from tests.hardware import fault_of, usb_slave, wait_joined

    def torque() -> list[int]:
        return list(peek(sim, reg.TORQUE_ENABLE).values())

    robot = await manager.create_robot("koch", robot_id="arm")
    with robot.subscribe() as events:
        await robot.attach_slave(usb_slave(sim, load_robot_model("koch"), estop="torque-off"))
        await eventually(lambda: all(torque()), what="torque on")
        await wait_joined(robot)
        await robot.estop("test")
        await eventually(lambda: not any(torque()), what="limp")
        with sim.paused() as bus:
            elbow = bus.servo(3)
            back = elbow.present
            elbow.move_by_hand(back + 4096)
            before = [s.torque_enables for s in bus.servos.values()]
        events.drain()
        await robot.reset()
        fault = await fault_of(events, ErrorCode.SERVO_OUT_OF_RANGE, "the refusal's fault")
        assert fault.severity is Severity.CRITICAL
        assert f"Servo 3 reads {back + 4096} (its frame 0..4095)" in fault.message
        assert robot.snapshot().mode is Mode.ESTOPPED
        with sim.paused() as bus:
            assert [s.torque_enables for s in bus.servos.values()] == before
            assert bus.servo(3).present == back + 4096  # not sent a turn back
            bus.servo(3).move_by_hand(back)
        await robot.reset()
        await eventually(lambda: all(torque()), what="torque back")
        assert robot.snapshot().mode is not Mode.ESTOPPED


async def test_a_reading_that_leaves_the_frame_under_torque_stops_the_robot(
    manager: RobotManager, sim: PtySimBus
) -> None:
    """A servo with torque that reads a turn away (its Homing_Offset changed under it) is a
    critical fault: the robot e-stops, and the e-stop's hold leaves that servo limp at goal =
    present while the others keep their torque."""
    from arena.protocol.errors import ErrorCode, Severity
    from arena.robot.model import load_robot_model
    from arena.robot.safety import Mode
    from tests.hardware import fault_of, usb_slave, wait_joined

    robot = await manager.create_robot("koch", robot_id="arm")
    with robot.subscribe() as events:
        await robot.attach_slave(usb_slave(sim, load_robot_model("koch")))
        await eventually(lambda: all(peek(sim, reg.TORQUE_ENABLE).values()), what="torque on")
        await wait_joined(robot)
        with sim.paused() as bus:
            bus.servo(4).poke(reg.HOMING_OFFSET, 4096)
        fault = await fault_of(events, ErrorCode.SERVO_OUT_OF_RANGE, "the out-of-frame fault")
        assert fault.severity is Severity.CRITICAL and fault.joint == "wrist_flex"
        assert "(its frame 0..4095)" in fault.message
        await eventually(lambda: robot.snapshot().mode is Mode.ESTOPPED, what="the e-stop")

        def wrist_limp_others_held() -> bool:
            torque = peek(sim, reg.TORQUE_ENABLE)
            return torque == {1: 1, 2: 1, 3: 1, 4: 0, 5: 1, 6: 1}

        await eventually(wrist_limp_others_held, what="servo 4 limp, the others held")
        with sim.paused() as bus:
            wrist = bus.servo(4)
            # goal = present (a turn away) was written: not sent back a whole turn
            assert wrist.peek(reg.GOAL_POSITION) > 4095 and wrist.present > 4095


def test_a_late_reply_to_an_earlier_read_is_not_taken_for_a_position(sim: PtySimBus) -> None:
    """A servo's telemetry reply that comes after its read timed out, in the window of the next
    read, is not that read's answer: decoded as a position it is step 0, half a turn away (a
    newcomer saw every joint of a busy Koch read -180 degrees now and then)."""
    from tests.hardware import open_test_bus

    dynamixel = open_test_bus(str(sim.link))
    dynamixel.open()
    try:
        handler = dynamixel._handler  # the SDK's packet handler, this open's
        receive = handler.rxPacket
        # A whole status packet from servo 6 carrying a telemetry block (all zeros), as the
        # SDK would hand it over had it come on the wire just before the real replies.
        late = [0xFF, 0xFF, 0xFD, 0x00, 6, 0, 0, 0x55, 0, *([0] * reg.TELEMETRY_SIZE), 0, 0]
        pending = [late]

        def late_first(*args: Any) -> Any:
            return (pending.pop(), 0) if pending else receive(*args)  # 0: COMM_SUCCESS

        handler.rxPacket = late_first
        positions, result = dynamixel.read_positions(range(1, 7))
    finally:
        dynamixel.close()
    assert not pending, "the late packet was not read first"
    assert positions == peek(sim, reg.PRESENT_POSITION), positions
    assert result.missing == [] and result.corrupt == []
