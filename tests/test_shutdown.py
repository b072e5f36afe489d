"""SIGTERM is a planned stop: masters told, a moving arm left as its e-stop setting says, the
recording finished whole; a second signal stops at once."""

from __future__ import annotations

import os
import signal
import socket
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
import trio
from mcap.reader import make_reader
from trio_websocket import ConnectionClosed, open_websocket_url

from arena.feetech import registers as reg
from arena.recording.analysis import summarize
from arena.recording.dataset import episode_notes, episodes_of
from arena.recording.mcap_file import read_recording
from arena.server.base import ArenaApp
from arena.server.config import ServerConfig
from arena.server.run import run_server
from arena.servo.sim_pty import PtySimBus
from tests.hardware import eventually, running_sim, servo_torque, wait_joined
from tests.serve_process import serving
from tests.test_server_ws import command

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture
def sim(tmp_path: Path) -> Iterator[PtySimBus]:
    yield from running_sim(tmp_path)


async def start(nursery: trio.Nursery, config: ServerConfig) -> tuple[ArenaApp, str, trio.Event]:
    """`run_server` as `arena serve` runs it (signals handled); `done` once it has returned."""
    done = trio.Event()

    async def run(task_status: trio.TaskStatus[Any]) -> None:
        try:
            await run_server(config, handle_signals=True, task_status=task_status)
        finally:
            done.set()

    app, urls = await nursery.start(run)
    return app, urls[0], done


def servos(sim: PtySimBus) -> dict[int, tuple[int, int, int]]:
    """(goal, present, velocity) of every simulated servo."""
    with sim.paused() as bus:
        return {
            sid: (
                servo.peek(reg.GOAL_POSITION),
                servo.peek(reg.PRESENT_POSITION),
                servo.peek(reg.PRESENT_VELOCITY),
            )
            for sid, servo in bus.servos.items()
        }


@pytest.mark.parametrize(("policy", "torque"), [("hold", 1), ("torque-off", 0)])
async def test_sigterm_stops_a_moving_arm_as_its_estop_setting_says(
    nursery: trio.Nursery, sim: PtySimBus, tmp_path: Path, policy: str, torque: int
) -> None:
    recordings = tmp_path / "recordings"
    app, url, done = await start(nursery, ServerConfig(port=0, recordings_dir=str(recordings)))
    async with httpx.AsyncClient(base_url=url, timeout=10) as http:
        made = await http.post("/api/robots", json={"id": "arm", "robot_type": "so-arm100"})
        assert made.status_code == 201
        slave = {"type": "usb-slave", "port": str(sim.link), "estop": policy}
        assert (await http.post("/api/robots/arm/slaves", json=slave)).status_code == 201
    await wait_joined(app.manager.get("arm"))
    ws_url = "ws" + url[len("http") :] + "/ws/master/arm"
    async with open_websocket_url(ws_url) as master:
        reply = await command(master, {"Rotation": 90}, duration=4000)
        assert reply["data"]["status"] == "accepted", reply
        await eventually(lambda: servos(sim)[1][2] != 0, what="the arm moving")
        os.kill(os.getpid(), signal.SIGTERM)
        with pytest.raises(ConnectionClosed) as closed:  # told, not cut
            while True:
                await master.get_message()
        assert closed.value.reason.code == 1001
    with trio.fail_after(30):
        await done.wait()
    # Left as the setting says, and still: each servo's goal is where it is (no motion left).
    assert set(servo_torque(sim).values()) == {torque}
    await eventually(
        lambda: all(
            goal == present and speed == 0 for goal, present, speed in servos(sim).values()
        ),
        what="every servo at rest on its goal",
    )
    moved = {sid: values[1] for sid, values in servos(sim).items()}
    assert moved[1] != 2048  # it had moved (Rotation 0 is step 2048)
    (path,) = recordings.glob("*.mcap")
    recording = read_recording(path)
    assert not recording.truncated and not recording.in_progress
    assert any(m.topic.endswith("/command") for m in recording.messages)
    with path.open("rb") as stream:  # mcap's own reader finds the index
        summary = make_reader(stream).get_summary()
    assert summary is not None and summary.statistics is not None
    assert summary.statistics.message_count == recording.message_count
    with pytest.raises(httpx.ConnectError):  # nothing listens any more
        httpx.get(url, timeout=5)


async def test_a_second_signal_stops_at_once(nursery: trio.Nursery, tmp_path: Path) -> None:
    # A grace of an hour: the planned stop waits for the request still being sent.
    config = ServerConfig(
        port=0, demo=True, recordings_dir=str(tmp_path / "rec"), shutdown_grace=3600.0
    )
    app, url, done = await start(nursery, config)
    host, port = url.removeprefix("http://").rsplit(":", 1)
    with socket.create_connection((host, int(port))) as slow:
        slow.sendall(b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\n")  # the headers never end
        os.kill(os.getpid(), signal.SIGTERM)
        with trio.fail_after(30):
            await app.shutting_down.wait()
        assert not done.is_set()
        os.kill(os.getpid(), signal.SIGINT)
        with trio.fail_after(30):
            await done.wait()
    (path,) = (tmp_path / "rec").glob("*.mcap")
    assert not read_recording(path).truncated  # cut short, yet closed whole


def test_arena_serve_exits_0_on_sigterm_with_its_recording_whole(tmp_path: Path) -> None:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    with serving(["--demo", "--port", "0"], cwd=tmp_path, env=env) as served:
        seq = httpx.post(f"{served.url}/api/robots/demo-arm/play-sequence/gentle-wave", timeout=10)
        assert seq.status_code == 200
        sent = time.monotonic()
        served.process.send_signal(signal.SIGTERM)
        status = served.process.wait(timeout=60)
        took = time.monotonic() - sent
    assert status == 0, served.log
    # Nothing left alive at the interpreter's exit: the trajectory's native objects (Ruckig,
    # through nanobind) were reported as leaks, 40 lines, on every planned stop.
    assert served.ended.wait(30)  # (the log read to its end)
    assert "leaked" not in served.log, served.log
    print(f"stopped {took:.2f} s after SIGTERM")  # the README's figure (pytest -s)
    (path,) = (tmp_path / "recordings").glob("*.mcap")
    recording = read_recording(path)
    assert not recording.truncated and not recording.in_progress
    assert any(m.topic.endswith("/command") for m in recording.messages)


#: A server whose arm is attached in its own process, not over REST (as an embedding program,
#: the demo or a config does it): run with the simulated bus's port and the `estop` setting.
SERVER_WITH_ITS_OWN_ARM = """
import logging, sys
from functools import partial

import trio

from arena.drivers.config import UsbSlaveConfig
from arena.drivers.usb_slave import UsbSlave
from arena.server.config import ServerConfig
from arena.server.run import run_server


async def main(port: str, estop: str) -> None:
    async with trio.open_nursery() as nursery:
        config = ServerConfig(port=0)
        app, _ = await nursery.start(partial(run_server, config, handle_signals=True))
        robot = await app.manager.create_robot("so-arm100", robot_id="arm")
        await robot.attach_slave(UsbSlave(UsbSlaveConfig(port, estop=estop), robot.model), "bus")


logging.basicConfig(level=logging.INFO)
trio.run(main, *sys.argv[1:])
"""


@pytest.mark.parametrize(("policy", "torque"), [("hold", 1), ("torque-off", 0)])
def test_sigterm_leaves_an_arm_attached_in_the_servers_own_process_as_its_setting_says(
    sim: PtySimBus, tmp_path: Path, policy: str, torque: int
) -> None:
    script = tmp_path / "serve_with_arm.py"
    script.write_text(SERVER_WITH_ITS_OWN_ARM, encoding="utf-8")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    argv = [str(sim.link), policy]
    with serving(argv, cwd=tmp_path, env=env, program=[str(script)]) as served:
        deadline = time.monotonic() + 60  # only a broken attach waits this long
        while True:
            robot = httpx.get(f"{served.url}/api/robots/arm", timeout=10)
            slaves = robot.json().get("slaves", []) if robot.status_code == 200 else []
            if slaves and not slaves[0]["joining"] and slaves[0]["connected"]:
                break
            assert time.monotonic() < deadline, served.log
            time.sleep(0.05)
        assert set(servo_torque(sim).values()) == {1}  # the arm holds itself up
        served.process.send_signal(signal.SIGTERM)
        status = served.process.wait(timeout=60)
    assert status == 0, served.log
    assert set(servo_torque(sim).values()) == {torque}, served.log
    assert all(goal == present for goal, present, _ in servos(sim).values())


async def test_sigterm_cuts_a_running_episode_and_the_recording_says_so(
    nursery: trio.Nursery, tmp_path: Path
) -> None:
    recordings = tmp_path / "recordings"
    config = ServerConfig(port=0, demo=True, recordings_dir=str(recordings))
    _, url, done = await start(nursery, config)
    async with httpx.AsyncClient(base_url=url, timeout=10) as http:
        for task in ("wave", "pick up the cube"):
            started = await http.post("/api/robots/demo-arm/episodes/start", json={"task": task})
            assert started.status_code == 201, started.text
            if task == "wave":
                assert (await http.post("/api/robots/demo-arm/episodes/stop")).status_code == 200
        os.kill(os.getpid(), signal.SIGTERM)
    with trio.fail_after(30):
        await done.wait()
    (path,) = recordings.glob("*.mcap")
    recording = read_recording(path)
    marks = [(m.data["index"], m.data["change"]) for m in recording.messages if m.kind == "episode"]
    assert marks == [(0, "start"), (0, "stop"), (1, "start"), (1, "cut")]
    # Whatever lists or exports episodes says how each ended.
    listed = summarize(recording)["episodes"]
    assert [(e["index"], e["task"], e["ended"]) for e in listed] == [
        (0, "wave", "stop"),
        (1, "pick up the cube", "cut"),
    ]
    spans = episodes_of([m for m in recording.messages if m.robot_id == "demo-arm"], "x")
    assert [(span.index, span.ended) for span in spans] == [(0, "stop"), (1, "cut")]
    assert episode_notes(spans) == [
        "episode 1 was cut short: its robot stopped (a server shutdown, the robot deleted) "
        "before the episode was stopped"
    ]
