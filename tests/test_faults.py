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
