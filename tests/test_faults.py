"""Faults around the server: a recordings folder that fails while the robot is driven."""

from __future__ import annotations

import shutil
from collections.abc import Awaitable, Callable
from pathlib import Path

import trio
from trio_websocket import open_websocket_url

from arena.recording.mcap_file import read_recording
from tests.conftest import RunningServer
from tests.test_server_ws import command, receive

StartServer = Callable[..., Awaitable[RunningServer]]


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
        for step in range(20):  # control goes on all the while
            reply = await command(master, {"Rotation": 2 + step * 0.5})
            assert reply["data"]["status"] == "accepted"
            await trio.sleep(0.03)
        with trio.fail_after(5):
            while True:
                status = (await http.get("/api/recordings")).json()["recorder"]
                if status["error"] is not None:
                    break
                await trio.sleep(0.05)
        assert status["dropped"] > 0
        # The disk comes back: recording resumes by itself.
        folder.unlink()
        folder.mkdir()
        await command(master, {"Rotation": 30})
        with trio.fail_after(5):
            while (await http.get("/api/recordings")).json()["recorder"]["error"] is not None:
                await command(master, {"Rotation": 31})
                await trio.sleep(0.1)
        await http.post("/api/recordings/current/stop")
    files = list(folder.glob("*.mcap"))
    assert files
    commands = [
        m for path in files for m in read_recording(path).messages if m.topic.endswith("/command")
    ]
    assert commands  # what came after the disk returned is in the new file


async def _open_and_drop(host: str, port: int, path: str) -> None:
    """A WebSocket handshake, then the TCP connection is cut without a close frame."""
    stream = await trio.open_tcp_stream(host, port)
    request = (
        f"GET {path} HTTP/1.1\r\nHost: {host}:{port}\r\nUpgrade: websocket\r\n"
        "Connection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n"
        "Sec-WebSocket-Version: 13\r\n\r\n"
    )
    await stream.send_all(request.encode())
    answer = b""
    while b"\r\n\r\n" not in answer:
        chunk = await stream.receive_some(4096)
        if not chunk:
            break
        answer += chunk
    assert answer.startswith(b"HTTP/1.1 101"), answer[:80]
    await stream.aclose()


async def test_a_thousand_connections_opened_and_dropped(server: RunningServer) -> None:
    host, port = server.url.split("//")[1].rsplit(":", 1)
    paths = ["/ws/robots/demo-arm/state", "/ws/slave/demo-arm", "/ws/master/demo-arm?takeover=1"]
    limit = trio.CapacityLimiter(50)

    async def one(i: int) -> None:
        async with limit:
            await _open_and_drop(host, int(port), paths[i % len(paths)])

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
