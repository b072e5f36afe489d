"""Every peer's faults, a leader arm's (usb-master) and a follower's (usb-slave) alike, in one
place each: the robot's details over REST, `fault` messages on the viewer socket, the
recording; and gone from all of them when they are over, when the robot is reset, or when the
peer leaves."""

from __future__ import annotations

import json
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import trio
from trio.testing import MockClock
from trio_websocket import WebSocketConnection, open_websocket_url

from arena.protocol.errors import ErrorCode, Severity
from arena.recording.mcap_file import read_recording
from arena.robot.events import FaultReported
from arena.robot.links import SlaveLink
from arena.robot.manager import RobotManager
from arena.robot.model import load_robot_model
from arena.robot.motion import Command
from arena.robot.safety import Mode
from arena.servo.sim_pty import PtySimBus
from tests.conftest import RunningServer, eventually
from tests.hardware import usb_slave
from tests.test_usb_master import follower, leader

MODEL = load_robot_model("so-arm100")
__all__ = ["follower", "leader"]  # the fixtures: two simulated buses


StartServer = Callable[..., Awaitable[RunningServer]]


class Viewer:
    """The `fault` messages a viewer socket got, read in the background."""

    def __init__(self, socket: WebSocketConnection) -> None:
        self.socket = socket
        self.faults: list[dict[str, Any]] = []

    async def run(self) -> None:
        while True:
            message = json.loads(await self.socket.get_message())
            if message["type"] == "fault":
                self.faults.append(message["data"])

    def saw(self, peer: str, code: str, *, cleared: bool) -> bool:
        return any(
            f["peer_id"] == peer and f["code"] == code and f["cleared"] is cleared
            for f in self.faults
        )


def codes(peer: dict[str, Any] | None) -> set[tuple[str, str | None]]:
    """The (code, joint) of each fault a peer of the REST details has."""
    assert peer is not None
    return {(f["code"], f["joint"]) for f in peer["faults"]}


async def test_a_leaders_and_a_followers_faults_are_shown_sent_recorded_and_cleared(
    start_server: StartServer, leader: PtySimBus, follower: PtySimBus, tmp_path: Path
) -> None:
    server = await start_server(calibration_dir=str(tmp_path / "calibration"))
    async with server.client() as http:
        assert (await http.post("/api/robots", json={"id": "arm"})).status_code == 201
    async with (
        server.client() as http,
        open_websocket_url(server.ws_url + "/ws/robots/arm/state?joint_states=false") as ws,
        trio.open_nursery() as nursery,
    ):
        slave = {"type": "usb-slave", "port": str(follower.link)}
        assert (await http.post("/api/robots/arm/slaves", json=slave)).status_code == 201
        master = {"type": "usb-master", "port": str(leader.link)}
        reply = await http.post("/api/robots/arm/master", json=master)
        assert reply.status_code == 201, reply.text
        viewer = Viewer(ws)
        nursery.start_soon(viewer.run)

        async def details() -> dict[str, Any]:
            answer: dict[str, Any] = (await http.get("/api/robots/arm")).json()
            return answer

        # The leader's supply sags (an error: a master's fault stops nothing); the follower's
        # elbow runs warm (a warning).
        with leader.paused() as bus:
            bus.servo(2).voltage = 3.0
        with follower.paused() as bus:
            bus.servo(3).temperature = 58.0

        async def both_shown() -> bool:
            robot = await details()
            return ("SERVO_VOLTAGE", "Pitch") in codes(robot["master"]) and (
                "SERVO_HOT",
                "Elbow",
            ) in codes(robot["slaves"][0])

        await eventually(both_shown, what="both faults in the robot's details")
        robot = await details()
        assert robot["state"] == "mastered"  # neither stopped the robot
        assert robot["master"]["last_error"].startswith("SERVO_VOLTAGE: Pitch: Servo 2")
        await eventually(lambda: viewer.saw(reply.json()["id"], "SERVO_VOLTAGE", cleared=False))
        slave_id = robot["slaves"][0]["id"]
        await eventually(lambda: viewer.saw(slave_id, "SERVO_HOT", cleared=False))

        # Both end: gone from the details, and the viewer is told.
        with leader.paused() as bus:
            bus.servo(2).voltage = 12.0
        with follower.paused() as bus:
            bus.servo(3).temperature = 30.0

        async def both_over() -> bool:
            robot = await details()
            return not {("SERVO_VOLTAGE", "Pitch")} & codes(robot["master"]) and not {
                ("SERVO_HOT", "Elbow")
            } & codes(robot["slaves"][0])

        await eventually(both_over, what="both faults over")
        await eventually(lambda: viewer.saw(reply.json()["id"], "SERVO_VOLTAGE", cleared=True))
        await eventually(lambda: viewer.saw(slave_id, "SERVO_HOT", cleared=True))
        robot = await details()
        assert robot["master"]["last_error"] is None
        stopped = (await http.post("/api/recordings/current/stop")).json()["stopped"]
        nursery.cancel_scope.cancel()
    recording = read_recording(Path(tmp_path / "recordings" / stopped))
    recorded = [
        (m.data["peer_id"], m.data["code"], m.data["joint"], m.data["cleared"])
        for m in recording.messages
        if m.kind == "fault" and m.data["code"] in ("SERVO_VOLTAGE", "SERVO_HOT")
    ]
    master_id = reply.json()["id"]
    assert (master_id, "SERVO_VOLTAGE", "Pitch", False) in recorded
    assert (master_id, "SERVO_VOLTAGE", "Pitch", True) in recorded
    assert (slave_id, "SERVO_HOT", "Elbow", False) in recorded
    assert (slave_id, "SERVO_HOT", "Elbow", True) in recorded


class FaultySlave:
    """A slave that reports one critical fault on its first target, then follows."""

    kind = "faulty-slave"
    measures = False

    async def run(self, link: SlaveLink) -> None:
        reported = False
        async for _message in link.messages():
            if not reported:
                reported = True
                await link.report_fault(
                    ErrorCode.SERVO_OVERLOAD, "Elbow: stuck", Severity.CRITICAL, "Elbow"
                )


async def test_a_reset_clears_every_old_fault(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot = await manager.create_robot("so-arm100", robot_id="arm")
    with robot.subscribe(kinds=[FaultReported]) as events:
        await robot.attach_slave(FaultySlave(), slave_id="arm-1")
        await robot.command(Command.of({"Rotation": 5.0}))
        await eventually(lambda: robot.snapshot().mode is Mode.ESTOPPED, what="the e-stop")
        (slave,) = robot.snapshot().slaves
        assert slave.last_error == "SERVO_OVERLOAD: Elbow: stuck"
        await robot.reset()
        (after,) = robot.snapshot().slaves
        assert after.last_error is None  # it stayed, an old error on a slave that works
        assert [(f.code, f.joint) for f in slave.faults] == [("SERVO_OVERLOAD", "Elbow")]
        assert after.faults == ()
        told = [(e.code, e.cleared) for e in events.drain()]
    assert told == [("SERVO_OVERLOAD", False), ("SERVO_OVERLOAD", True)]


async def test_a_fault_that_lasts_through_a_reset_is_reported_again(
    manager: RobotManager, follower: PtySimBus
) -> None:
    # The reset ends every fault shown; the arm's bus reports again what still ails it.
    robot = await manager.create_robot("so-arm100", robot_id="arm")
    await robot.attach_slave(usb_slave(follower, MODEL), slave_id="arm-1")
    with follower.paused() as bus:
        bus.servo(3).temperature = 58.0

    def hot() -> bool:
        (slave,) = robot.snapshot().slaves
        return ("SERVO_HOT", "Elbow") in {(f.code, f.joint) for f in slave.faults}

    await eventually(hot, what="the warm elbow")
    with robot.subscribe(kinds=[FaultReported]) as events:
        await robot.estop("test")
        await robot.reset()
        await eventually(hot, what="the elbow, still warm, reported again")
        told = [(e.code, e.cleared) for e in events.drain() if e.code == "SERVO_HOT"]
    assert told == [("SERVO_HOT", True), ("SERVO_HOT", False)]
