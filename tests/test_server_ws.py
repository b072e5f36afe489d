"""The WebSocket API against a real server on 127.0.0.1: the seed's clients, errors, races."""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import itertools
import json
import os
import struct
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from types import SimpleNamespace
from typing import Any, cast

import pytest
import trio
import trio.testing
from trio.testing import MockClock
from trio_websocket import ConnectionClosed, WebSocketConnection, open_websocket_url

from arena.protocol import messages as wire
from arena.protocol.errors import ErrorCode
from arena.protocol.ws_frames import OP_BINARY, OP_PING, OP_PONG, encode_frame
from arena.robot.events import (
    CommandHandled,
    JointStatesReceived,
    PeerChanged,
    RobotEvent,
    TargetsSent,
)
from arena.robot.handle import Robot
from arena.robot.mailbox import EventQueue
from arena.robot.manager import RobotManager
from arena.robot.model import load_robot_model
from arena.robot.motion import Clamp, Command, CommandResult
from arena.server.ws.acks import AckCache
from arena.server.ws.backpressure import Encoded
from arena.server.ws.forwarder import RobotEventForwarder
from arena.server.ws.master import decide_commands
from arena.server.ws.slave import slave_writer
from tests.conftest import RunningServer
from tests.raw_websocket import OP_CLOSE, OP_TEXT, RawWebSocket

StartServer = Callable[..., Awaitable[RunningServer]]


async def receive(ws: WebSocketConnection, wanted: str, timeout: float = 5.0) -> dict[str, Any]:
    """The next message of type `wanted`, skipping others."""
    with trio.fail_after(timeout):
        while True:
            message = json.loads(await ws.get_message())
            if message["type"] == wanted:
                return message


async def command(ws: WebSocketConnection, joints: dict[str, float], **data: Any) -> dict[str, Any]:
    """Send a command in the seed's format and return its acknowledgment."""
    await ws.send_message(
        json.dumps(
            {
                "type": "command",
                "timestamp": "2024-01-01T12:00:00Z",
                "data": {
                    "timestamp": 1704110400000,
                    "joints": [{"name": n, "value": v} for n, v in joints.items()],
                    **data,
                },
            }
        )
    )
    return await receive(ws, "ack")


async def closed_with(ws: WebSocketConnection, timeout: float = 5.0) -> int | None:
    """Wait for the server to close the socket; its close code."""
    with trio.fail_after(timeout):
        try:
            while True:
                await ws.get_message()
        except ConnectionClosed as closed:
            return closed.reason.code


def test_seed_python_example_with_websockets(tmp_path: Path) -> None:
    """The seed's `websockets` master snippet, unchanged but for stopping after one answer."""

    async def scenario() -> list[str]:
        async with trio.open_nursery() as nursery:
            from arena.server.config import ServerConfig
            from arena.server.run import run_server

            stop = trio.Event()
            app, urls = await nursery.start(
                lambda task_status: run_server(
                    ServerConfig(port=0, recordings_dir=str(tmp_path)),
                    stop=stop,
                    task_status=task_status,
                )
            )
            robot = await app.manager.create_robot("so-arm100", "My Robot", "my-robot")
            from arena.drivers.mock_slave import MockSlave

            await robot.attach_slave(MockSlave())
            uri = urls[0].replace("http", "ws") + "/ws/master/my-robot"
            printed = await trio.to_thread.run_sync(asyncio.run, seed_example(uri))
            stop.set()
            return printed

    printed = trio.run(scenario)
    assert printed and printed[0].startswith("Robot position: [{")


async def seed_example(uri: str) -> list[str]:
    import websockets

    printed: list[str] = []
    async with websockets.connect(uri) as websocket:
        # Send command
        command = {
            "type": "command",
            "timestamp": "2024-01-01T12:00:00Z",
            "data": {
                "timestamp": 1704110400000,
                "joints": [{"name": "Rotation", "value": 45}],
            },
        }
        await websocket.send(json.dumps(command))
        # Listen for responses
        async for message in websocket:
            data = json.loads(message)
            if data["type"] == "joint_states":
                printed.append(f"Robot position: {data['data']}")
                rotation = next(j for j in data["data"] if j["name"] == "Rotation")
                if rotation["real_value"] == 45:
                    break
    return printed


async def test_arduino_like_slave_reads_only_data_joints(server: RunningServer) -> None:
    # The demo arm's mock slave reports real values too: it leaves, so only the sketch does.
    async with server.client() as http:
        for slave in (await http.get("/api/robots/demo-arm")).json()["slaves"]:
            await http.delete(f"/api/robots/demo-arm/slaves/{slave['id']}")
    async with (
        open_websocket_url(server.ws_url + "/ws/slave/demo-arm?id=arduino") as slave,
        open_websocket_url(server.ws_url + "/ws/master/demo-arm") as master,
    ):
        ack = await command(master, {"Rotation": 10, "Jaw": 5})
        assert ack["data"]["status"] == "accepted"
        moved: dict[str, float] = {}
        while moved.get("Rotation") != 10 or moved.get("Jaw") != 5:  # along the trajectory
            doc = await receive(slave, "execute_command")
            moved = {j["name"]: j["value"] for j in doc["data"]["joints"]}
        # Like the sketch, it moves its servos and reports plain values back.
        await slave.send_message(
            json.dumps(
                {
                    "type": "joint_states",
                    "data": [{"name": n, "value": v + 0.5} for n, v in moved.items()],
                }
            )
        )
        async with server.client() as http:
            with trio.fail_after(30):
                while True:
                    joints = {
                        j["name"]: j for j in (await http.get("/api/robots/demo-arm/joints")).json()
                    }
                    if joints["Rotation"]["real_value"] == 10.5:
                        break
                    await trio.sleep(0.01)


async def tick(clock: MockClock, seconds: float, step: float = 0.02) -> None:
    """Let `seconds` of trio's time pass on a clock that stands still, control tick by
    control tick, everything done at each."""
    for _ in range(round(seconds / step)):
        clock.jump(step)
        await trio.testing.wait_all_tasks_blocked()


async def test_a_websocket_arm_that_says_where_it_is_joins_at_the_joining_speed(
    mock_clock: MockClock, start_server: StartServer
) -> None:
    # The robot is at Rotation 60 (a master put it there); an arm connects over /ws/slave and
    # reports Rotation 0. It is an arm that measures: brought to 60 at 15 deg/s, never sent 60
    # at once, whatever the master commands meanwhile.
    server = await start_server(record=False)
    robot = await server.app.manager.create_robot("so-arm100", robot_id="arm")
    rest = [{"name": joint.name, "value": 0.0} for joint in robot.model.joints]
    got: list[float] = []

    async def follow(arm: WebSocketConnection) -> None:
        while True:
            message = json.loads(await arm.get_message())
            if message["type"] == "execute_command":
                values = {j["name"]: j["value"] for j in message["data"]["joints"]}
                got.append(values["Rotation"])

    async with (
        open_websocket_url(server.ws_url + "/ws/master/arm") as master,
        trio.open_nursery() as nursery,
    ):
        assert (await command(master, {"Rotation": 60}))["data"]["status"] == "accepted"
        await tick(mock_clock, 1.0)
        assert robot.snapshot().joint("Rotation").virtual_value == pytest.approx(60.0)
        with robot.subscribe(kinds=[JointStatesReceived, PeerChanged]) as events:
            arm = await nursery.start(_open_slave, server.ws_url + "/ws/slave/arm?id=arm")
            nursery.start_soon(follow, arm)
            await arm.send_message(json.dumps({"type": "joint_states", "data": rest}))
            seen = [await events.get()]
            while not isinstance(seen[-1], JointStatesReceived):
                seen.append(await events.get())
            # The master moves another joint: the targets it makes are not the arm's.
            assert (await command(master, {"Jaw": 5}))["data"]["status"] == "accepted"
            await tick(mock_clock, 1.0)
            assert got and max(got) <= 15.0 + 1e-6  # 1 s at 15 deg/s from where it was
            assert got[-1] == pytest.approx(15.0, abs=0.5)
            (slave,) = robot.snapshot().slaves
            assert slave.joining  # no target of the robot's until it is at the robot's pose
            await tick(mock_clock, 4.0)
            assert got[-1] == pytest.approx(60.0)
            assert all(b - a <= 15.0 * 0.02 + 1e-6 for a, b in itertools.pairwise([0.0, *got]))
            changes = [e.change for e in seen + events.drain() if isinstance(e, PeerChanged)]
            assert changes == ["attached", "joining", "joined"]
        assert not robot.snapshot().slaves[0].joining
        nursery.cancel_scope.cancel()


async def _open_slave(url: str, task_status: trio.TaskStatus[WebSocketConnection]) -> None:
    """A slave's WebSocket, open until cancelled."""
    async with open_websocket_url(url) as ws:
        task_status.started(ws)
        await trio.sleep_forever()


async def test_acks_accepted_clamped_refused(server: RunningServer) -> None:
    async with open_websocket_url(server.ws_url + "/ws/master/demo-arm") as master:
        state = await receive(master, "state")
        assert state["data"]["mode"] == "mastered"
        assert (await command(master, {"Rotation": 45, "Pitch": -30}))["data"]["status"] == (
            "accepted"
        )
        clamped = (await command(master, {"Rotation": 500}))["data"]
        assert clamped["status"] == "clamped"
        assert clamped["clamped"][0]["joint"] == "Rotation"
        assert clamped["clamped"][0]["requested"] == 500
        refused = (await command(master, {"Nope": 1}))["data"]
        assert refused["status"] == "refused" and refused["code"] == "UNKNOWN_JOINT"
        smooth = await command(master, {"Rotation": 0}, duration=500)
        assert smooth["data"]["status"] == "accepted"


BAD_MESSAGES: list[tuple[str | bytes, str]] = [
    ("{not json", "INVALID_JSON"),
    ('{"type": "teleport", "data": {}}', "UNKNOWN_MESSAGE_TYPE"),
    ('{"data": {}}', "UNKNOWN_MESSAGE_TYPE"),
    ('{"type": "command"}', "INVALID_MESSAGE"),
    ('{"type": "command", "data": {"joints": "Rotation"}}', "INVALID_MESSAGE"),
    (
        '{"type": "command", "data": {"joints": [{"name": "Rotation", "value": "45"}]}}',
        "INVALID_MESSAGE",
    ),
    (
        '{"type": "command", "data": {"joints": [{"name": "Rotation", "value": 1e400}]}}',
        "INVALID_MESSAGE",
    ),
    (
        '{"type": "command", "data": {"joints": [{"name": "Rotation", "value": NaN}]}}',
        "INVALID_JSON",
    ),
    ('{"type": "sequence", "data": {"commands": []}}', "INVALID_VALUE"),
    (
        '{"type": "sequence", "data": {"commands": [{"joints": [{"name": "X", "value": 1}]}]}}',
        "UNKNOWN_JOINT",
    ),
    ("[1, 2, 3]", "INVALID_MESSAGE"),
    (
        '{"type": "command", "data": {"joints": [], "pad": "' + "x" * 70_000 + '"}}',
        "MESSAGE_TOO_LARGE",
    ),
    (b'{"type": "heartbeat"}', "BINARY_NOT_SUPPORTED"),
]


@pytest.mark.parametrize(("raw", "code"), BAD_MESSAGES)
async def test_bad_master_messages_get_an_error_and_change_nothing(
    server: RunningServer, raw: str | bytes, code: str
) -> None:
    async with (
        server.client() as http,
        open_websocket_url(server.ws_url + "/ws/master/demo-arm") as master,
    ):
        await receive(master, "joint_states")
        before = (await http.get("/api/robots/demo-arm")).json()
        await master.send_message(raw)
        error = await receive(master, "error")
        assert error["data"]["code"] == code and error["data"]["message"]
        assert (await http.get("/api/robots/demo-arm")).json() == before
        # The connection is still usable.
        assert (await command(master, {"Rotation": 1}))["data"]["status"] == "accepted"


async def test_bad_slave_messages_get_an_error(server: RunningServer) -> None:
    async with open_websocket_url(server.ws_url + "/ws/slave/demo-arm") as slave:
        for raw, code in [
            ("nope", "INVALID_JSON"),
            ('{"type": "command", "data": {}}', "UNKNOWN_MESSAGE_TYPE"),
            ('{"type": "joint_states", "data": [{"name": 5}]}', "INVALID_MESSAGE"),
            ('{"type": "joint_states", "data": [{"name": "Zz", "value": 1}]}', "UNKNOWN_JOINT"),
        ]:
            await slave.send_message(raw)
            assert (await receive(slave, "error"))["data"]["code"] == code
        await slave.send_message(
            json.dumps(
                {
                    "type": "error",
                    "data": {
                        "code": "SERVO_TIMEOUT",
                        "message": "Servo 3 not responding",
                        "joint": "Elbow",
                        "severity": "warning",
                    },
                }
            )
        )
        await slave.send_message(
            json.dumps(
                {
                    "type": "status_update",
                    "data": {
                        "isConnected": True,
                        "lastConnected": "2024-01-01T11:58:00Z",
                        "error": None,
                    },
                }
            )
        )
        await slave.send_message('{"type": "heartbeat"}')
        async with server.client() as http:
            with trio.fail_after(30):
                while True:
                    status = (await http.get("/api/robots/demo-arm/status")).json()
                    errors = [s["last_error"] for s in status["slaves"] if s["last_error"]]
                    if errors:
                        break
                    await trio.sleep(0.01)
        assert errors == ["SERVO_TIMEOUT: Servo 3 not responding"]
        assert status["state"] == "idle"  # a warning does not stop the robot


async def test_two_masters_and_takeover(server: RunningServer) -> None:
    url = server.ws_url + "/ws/master/demo-arm"
    async with open_websocket_url(url + "?id=alice") as alice:
        await receive(alice, "state")
        async with open_websocket_url(url + "?id=bob") as bob:
            error = await receive(bob, "error")
            assert error["data"]["code"] == "MASTER_ACTIVE"
            assert await closed_with(bob) == 4409
        async with open_websocket_url(url + "?id=carol&takeover=1") as carol:
            detached = await receive(alice, "detached")
            assert detached["data"]["code"] == "TAKEN_OVER"
            assert await closed_with(alice) == 4409
            assert (await command(carol, {"Rotation": 3}))["data"]["status"] == "accepted"


async def test_a_second_connection_under_the_owners_id_is_another_master(
    server: RunningServer,
) -> None:
    # An id is a label, not a credential: "alice" twice is refused like any second master,
    # and with takeover the first alice is told and closed; never two sockets on one link.
    url = server.ws_url + "/ws/master/demo-arm?id=alice"
    robot = server.app.manager.get("demo-arm")
    async with open_websocket_url(url) as first:
        await receive(first, "joint_states")
        async with open_websocket_url(url) as second:
            error = await receive(second, "error")
            assert error["data"]["code"] == "MASTER_ACTIVE"
            assert await closed_with(second) == 4409
        assert (await command(first, {"Rotation": 2}))["data"]["status"] == "accepted"
        async with open_websocket_url(url + "&takeover=1") as third:
            detached = await receive(first, "detached")
            assert detached["data"]["code"] == "TAKEN_OVER"
            assert await closed_with(first) == 4409
            # The first one's leaving (a loss) did not take the new alice's robot away.
            assert (await command(third, {"Rotation": 4}))["data"]["status"] == "accepted"
            assert robot.snapshot().owner == "alice" and str(robot.snapshot().mode) != "estopped"


async def test_racing_masters_one_wins(server: RunningServer) -> None:
    url = server.ws_url + "/ws/master/demo-arm"
    outcomes: list[str] = []
    everyone_answered = trio.Event()

    async def contender(name: str) -> None:
        async with open_websocket_url(f"{url}?id={name}") as ws:
            first = json.loads(await ws.get_message())
            outcomes.append(first["type"] if first["type"] != "error" else first["data"]["code"])
            if len(outcomes) == 4:
                everyone_answered.set()
            if first["type"] == "state":
                await everyone_answered.wait()  # the winner holds on until all have tried

    async with trio.open_nursery() as nursery:
        for name in ("m1", "m2", "m3", "m4"):
            nursery.start_soon(contender, name)
    assert sorted(outcomes) == ["MASTER_ACTIVE"] * 3 + ["state"]


async def test_master_disconnect_estops_the_robot(server: RunningServer) -> None:
    async with open_websocket_url(server.ws_url + "/ws/master/demo-arm?id=alice") as alice:
        await command(alice, {"Rotation": 5})
    async with server.client() as http:
        with trio.fail_after(30):
            while (status := (await http.get("/api/robots/demo-arm/status")).json())[
                "state"
            ] != "estopped":
                await trio.sleep(0.01)
    assert "alice" in status["estop_reason"]


async def test_heartbeat_timeout_drops_a_silent_master(start_server: StartServer) -> None:
    server = await start_server(demo=True, heartbeat_timeout=0.5, heartbeat_interval=0.1)
    async with open_websocket_url(server.ws_url + "/ws/master/demo-arm") as master:
        heartbeat = await receive(master, "heartbeat")  # the server's heartbeats reach us
        assert heartbeat["timestamp"]
        detached = await receive(master, "detached")
        assert detached["data"]["code"] == "MASTER_LOST"
        assert await closed_with(master) == 4408
    async with server.client() as http:
        assert (await http.get("/api/robots/demo-arm/status")).json()["state"] == "estopped"


async def test_heartbeats_keep_a_master(start_server: StartServer) -> None:
    # Wiring only (the timeout itself is tested on MockClock in test_actor.py): each
    # heartbeat message refreshes the robot's note of when it last heard from its master.
    server = await start_server(demo=True, heartbeat_interval=10)
    robot = server.app.manager.get("demo-arm")
    async with open_websocket_url(server.ws_url + "/ws/master/demo-arm") as master:
        await receive(master, "joint_states")
        assert robot._actor.peers.master is not None
        for _ in range(3):
            before = robot._actor.peers.master.last_seen
            await master.send_message('{"type": "heartbeat"}')
            await receive(master, "heartbeat")
            with trio.fail_after(30):  # noted at once, or by the actor's next turn
                while robot._actor.peers.master.last_seen <= before:
                    await trio.sleep(0.01)
        assert (await command(master, {"Rotation": 1}))["data"]["status"] == "accepted"


async def test_rest_estop_stops_a_websocket_master_and_reset_resumes(server: RunningServer) -> None:
    async with (
        server.client() as http,
        open_websocket_url(server.ws_url + "/ws/slave/demo-arm") as slave,
        open_websocket_url(server.ws_url + "/ws/master/demo-arm") as master,
    ):
        assert (await command(master, {"Rotation": 2}))["data"]["status"] == "accepted"
        await receive(slave, "execute_command")
        await http.post("/api/robots/demo-arm/estop", json={"reason": "hand in the way"})
        notice = await receive(slave, "estop")
        assert notice["data"]["reason"] == "hand in the way"
        state = await receive(master, "state")
        assert state["data"]["mode"] == "estopped"
        refused = (await command(master, {"Rotation": 3}))["data"]
        assert refused["status"] == "refused" and refused["code"] == "ESTOPPED"
        await http.post("/api/robots/demo-arm/reset")
        await receive(slave, "reset")
        assert (await command(master, {"Rotation": 3}))["data"]["status"] == "accepted"
        value = 0.0
        while value != 3:  # along the trajectory, to the goal
            value = (await receive(slave, "execute_command"))["data"]["joints"][0]["value"]


async def test_master_estop_and_reset_messages(server: RunningServer) -> None:
    async with open_websocket_url(server.ws_url + "/ws/master/demo-arm") as master:
        assert (await receive(master, "state"))["data"]["mode"] == "mastered"  # on connect
        await master.send_message('{"type": "estop", "data": {"reason": "operator"}}')
        assert (await receive(master, "state"))["data"]["mode"] == "estopped"
        await master.send_message('{"type": "reset"}')
        assert (await receive(master, "state"))["data"]["mode"] == "mastered"


async def test_sequence_message_plays(server: RunningServer) -> None:
    async with open_websocket_url(server.ws_url + "/ws/master/demo-arm") as master:
        await master.send_message(
            json.dumps(
                {
                    "type": "sequence",
                    "data": {
                        "id": "custom-dance",
                        "name": "Custom Dance Sequence",
                        "commands": [
                            {
                                "timestamp": 0,
                                "joints": [{"name": "Rotation", "value": -30}],
                                "duration": 200,
                            },
                            {
                                "timestamp": 300,
                                "joints": [{"name": "Rotation", "value": 30}],
                                "duration": 200,
                            },
                        ],
                        "total_duration": 600,
                        "loop": False,
                    },
                }
            )
        )
        assert (await receive(master, "ack"))["data"]["status"] == "accepted"
        seen = set()
        with trio.fail_after(30):
            while not {-30.0, 30.0} <= seen:
                states = await receive(master, "joint_states")
                seen.add(
                    next(j["virtual_value"] for j in states["data"] if j["name"] == "Rotation")
                )


async def test_state_stream_for_many_viewers(server: RunningServer) -> None:
    url = server.ws_url + "/ws/robots/demo-arm/state"
    async with open_websocket_url(url) as one, open_websocket_url(url) as two:
        for viewer in (one, two):
            assert (await receive(viewer, "state"))["data"]["mode"] == "idle"
        async with server.client() as http:
            await http.post("/api/robots/demo-arm/estop")
        for viewer in (one, two):
            assert (await receive(viewer, "state"))["data"]["mode"] == "estopped"
        await one.send_message('{"type": "command", "data": {"joints": []}}')
        assert (await receive(one, "error"))["data"]["code"] == "FORBIDDEN"


async def test_websocket_auth(start_server: StartServer) -> None:
    server = await start_server(demo=True, api_keys=("k1",))
    async with open_websocket_url(server.ws_url + "/ws/master/demo-arm") as master:
        assert (await receive(master, "error"))["data"]["code"] == "UNAUTHORIZED"
        assert await closed_with(master) == 4401
    async with open_websocket_url(server.ws_url + "/ws/slave/demo-arm?token=bad") as slave:
        assert (await receive(slave, "error"))["data"]["code"] == "FORBIDDEN"
    async with open_websocket_url(server.ws_url + "/ws/master/demo-arm?token=k1") as master:
        assert (await command(master, {"Rotation": 1}))["data"]["status"] == "accepted"


async def test_unknown_robot_is_refused(server: RunningServer) -> None:
    async with open_websocket_url(server.ws_url + "/ws/master/ghost") as master:
        assert (await receive(master, "error"))["data"]["code"] == "UNKNOWN_ROBOT"
        assert await closed_with(master) == 4404


async def test_shutdown_closes_every_socket_with_1001(server: RunningServer) -> None:
    base = server.ws_url
    async with (
        open_websocket_url(base + "/ws/master/demo-arm") as master,
        open_websocket_url(base + "/ws/slave/demo-arm") as slave,
        open_websocket_url(base + "/ws/robots/demo-arm/state") as viewer,
    ):
        for ws in (master, slave, viewer):
            await ws.send_message('{"type": "heartbeat"}')
        await receive(master, "heartbeat")
        server.stop.set()
        codes = [await closed_with(ws, timeout=1.0) for ws in (master, slave, viewer)]
    assert codes == [1001, 1001, 1001]


async def test_deleting_a_robot_closes_its_sockets(server: RunningServer) -> None:
    async with (
        open_websocket_url(server.ws_url + "/ws/master/demo-arm") as master,
        open_websocket_url(server.ws_url + "/ws/slave/demo-arm") as slave,
    ):
        await receive(master, "state")
        async with server.client() as http:
            await http.delete("/api/robots/demo-arm")
        assert await closed_with(slave) == 1000
        assert await closed_with(master) in (1000, 4404)


async def unlimited_robot(server: RunningServer, robot_id: str) -> Robot:
    """A so-arm100 whose per-master rate limit is lifted (bursts here go beyond it)."""
    model = load_robot_model("so-arm100")
    policy = dataclasses.replace(model.safety, command_rate=1e9, command_burst=10**9)
    robot: Robot = await server.app.manager.create_robot(
        "so-arm100", robot_id=robot_id, policy=policy
    )
    return robot


def masked_command(value: float) -> bytes:
    """A client's frame of a command moving Rotation to `value`."""
    text = json.dumps(
        {"type": "command", "data": {"joints": [{"name": "Rotation", "value": value}]}}
    )
    return encode_frame(OP_TEXT, text.encode(), mask=os.urandom(4))


async def test_a_slave_gets_each_lone_command_at_once_and_the_newest_of_a_burst(
    server: RunningServer,
) -> None:
    # Targets are written to an idle slave's socket by the robot itself; during a master's
    # burst they wait for the slave's writer task, which sends the newest once. (The rate
    # limit is lifted: the lone commands would otherwise leave the burst of ten short of
    # tokens until the limiter refilled, which only time does.)
    await unlimited_robot(server, "lone")
    async with open_websocket_url(server.ws_url + "/ws/slave/lone?id=ws-slave") as slave:
        master = await RawWebSocket.connect(server.url, "/ws/master/lone")

        async def rotations_until(last: float) -> list[float]:
            seen: list[float] = []
            while not seen or seen[-1] != last:
                doc = await receive(slave, "execute_command")
                seen += [j["value"] for j in doc["data"]["joints"] if j["name"] == "Rotation"]
            return seen

        lone = [0.001, 0.002, 0.003]  # moves done in one step: one target each
        for value in lone:
            await master.stream.send_all(masked_command(value))
            seen = await rotations_until(value)  # a step, or a stream's share if in its window
            assert seen[-1] == value and len(seen) <= 5
        burst = [0.001 * n for n in range(4, 14)]
        await master.stream.send_all(b"".join(masked_command(v) for v in burst))  # one write
        seen = await rotations_until(burst[-1])
        assert len(seen) < len(burst) and seen == sorted(seen)
        await master.aclose()


async def test_a_burst_faster_than_the_arm_is_acked_and_recorded_whole_with_targets_on_the_ticks(
    server: RunningServer,
) -> None:
    # 300 commands in one write, 0.3 degree apart: far beyond what Rotation may move in the
    # time. Every one is acknowledged and recorded; the trailing joint moves on the control
    # ticks (not once per command), and the slave ends at the last goal.
    model = load_robot_model("so-arm100")
    robot = await unlimited_robot(server, "fast")
    goals = [round(0.3 * n, 1) for n in range(1, 301)]  # to 90 degrees, inside the limits
    with robot.subscribe(maxlen=10_000) as events:
        async with open_websocket_url(server.ws_url + "/ws/slave/fast?id=ws-slave") as slave:
            master = await RawWebSocket.connect(server.url, "/ws/master/fast")
            await master.stream.send_all(b"".join(map(masked_command, goals)))  # a burst
            acks = 0
            with trio.fail_after(30):
                while acks < len(goals):
                    frame = await master.receive_frame()
                    assert frame is not None
                    doc = json.loads(frame.payload)
                    if doc["type"] == "ack":
                        assert doc["data"]["status"] == "accepted"
                        acks += 1
                while True:  # the slave is taken to the last goal at the velocity limit
                    doc = await receive(slave, "execute_command")
                    rotation = {j["name"]: j["value"] for j in doc["data"]["joints"]}["Rotation"]
                    if rotation == goals[-1]:
                        break
            await master.aclose()
        seen: list[RobotEvent] = []
        while len(events):
            seen.append(events.get_nowait())
    commanded = [e for e in seen if isinstance(e, CommandHandled)]
    targets = [e for e in seen if isinstance(e, TargetsSent)]
    assert [e.command.joints[0].value for e in commanded] == goals
    assert len(targets) < len(goals) / 2  # ~one per tick, not one per command
    assert targets[-1].joints["Rotation"] == goals[-1]
    speed = model.joint("Rotation").max_velocity  # type: ignore[union-attr]
    budget = speed / model.safety.control_rate  # targets lead the clock by a tick
    for before, after in itertools.pairwise(targets):
        moved = abs(after.joints["Rotation"] - before.joints["Rotation"])
        assert moved <= speed * (after.time - before.time) + budget + 1e-9


async def test_a_burst_of_commands_and_other_messages_is_answered_in_order(
    server: RunningServer,
) -> None:
    # Frames in hand together are taken at once and each run of commands among them is
    # decided in one pass: every message still gets its own answer, in the order sent, the
    # commands between bad messages all count, and a close among them comes after the answers
    # to what was sent before it.
    robot = await unlimited_robot(server, "mixed")

    def masked(opcode: int, payload: bytes) -> bytes:
        return encode_frame(opcode, payload, mask=os.urandom(4))

    frames, expected, goals = [], [], []
    for n, (raw, code) in enumerate(BAD_MESSAGES):
        goals.append(float(n + 1))
        frames.append(masked_command(goals[-1]))
        expected.append("accepted")
        bad = raw if isinstance(raw, bytes) else raw.encode()
        frames.append(masked(OP_BINARY if isinstance(raw, bytes) else OP_TEXT, bad))
        expected.append(code)
    frames.append(masked(OP_PING, b"still there?"))
    frames.append(masked(OP_TEXT, b'{"type": "heartbeat"}'))
    expected.append("heartbeat")
    goals.append(40.0)
    frames.append(masked_command(goals[-1]))
    expected.append("accepted")
    frames.append(masked(OP_CLOSE, struct.pack("!H", 1000)))
    with robot.subscribe(maxlen=1000) as events:
        master = await RawWebSocket.connect(server.url, "/ws/master/mixed")
        await master.stream.send_all(b"".join(frames))  # one write
        answers, pongs = [], []
        with trio.fail_after(30):
            while (frame := await master.receive_frame()) is not None:
                if frame.opcode == OP_CLOSE:
                    break
                if frame.opcode == OP_PONG:
                    pongs.append(frame.payload)
                    continue
                doc = json.loads(frame.payload)
                if doc["type"] in ("ack", "error"):
                    answers.append(doc["data"].get("code") or doc["data"]["status"])
                elif doc["type"] == "heartbeat":
                    answers.append("heartbeat")
        await master.aclose()
        commanded = []
        while len(events):
            event = events.get_nowait()
            if isinstance(event, CommandHandled):
                commanded.append(event.command.joints[0].value)
    assert frame is not None and frame.close_code == 1000
    assert answers == expected
    assert pongs == [b"still there?"]
    assert commanded == goals


async def test_the_slave_writer_lets_the_robot_write_lone_targets_itself(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    # With the writer task waiting, a target goes out inside the robot's own step (no task
    # wakes); inside a master's burst it goes through the task; the end always does. (Moves
    # of a thousandth of a degree with a duration, steps and not a stream, are done in one
    # step; the clock moves a tick between commands: a trajectory moves nothing in no time.)
    robot = await manager.create_robot("so-arm100", robot_id="direct")
    link = await robot.connect_slave("ws")
    direct: list[str] = []
    by_task: list[str] = []

    def send_now(message: Any) -> bool:
        direct.append(type(message).__name__)
        return True

    async def send(*messages: Any) -> None:
        by_task.extend(type(m).__name__ for m in messages)

    async def close(code: int, reason: str = "") -> None:
        by_task.append(f"close {code}")

    connection = cast(Any, SimpleNamespace(send_now=send_now, send_in_turn=send, close=close))
    ended = trio.Event()
    async with trio.open_nursery() as nursery:
        nursery.start_soon(slave_writer, connection, link, ended)
        await trio.testing.wait_all_tasks_blocked()
        assert robot.command_now(Command.of({"Rotation": 0.001}, duration=0.0)) is not None
        assert direct == ["ExecuteCommandMessage"] and by_task == []  # written before any switch
        autojump_clock.jump(robot.core.tick_interval)
        robot.command_now(Command.of({"Rotation": 0.002}, duration=0.0), in_burst=True)
        assert direct == ["ExecuteCommandMessage"]
        await trio.testing.wait_all_tasks_blocked()
        assert by_task == ["ExecuteCommandMessage"]
        # The same when the actor decides it (the target carries the burst with it).
        autojump_clock.jump(robot.core.tick_interval)
        await robot.command(Command.of({"Rotation": 0.003}, duration=0.0), in_burst=True)
        await trio.testing.wait_all_tasks_blocked()
        assert direct == ["ExecuteCommandMessage"] and by_task == ["ExecuteCommandMessage"] * 2
        await link.detach("done")
        await trio.testing.wait_all_tasks_blocked()
    assert ended.is_set()
    assert by_task == ["ExecuteCommandMessage"] * 2 + ["StopNotice", "close 1000"]


async def test_a_reader_takes_the_due_joint_states_so_the_forwarder_sends_no_copy(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    # What the reader takes along with an ack leaves the queue (the forwarder's task finds
    # nothing to repeat); pacing and state changes work as they do in the forwarder's task.
    # (Moves done in one step, a millisecond apart: a trajectory moves nothing in no time; a
    # duration makes each a step, not part of a stream followed over the time between them.)
    robot = await manager.create_robot("so-arm100", robot_id="paced")
    with robot.subscribe(maxlen=256) as events:
        forwarder, _ = _forwarder_on(robot, events)
        await robot.command(Command.of({"Rotation": 0.001}, duration=0.0))
        assert [type(m) for m in forwarder.take_due()] == [wire.JointStatesOut]
        assert len(events) == 0
        await trio.sleep(0.001)
        await robot.command(
            Command.of({"Rotation": 0.002}, duration=0.0)
        )  # the pacing allows two at once
        assert [type(m) for m in forwarder.take_due()] == [wire.JointStatesOut]
        await trio.sleep(0.001)
        await robot.command(Command.of({"Rotation": 0.003}, duration=0.0))
        assert forwarder.take_due() == [] and forwarder.pending  # held for the interval
        await trio.sleep(0.025)
        assert [type(m) for m in forwarder.take_due()] == [wire.JointStatesOut]
        await robot.estop("test")
        due = forwarder.take_due()
        assert isinstance(due[0], wire.StateMessage) and due[0].data.mode == "estopped"


async def test_a_run_that_finds_the_actor_busy_posts_one_command_and_decides_the_rest_at_once(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    # A motion tick due makes the actor busy: a command of the run waits in the actor's
    # inbox, and once the actor is idle again the rest are decided at once.
    robot = await manager.create_robot("so-arm100", robot_id="busy")
    link = await robot.connect_master("alice")
    assert (await link.command(Command.of({"Rotation": 90.0}))).accepted  # a long move
    await trio.testing.wait_all_tasks_blocked()
    autojump_clock.jump(robot.core.tick_interval)  # its next tick is due; no task has run
    assert link.command_run_now([Command.of({"Rotation": 1.0})]) is None
    posted = []
    through_inbox = link.command

    async def command(*args: Any, **kwargs: Any) -> Any:
        posted.append(args[0])
        return await through_inbox(*args, **kwargs)

    link.command = command  # type: ignore[method-assign]
    sent: list[Any] = []

    async def send(*messages: Any, whole: bool = False) -> None:
        assert whole  # the answers to a run go out at once
        sent.extend(messages)

    connection = cast(Any, SimpleNamespace(send=send, wants_acks=True))
    forwarder = cast(Any, SimpleNamespace(handling_command=contextlib.nullcontext, take_due=list))
    values = [10.0, 20.0, 30.0, 40.0, 50.0, 60.0]
    run = [wire.CommandData([wire.JointValue("Rotation", v)]) for v in values]
    with robot.subscribe(kinds=[CommandHandled]) as handled:
        assert await decide_commands(connection, link, forwarder, run, False, AckCache())
        decided = [handled.get_nowait() for _ in range(len(handled))]
    assert [e.command.joints[0].value for e in decided] == values  # type: ignore[attr-defined]
    # The first waited (the second may too: the actor still had its due tick to run), then
    # the actor was idle and the rest were decided at once.
    assert [g.joints[0].value for g in posted] in ([10.0], [10.0, 20.0])
    assert len(sent) == len(values)
    assert all(isinstance(m, Encoded) and m.kind == "ack" for m in sent)


def _forwarder_on(robot: Robot, events: EventQueue[RobotEvent]) -> tuple[Any, list[Any]]:
    """A forwarder for `robot` whose connection notes (time, message type) of what it sends."""
    sent: list[tuple[float, type]] = []

    async def send(*messages: Any) -> None:
        sent.extend((trio.current_time(), type(m)) for m in messages)

    config = SimpleNamespace(joint_states_interval=0.02)
    connection = SimpleNamespace(
        app=SimpleNamespace(arena_config=config), send=send, wants_joint_states=True
    )
    return RobotEventForwarder(cast(Any, connection), robot, events), sent


async def test_joint_states_the_reader_held_back_are_sent_by_the_task_when_due(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    # While the reader handles a command the forwarder's task is not woken; what the reader
    # leaves pending must still go out, when the interval allows, from the task.
    robot = await manager.create_robot("so-arm100", robot_id="held")
    with robot.subscribe(maxlen=256) as events:
        forwarder, sent = _forwarder_on(robot, events)
        async with trio.open_nursery() as nursery:
            nursery.start_soon(forwarder.run)
            await trio.sleep(0.1)
            with forwarder.handling_command():
                # Moves so small that each is done in one step (no motion ticks follow; a
                # duration makes each a step, not a stream), a millisecond apart (a trajectory
                # moves nothing in no time).
                for value in (0.001, 0.002):  # the pacing allows two at once
                    await robot.command(Command.of({"Rotation": value}, duration=0.0))
                    assert [type(m) for m in forwarder.take_due()] == [wire.JointStatesOut]
                    await trio.sleep(0.001)
                await robot.command(Command.of({"Rotation": 0.003}, duration=0.0))
                assert forwarder.take_due() == [] and forwarder.pending
            await trio.sleep(0.1)
            assert [kind for _, kind in sent] == [wire.JointStatesOut]
            # An interval after the bucket allows them (a command before then carries them).
            assert sent[0][0] == pytest.approx(0.1 + 0.02 + 0.02)
            nursery.cancel_scope.cancel()


async def test_after_a_stall_the_acknowledgments_carry_the_joint_states_again(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    # A client at the interval's own rate whose two commands arrive together after a stall:
    # one acknowledgment goes without, the next carries them again, and the forwarder's task
    # never sends joint states on its own (it did, for every command, before the fix).
    robot = await manager.create_robot("so-arm100", robot_id="stalled")
    with robot.subscribe(maxlen=256) as events:
        forwarder, sent = _forwarder_on(robot, events)
        carried: list[bool] = []
        async with trio.open_nursery() as nursery:
            nursery.start_soon(forwarder.run)
            start = trio.current_time() + 0.0003
            for n in range(60):
                due = start + 0.02 * n
                if n == 21:
                    continue  # sent on time but stuck behind number 20: it arrives with it
                if n == 20:
                    due += 0.025
                await trio.sleep_until(due)
                # (the pair asks for one pose: a second goal in the same instant would be the
                # trajectory's at its next tick, whose joint states then go out on their own)
                for value in (0.003, 0.003) if n == 20 else (0.001 * (1 + n % 2),):
                    with forwarder.handling_command():
                        await robot.command(Command.of({"Rotation": value}, duration=0.0))
                        due_now = forwarder.take_due()
                    carried.append(any(isinstance(m, wire.JointStatesOut) for m in due_now))
            await trio.sleep(0.1)
            nursery.cancel_scope.cancel()
        # (A move this small is one target at once, trajectory or not: `MotionLimiter._jump`.)
        assert carried.count(False) == 1, carried
        assert [kind for _, kind in sent] == []


async def test_joint_states_keep_to_the_interval_on_average_despite_jitter(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot = await manager.create_robot("so-arm100", robot_id="jitter")
    with robot.subscribe(maxlen=256) as events:
        forwarder, _ = _forwarder_on(robot, events)
        # A client at the interval's own rate, each send up to 1 ms early or late.
        with_states = 0
        for n in range(50):
            await trio.sleep(0.02 + (0.0005 if n % 2 else -0.0005))
            await robot.command(
                Command.of({"Rotation": 0.001 * (1 + n % 2)}, duration=0.0)
            )  # one step each
            with_states += any(isinstance(m, wire.JointStatesOut) for m in forwarder.take_due())
        assert with_states == 50, "every acknowledgment carries joint states"
        # Commands at twice the interval's rate (inside the robot's command rate): about one
        # per interval, and never more than two beyond that in any window.
        times = []
        started = trio.current_time()
        for n in range(200):
            await trio.sleep(0.011)
            await robot.command(Command.of({"Rotation": 0.001 * (1 + n % 2)}, duration=0.0))
            if any(isinstance(m, wire.JointStatesOut) for m in forwarder.take_due()):
                times.append(trio.current_time())
        elapsed = trio.current_time() - started
        assert elapsed / 0.025 <= len(times) <= elapsed / 0.02 + 2
        for start in times:
            assert sum(start <= t < start + 0.1 for t in times) <= 0.1 / 0.02 + 2


async def test_a_looping_sequence_of_no_duration_is_refused_over_the_wire(
    server: RunningServer,
) -> None:
    async with open_websocket_url(server.ws_url + "/ws/master/demo-arm") as master:
        await receive(master, "joint_states")
        spin = {
            "id": "spin",
            "name": "spin",
            "loop": True,
            "commands": [{"timestamp": 0, "joints": [{"name": "Jaw", "value": 1}]}],
        }
        await master.send_message(json.dumps({"type": "sequence", "data": spin}))
        error = await receive(master, "error")
        assert error["data"]["code"] == "INVALID_VALUE" and "duration" in error["data"]["message"]
        # Nothing plays; the master still commands.
        assert (await command(master, {"Rotation": 3}))["data"]["status"] == "accepted"


async def test_after_the_close_handshake_the_server_closes_the_connection_first(
    server: RunningServer, monkeypatch: pytest.MonkeyPatch
) -> None:
    # RFC 6455 7.1.1: the server closes TCP first. A client that waits for that (as the
    # `websockets` library does) must not wait out the server's close timeout, which is made
    # endless here: only a server that waits for the client's end of stream would hang.
    monkeypatch.setattr("arena.server.listener.CLOSE_TIMEOUT", 10_000.0)
    viewer = await RawWebSocket.connect(server.url, "/ws/robots/demo-arm/state")
    await viewer.send_frame(OP_CLOSE, (1000).to_bytes(2, "big"))
    with trio.fail_after(30):
        while (frame := await viewer.receive_frame()) is not None and frame.opcode != OP_CLOSE:
            pass  # the state sent on connect, then the echoed close
        assert frame is not None and frame.close_code == 1000
        assert await viewer.receive_frame() is None  # and then the end of the stream
    await viewer.aclose()


def test_a_plain_acceptance_is_encoded_once_a_millisecond(monkeypatch: pytest.MonkeyPatch) -> None:
    # The acks of a burst share one text (the transport frames it once); a new millisecond,
    # a clamp or a refusal each get their own.
    clock = [1_800_000_000_000_000_000]
    monkeypatch.setattr(time, "time_ns", lambda: clock[0])
    acks = AckCache()
    first = acks.ack(CommandResult(True))
    assert isinstance(first, Encoded) and json.loads(first.text)["data"]["status"] == "accepted"
    assert acks.ack(CommandResult(True)) is first
    clamp = Clamp("Rotation", 200.0, 180.0)
    assert isinstance(acks.ack(CommandResult(True, clamped=(clamp,))), wire.AckMessage)
    refusal = acks.ack(CommandResult.refused(ErrorCode.ESTOPPED, "stopped"))
    assert isinstance(refusal, wire.AckMessage) and refusal.data is not None
    assert refusal.data.code == "ESTOPPED"
    clock[0] += 1_000_000
    later = acks.ack(CommandResult(True))
    assert later is not first and json.loads(later.text)["timestamp"].endswith(".001Z")  # type: ignore[union-attr]
