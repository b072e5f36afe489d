"""Faults around the server: failing disks, slow and vanishing peers, flapping masters."""

from __future__ import annotations

import json
import shutil
import threading
from collections.abc import Awaitable, Callable
from pathlib import Path

import pytest
import trio
from trio_websocket import open_websocket_url

from arena.bench import BENCH_TYPE, bench_types
from arena.recording.mcap_file import Recording, read_recording
from arena.robot.model import TYPES_PATH_ENV
from arena.server import drivers as server_drivers
from arena.server import recordings_api
from tests.conftest import RunningServer, eventually
from tests.raw_websocket import OP_TEXT, Frame, RawWebSocket
from tests.test_server_ws import command, receive

StartServer = Callable[..., Awaitable[RunningServer]]
GOLDEN = Path(__file__).resolve().parent.parent / "recordings" / "golden" / "gentle-wave.mcap"


async def test_a_failing_recordings_folder_never_stops_control(
    start_server: StartServer, tmp_path: Path
) -> None:
    folder = tmp_path / "rec"
    server = await start_server(demo=True, recordings_dir=str(folder))
    async with (
        server.client() as http,
        open_websocket_url(server.ws_url + "/ws/master/demo-arm") as master,
    ):
        await receive(master, "joint_states")
        assert (await command(master, {"Rotation": 1}))["data"]["status"] == "accepted"
        await http.post("/api/recordings/current/stop")
        # The disk goes bad: the folder is replaced by a file, so no recording can be opened.
        shutil.move(folder, tmp_path / "rec-before")
        folder.write_text("not a folder")
        assert (await http.post("/api/recordings")).status_code == 201
        step = 0
        with trio.fail_after(30):  # control goes on all the while; the recorder says why
            while (status := (await http.get("/api/recordings")).json()["recorder"])[
                "error"
            ] is None:
                reply = await command(master, {"Rotation": 2 + step % 20 * 0.5})
                assert reply["data"]["status"] == "accepted"
                step += 1
                await trio.sleep(0.02)  # pacing only: the loop waits for the error
        assert status["dropped"] > 0 and status["errors"] >= 1
        assert "Not a directory" in status["error"] or "File exists" in status["error"]
        gauges = (await http.get("/metrics")).text
        assert "arena_recording_active 1" in gauges and "arena_recording_failing 1" in gauges
        # The disk comes back; starting the recording again retries at once.
        folder.unlink()
        folder.mkdir()
        assert (await http.post("/api/recordings")).status_code == 201
        with trio.fail_after(30):
            while (await http.get("/api/recordings")).json()["recorder"]["error"] is not None:
                await command(master, {"Rotation": 31})
                await trio.sleep(0.02)
        await command(master, {"Rotation": 30})
        await http.post("/api/recordings/current/stop")
        assert "arena_recording_failing 0" in (await http.get("/metrics")).text
    files = list(folder.glob("*.mcap"))
    assert files
    commands = [
        m for path in files for m in read_recording(path).messages if m.topic.endswith("/command")
    ]
    assert commands  # what came after the disk returned is in the new file


async def test_a_thousand_connections_opened_and_dropped(server: RunningServer) -> None:
    paths = ["/ws/robots/demo-arm/state", "/ws/slave/demo-arm", "/ws/master/demo-arm?takeover=1"]
    limit = trio.CapacityLimiter(50)

    async def one(i: int) -> None:
        async with limit:
            connection = await RawWebSocket.connect(server.url, paths[i % len(paths)])
            await connection.aclose()

    with trio.fail_after(60):
        async with trio.open_nursery() as nursery:
            for i in range(1000):
                nursery.start_soon(one, i)
    async with server.client() as http:
        with trio.fail_after(10):  # every dropped socket is noticed and its peer let go
            while True:
                robot = (await http.get("/api/robots/demo-arm")).json()
                gauges = (await http.get("/metrics")).text
                open_sockets = [
                    line
                    for line in gauges.splitlines()
                    if line.startswith("arena_connections{") and not line.endswith(" 0")
                ]
                if not open_sockets and robot["master"] is None and len(robot["slaves"]) == 1:
                    break
                await trio.sleep(0.1)
        assert (await http.post("/api/robots/demo-arm/reset")).status_code == 200
    async with open_websocket_url(server.ws_url + "/ws/master/demo-arm") as master:
        await receive(master, "joint_states")
        assert (await command(master, {"Rotation": 4}))["data"]["status"] == "accepted"


ARM = ["Rotation", "Pitch", "Elbow", "Wrist_Pitch", "Wrist_Roll", "Jaw"]


def whole_arm(value: float) -> str:
    """A command that moves every joint, so each `execute_command` is a few hundred bytes:
    Rotation to `value`, the others a tenth of it (an arm folded far enough meets its own
    table, which the collision guard refuses)."""
    joints = [{"name": name, "value": value if name == "Rotation" else value / 10} for name in ARM]
    return json.dumps({"type": "command", "data": {"joints": joints}})


def targets_in(payload: bytes) -> list[float]:
    """The Rotation value of an `execute_command` frame (nothing for other messages)."""
    message = json.loads(payload)
    if message["type"] != "execute_command":
        return []
    return [j["value"] for j in message["data"]["joints"] if j["name"] == "Rotation"]


async def test_a_slave_that_stops_reading_slows_no_one(
    start_server: StartServer, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # A slave with a 4 KiB receive buffer that never reads: after a few frames the server's
    # writes to it block. Its targets are latest-wins, so the robot, the master and the other
    # slaves go on, and when it reads again it gets the newest target, not a backlog.
    # (The robot type has its rate limit lifted, so the master can send as fast as it likes;
    # the trajectory offers the slaves a target at most every half tick, a few hundred here.)
    monkeypatch.setenv(TYPES_PATH_ENV, str(bench_types(tmp_path / "types")))
    server = await start_server()
    async with server.client() as http:
        created = await http.post("/api/robots", json={"robot_type": BENCH_TYPE, "id": "fast"})
        assert created.status_code == 201, created.text
    stalled = await RawWebSocket.connect(server.url, "/ws/slave/fast?id=slow", 4096)
    sent = 2000
    final = 33.3
    async with (
        open_websocket_url(server.ws_url + "/ws/slave/fast?id=brisk") as brisk,
        open_websocket_url(server.ws_url + "/ws/master/fast") as master,
    ):
        await receive(master, "joint_states")
        brisk_seen: list[float] = []
        brisk_done = trio.Event()

        async def read_brisk() -> None:
            while True:
                brisk_seen.extend(targets_in((await brisk.get_message()).encode()))
                if brisk_seen and brisk_seen[-1] == final:
                    brisk_done.set()
                    return

        async with trio.open_nursery() as nursery:
            nursery.start_soon(read_brisk)
            with trio.fail_after(60):
                for i in range(sent):
                    value = final if i == sent - 1 else 10 + (i % 50) * 0.1
                    await master.send_message(whole_arm(value))
                    ack = await receive(master, "ack")
                    assert ack["data"]["status"] in ("accepted", "clamped"), ack
                await brisk_done.wait()
        # The brisk slave kept pace: it has the final target (`brisk_done`).
        frames: list[float] = []
        with trio.fail_after(10):  # the stalled slave reads again: a short backlog, the newest
            while not frames or frames[-1] != final:
                frame = await stalled.receive_frame()
                assert frame is not None
                frames.extend(targets_in(frame.payload))
    # Its connection pushed back before the master was done: targets were merged, and it reads
    # the newest, not the backlog.
    assert frames[-1] == final and len(frames) < len(brisk_seen), (len(frames), len(brisk_seen))
    await stalled.aclose()
    async with server.client() as http:
        gauges = (await http.get("/metrics")).text
        (superseded,) = [
            int(line.split()[1])
            for line in gauges.splitlines()
            if line.startswith("arena_targets_superseded_total ")
        ]
        # Each slave was offered the same targets, at least as many as the brisk one saw: what
        # the stalled one did not get was superseded, and counted.
        assert superseded >= len(brisk_seen) - len(frames) > 0
        stopped = (await http.post("/api/recordings/current/stop")).json()["stopped"]
    # Every accepted command is in the recording, superseded targets or not.
    recording = read_recording(tmp_path / "recordings" / stopped)
    commands = [m for m in recording.messages if m.topic == "/robots/fast/command"]
    assert len(commands) == sent


async def test_a_slave_that_vanishes_mid_motion_stops_the_robot_safely(
    server: RunningServer,
) -> None:
    async with (
        server.client() as http,
        open_websocket_url(server.ws_url + "/ws/master/demo-arm") as master,
    ):
        await receive(master, "joint_states")
        vanishing = await RawWebSocket.connect(server.url, "/ws/slave/demo-arm?id=vanishing")
        for step in range(5):
            await master.send_message(whole_arm(10 + step))
            await receive(master, "ack")
        with trio.fail_after(30):  # it has a target in hand when it goes
            while not targets_in((await vanishing.receive_frame() or Frame(0, b"{}")).payload):
                pass
        await vanishing.aclose()
        # The loss policy (e-stop by default) names the slave; the master is told.
        with trio.fail_after(30):
            while (await receive(master, "state"))["data"]["mode"] != "estopped":
                pass
        robot = (await http.get("/api/robots/demo-arm")).json()
        assert "vanishing" in robot["estop_reason"]
        assert [s["id"] for s in robot["slaves"]] == ["demo-mock-slave"]
        refused = await command(master, {"Rotation": 20})
        assert refused["data"]["status"] == "refused"
        assert (await http.post("/api/robots/demo-arm/reset")).status_code == 200
        again = await command(master, {"Rotation": 21})
        assert again["data"]["status"] in ("accepted", "clamped")


async def test_a_flapping_master(server: RunningServer) -> None:
    # Forty masters in a row, each gone without a word after one command: the first loss
    # e-stops the robot, the later ones are refused, none of them lingers, and after a reset
    # the robot is still where the e-stop froze the last accepted command's move (on its
    # straight line from the start, every joint the same share of its way).
    robot = server.app.manager.get("demo-arm")
    for flap in range(40):
        master = await RawWebSocket.connect(server.url, "/ws/master/demo-arm")
        await master.send_frame(OP_TEXT, whole_arm(5 + flap).encode())
        with trio.fail_after(30):
            while True:
                frame = await master.receive_frame()
                assert frame is not None
                reply = json.loads(frame.payload)
                if reply["type"] == "ack":
                    break
        if flap == 0:
            assert reply["data"]["status"] in ("accepted", "clamped"), reply
        else:
            assert reply["data"]["code"] == "ESTOPPED", reply
        await master.aclose()
        await eventually(lambda: robot.snapshot().owner is None, what="the master's loss")
    snapshot = robot.snapshot()
    assert str(snapshot.mode) == "estopped"
    goals = {j.name: j.goal or 0.0 for j in snapshot.joints}
    share = goals["Rotation"] / 5.0
    assert 0.0 < share <= 1.0
    for name in ARM:
        assert goals[name] == pytest.approx(share * (5.0 if name == "Rotation" else 0.5))
        assert snapshot.joint(name).virtual_value == goals[name]  # frozen where it was
    async with server.client() as http:
        gauges = (await http.get("/metrics")).text
        assert 'arena_connections{role="master"} 0' in gauges
        assert (await http.post("/api/robots/demo-arm/reset")).status_code == 200
    async with open_websocket_url(server.ws_url + "/ws/master/demo-arm") as master:
        await receive(master, "joint_states")
        assert (await command(master, {"Rotation": 6}))["data"]["status"] == "accepted"


@pytest.mark.parametrize("reader", ["master", "replay", "summary"])
async def test_reading_a_recording_stalls_no_robot(
    start_server: StartServer, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, reader: str
) -> None:
    # The file read is held until the test lets it go: an e-stop sent meanwhile is answered
    # first, which it could not be if the read ran on the event loop.
    folder = tmp_path / "rec"
    folder.mkdir()
    shutil.copy(GOLDEN, folder / "long.mcap")
    server = await start_server(demo=True, recordings_dir=str(folder), record=False)
    entered, release = threading.Event(), threading.Event()
    order: list[str] = []

    def held_read(path: Path) -> Recording:
        entered.set()
        release.wait(30)
        order.append("read")
        return read_recording(path)

    monkeypatch.setattr(server_drivers, "read_recording", held_read)
    monkeypatch.setattr(recordings_api, "read_recording", held_read)
    answers: list[int] = []
    async with server.client() as http:

        async def load() -> None:
            body = {"recording": "long.mcap", "speed": 100}
            if reader == "master":
                reply = await http.post(
                    "/api/robots/demo-arm/master", json={"type": "replay", **body}
                )
            elif reader == "replay":
                reply = await http.post("/api/robots/demo-arm/replay", json=body)
            else:
                reply = await http.get("/api/recordings/long.mcap")
            answers.append(reply.status_code)

        async with trio.open_nursery() as nursery:
            nursery.start_soon(load)
            await trio.to_thread.run_sync(entered.wait, 30)
            assert (await http.post("/api/estop")).status_code == 200
            order.append("estop answered")
            release.set()
        assert (await http.post("/api/robots/demo-arm/reset")).status_code == 200
    assert order == ["estop answered", "read"]
    # The e-stop came first: a replay is then refused (423 ESTOPPED), a summary answered.
    assert answers == [200 if reader == "summary" else 423]
