"""Calibration over REST and hardware attach errors, on a real server and a simulated bus."""

from __future__ import annotations

import errno
from collections.abc import Awaitable, Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import serial

from arena.feetech import registers as reg
from arena.feetech.bus import ADAPTERS
from arena.protocol.errors import ArenaError, ErrorCode
from arena.servo.calibration import Calibration
from arena.servo.ports import PortInfo, find_adapter, port_error
from arena.servo.sim_pty import PtySimBus
from tests.conftest import RunningServer, eventually
from tests.hardware import running_sim, servo_goals, servo_torque

StartServer = Callable[..., Awaitable[RunningServer]]


@pytest.fixture
def sim(tmp_path: Path) -> Iterator[PtySimBus]:
    yield from running_sim(tmp_path)


async def arm_on_bus(start_server: StartServer, sim: PtySimBus, tmp_path: Path) -> RunningServer:
    server = await start_server(calibration_dir=str(tmp_path / "calibration"))
    async with server.client() as http:
        assert (await http.post("/api/robots", json={"id": "arm"})).status_code == 201
        attached = await http.post(
            "/api/robots/arm/slaves", json={"type": "usb-slave", "port": str(sim.link)}
        )
        assert attached.status_code == 201, attached.text
    await eventually(lambda: all(servo_torque(sim).values()), what="torque on")
    return server


def real_values(joints: list[dict[str, Any]]) -> dict[str, float]:
    return {j["name"]: j["real_value"] for j in joints}


async def test_calibration_workflow(
    start_server: StartServer, sim: PtySimBus, tmp_path: Path
) -> None:
    server = await arm_on_bus(start_server, sim, tmp_path)
    async with server.client() as http:
        status = (await http.get("/api/robots/arm/calibration")).json()
        assert status["calibrated"] is False and status["session"] is None
        started = await http.post("/api/robots/arm/calibration/start")
        assert started.status_code == 200, started.text
        assert started.json()["session"]["phase"] == "posing"
        await eventually(lambda: not any(servo_torque(sim).values()), what="torque off")
        # The user poses the arm like the twin (every joint at 0 degrees): here the horns sit
        # at arbitrary raw steps, as they do on a freshly assembled arm.
        rest_raw = {1: 3000, 2: 1100, 3: 2500, 4: 700, 5: 3900, 6: 2048}
        with sim.paused() as bus:
            for sid, raw in rest_raw.items():
                bus.servo(sid).move_by_hand(raw)
        captured = await http.post("/api/robots/arm/calibration/capture")
        assert captured.json()["session"]["phase"] == "range"
        # Then each joint through its range.
        for delta in (-400, 300, 0):
            with sim.paused() as bus:
                bus.servo(1).move_by_hand(rest_raw[1] + delta)
            await eventually(
                lambda d=delta: (
                    abs(real_values(_joints(server)).get("Rotation", 1e9) - d * 360 / 4096) < 0.2
                ),
                what="the reading of the moved joint",
            )
        finished = await http.post("/api/robots/arm/calibration/finish", json={"writeHoming": True})
        assert finished.status_code == 200, finished.text
        body = finished.json()
        rotation = body["calibration"]["joints"]["Rotation"]
        assert rotation["offset"] == 0  # moved into the servo
        assert rotation["min_degrees"] == pytest.approx(-400 * 360 / 4096, abs=0.01)
        assert rotation["max_degrees"] == pytest.approx(300 * 360 / 4096, abs=0.01)
        assert body["calibration"]["homing_in_servos"] is True
        await eventually(lambda: all(servo_torque(sim).values()), what="torque back on")
        with sim.paused() as bus:
            assert bus.servo(1).peek(reg.HOMING_OFFSET) == 3000 - 2048
            assert bus.servo(1).peek(reg.GOAL_POSITION) == bus.servo(1).present  # no jump
        # The rest pose now reads as the twin's zeros, and the file is on disk.
        await eventually(
            lambda: all(abs(v) < 0.1 for v in real_values(_joints(server)).values()),
            what="calibrated zeros",
        )
        stored = Calibration.load(tmp_path / "calibration" / "arm.json")
        assert stored.joints["Rotation"].max_degrees == rotation["max_degrees"]
        # Commands use it, clamped to the captured range.
        moved = await http.put(
            "/api/robots/arm/joints", json={"joints": [{"name": "Rotation", "value": 40}]}
        )
        assert moved.status_code == 200, moved.text
        limit = round(300 * 360 / 4096 * 4096 / 360)
        await eventually(lambda: servo_goals(sim)[1] == 2048 + limit, what="clamped goal")


def _joints(server: RunningServer, robot_id: str = "arm") -> list[dict[str, Any]]:
    from arena.server import convert

    robot = server.app.manager.get(robot_id)
    data: list[dict[str, Any]] = [
        {"name": j.name, "real_value": j.real_value} for j in convert.joint_states(robot).data
    ]
    return data


async def test_calibration_errors_and_cancel(
    start_server: StartServer, sim: PtySimBus, tmp_path: Path
) -> None:
    server = await arm_on_bus(start_server, sim, tmp_path)
    async with server.client() as http:
        wrong_order = await http.post("/api/robots/arm/calibration/capture")
        assert (wrong_order.status_code, wrong_order.json()["error"]["code"]) == (
            409,
            "CALIBRATION_STATE",
        )
        bad = await http.post("/api/robots/arm/calibration/start", json={"rest": {"Nope": 1}})
        assert bad.json()["error"]["code"] == "UNKNOWN_JOINT"
        huge = await http.post("/api/robots/arm/calibration/start", json={"rest": {"Pitch": 1e9}})
        assert huge.json()["error"]["code"] == "INVALID_BODY"
        await http.post("/api/robots", json={"id": "plain"})
        none = await http.get("/api/robots/plain/calibration")
        assert (none.status_code, none.json()["error"]["code"]) == (404, "NO_HARDWARE")
        # While a master drives the robot, calibration is refused.
        await http.post(
            "/api/robots/arm/master", json={"type": "mock-sequence", "autoStart": False}
        )
        busy = await http.post("/api/robots/arm/calibration/start")
        assert (busy.status_code, busy.json()["error"]["code"]) == (409, "MASTER_ACTIVE")
        await http.delete("/api/robots/arm/master")
        assert (await http.post("/api/robots/arm/calibration/start")).status_code == 200
        again = await http.post("/api/robots/arm/calibration/start")
        assert again.json()["error"]["code"] == "CALIBRATION_STATE"
        with sim.paused() as bus:
            bus.servo(1).move_by_hand(3000)
        await http.post("/api/robots/arm/calibration/capture")
        cancelled = await http.post("/api/robots/arm/calibration/cancel")
        assert cancelled.json()["session"] is None
        assert cancelled.json()["calibration"]["joints"]["Rotation"]["offset"] == 0
        assert not (tmp_path / "calibration" / "arm.json").exists()
        await eventually(lambda: all(servo_torque(sim).values()), what="torque back on")


async def test_port_problems_say_what_to_do(
    start_server: StartServer, sim: PtySimBus, tmp_path: Path
) -> None:
    server = await start_server(calibration_dir=str(tmp_path / "calibration"))
    async with server.client() as http:
        await http.post("/api/robots", json={"id": "arm"})

        async def attach(**config: Any) -> tuple[int, dict[str, str]]:
            reply = await http.post("/api/robots/arm/slaves", json={"type": "usb-slave", **config})
            return reply.status_code, reply.json().get("error", {})

        status, error = await attach(port=str(tmp_path / "ttyUSB9"))
        assert (status, error["code"]) == (404, "PORT_NOT_FOUND")
        assert "plugged in" in error["message"]
        (tmp_path / "notatty").write_text("")
        status, error = await attach(port=str(tmp_path / "notatty"))
        assert (status, error["code"]) == (422, "INVALID_CONFIG")
        holder = serial.Serial(str(sim.link), 1_000_000, exclusive=True)
        try:
            status, error = await attach(port=str(sim.link))
        finally:
            holder.close()
        assert (status, error["code"]) == (409, "PORT_BUSY")
        assert "another program" in error["message"]
        with sim.paused() as bus:
            bus.servo(4).faults.silent = True
        status, error = await attach(port=str(sim.link))
        assert (status, error["code"]) == (504, "SERVO_TIMEOUT")
        assert "Servo 4" in error["message"]
        status, error = await attach(port=str(sim.link), rate=0)
        assert (status, error["code"]) == (422, "INVALID_BODY")
        status, error = await attach(port=str(sim.link), calibration="../etc/x")
        assert (status, error["code"]) == (422, "INVALID_BODY")
        robot = (await http.get("/api/robots/arm")).json()
        assert robot["slaves"] == []  # nothing half-attached


async def test_a_port_this_server_holds_is_said_to_be_held_by_it(
    start_server: StartServer, sim: PtySimBus, tmp_path: Path
) -> None:
    """A second usb-slave on a port an arm of this server holds: PORT_BUSY naming the robot
    that holds it, not "another program"; once that one is detached, the port is free."""
    server = await arm_on_bus(start_server, sim, tmp_path)
    async with server.client() as http:
        assert (await http.post("/api/robots", json={"id": "arm2"})).status_code == 201
        body = {"type": "usb-slave", "port": str(sim.link)}
        refused = await http.post("/api/robots/arm2/slaves", json=body)
        error = refused.json()["error"]
        assert (refused.status_code, error["code"]) == (409, "PORT_BUSY")
        assert (
            "this server" in error["message"] and "the usb-slave of robot 'arm'" in error["message"]
        )
        assert "another program" not in error["message"]
        [slave] = (await http.get("/api/robots/arm")).json()["slaves"]
        detached = await http.delete(f"/api/robots/arm/slaves/{slave['id']}")
        assert detached.is_success, detached.text
        attached = await http.post("/api/robots/arm2/slaves", json=body)
        assert attached.status_code == 201, attached.text


def test_permission_denied_is_explained() -> None:
    error = port_error("/dev/ttyUSB0", serial.SerialException(errno.EACCES, "Permission denied"))
    assert error.code is ErrorCode.PORT_PERMISSION_DENIED
    assert "dialout" in error.message


def test_adapter_auto_detection() -> None:
    ch340 = PortInfo("/dev/ttyUSB0", 0x1A86, 0x7523)
    ch343 = PortInfo("/dev/ttyACM0", 0x1A86, 0x55D3)
    other = PortInfo("/dev/ttyS0")
    assert find_adapter(ADAPTERS, [other, ch340]) == "/dev/ttyUSB0"
    assert find_adapter(ADAPTERS, [ch343]) == "/dev/ttyACM0"
    with pytest.raises(ArenaError) as none:
        find_adapter(ADAPTERS, [other])
    assert "/dev/ttyS0" in none.value.message and "1a86:7523" in none.value.message
    with pytest.raises(ArenaError) as several:
        find_adapter(ADAPTERS, [ch340, ch343])
    assert "/dev/ttyUSB0" in several.value.message and "/dev/ttyACM0" in several.value.message


async def test_the_so101_gripper_reads_and_moves_in_percent_through_arenas_calibration(
    start_server: StartServer, sim: PtySimBus, tmp_path: Path
) -> None:
    # The robot type says 0 (closed) to 100 (open), as LeRobot and the export do: Arena's own
    # calibration reads it so too, 100 at the end of its captured range, not in degrees.
    server = await start_server(calibration_dir=str(tmp_path / "calibration"))
    async with server.client() as http:
        body = {"id": "arm", "robot_type": "so-101"}
        assert (await http.post("/api/robots", json=body)).status_code == 201
        slave = {"type": "usb-slave", "port": str(sim.link)}
        assert (await http.post("/api/robots/arm/slaves", json=slave)).status_code == 201
        await eventually(lambda: all(servo_torque(sim).values()), what="torque on")

        def gripper() -> float:
            return real_values(_joints(server, "arm"))["gripper"]

        # Uncalibrated, the gripper's span (110 degrees of jaw) is its 0..100.
        span_steps = round(110.0 * 4096 / 360)
        await http.post("/api/robots/arm/calibration/start")
        await eventually(lambda: not any(servo_torque(sim).values()), what="torque off")
        with sim.paused() as bus:
            bus.servo(6).move_by_hand(2048 + span_steps // 2)
        await eventually(lambda: abs(gripper() - 50.0) < 0.2, what="half open: 50")
        # Posed like the twin's rest (the gripper closed: 0), then opened and closed fully.
        rest = 1500
        with sim.paused() as bus:
            bus.servo(6).move_by_hand(rest)
        captured = await http.post("/api/robots/arm/calibration/capture")
        assert captured.status_code == 200, captured.text
        await eventually(lambda: abs(gripper()) < 0.2, what="closed: 0")
        for raw in (rest + 1000, rest):
            with sim.paused() as bus:
                bus.servo(6).move_by_hand(raw)
            await eventually(lambda r=raw: abs(gripper() - (r - rest) * 100 / span_steps) < 0.2)
        session = (await http.get("/api/robots/arm/calibration")).json()["session"]
        low, high = session["range"]["gripper"]
        assert (low, round(high, 1)) == (0.0, round(1000 * 100 / span_steps, 1))
        finished = await http.post("/api/robots/arm/calibration/finish")
        assert finished.status_code == 200, finished.text
        joint = finished.json()["calibration"]["joints"]["gripper"]  # the file holds degrees
        assert joint["max_degrees"] == pytest.approx(1000 * 360 / 4096, abs=0.01)
        await eventually(lambda: all(servo_torque(sim).values()), what="torque back on")
        await eventually(lambda: abs(gripper()) < 0.2, what="closed at rest: 0")
        # A command in percent goes to that share of the captured range, and reads so.
        for value, goal in ((100, rest + 1000), (25, rest + 250)):
            moved = await http.put(
                "/api/robots/arm/joints", json={"joints": [{"name": "gripper", "value": value}]}
            )
            assert moved.status_code == 200, moved.text
            await eventually(lambda g=goal: servo_goals(sim)[6] == g, what=f"the goal of {value}")
            await eventually(lambda v=value: abs(gripper() - v) < 0.2, what=f"reads {value}")
