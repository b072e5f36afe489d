"""Scripts as masters (specs/scripts.md): a script in a worker process of its own drives a robot
of a real server through every rule; its errors are faults with its line; an e-stop kills it;
only a file of the tenant's scripts folder runs; `arena script` runs one from another machine."""

from __future__ import annotations

import math
import os
import textwrap
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import httpx
import pytest
import trio

from arena.recording.mcap_file import read_recording
from arena.robot.cartesian import hand_for
from arena.robot.events import CommandHandled, FaultReported, RobotEvent, StateChanged
from arena.robot.mailbox import EventQueue
from arena.robot.model import load_robot_model
from arena.robot.safety import Mode
from tests.conftest import RunningServer

Start = Callable[..., Awaitable[RunningServer]]
ROBOT = "/api/robots/demo-arm"
#: Bounds on waits that only a broken feature reaches (a worker starts Python: a second or so).
WAIT = 60.0

THREE_POSES = """
from arena.script import move_to_pose, pose, wait, joints

start = pose()["position"]
for dx, dy, dz in [(0.02, 0.0, 0.0), (0.0, 0.02, 0.0), (0.0, 0.0, 0.03)]:
    move_to_pose([start[0] + dx, start[1] + dy, start[2] + dz])
    print("at", [round(v, 4) for v in pose()["position"]])
wait(0.05)
print("done", sorted(joints()))
"""


def write(folder: Path, name: str, text: str) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / name
    path.write_text(textwrap.dedent(text))
    return path


def script_workers() -> list[int]:
    """Process ids of the script workers running now."""
    found = []
    for pid in os.listdir("/proc"):
        if pid.isdigit():
            try:
                command = Path(f"/proc/{pid}/cmdline").read_bytes()
            except OSError:
                continue
            if b"arena.script.worker" in command:
                found.append(int(pid))
    return found


async def next_event(events: EventQueue[RobotEvent], check: Callable[[RobotEvent], bool]) -> Any:
    with trio.fail_after(WAIT):
        while True:
            event = await events.get()
            if check(event):
                return event


async def attach(server: RunningServer, name: str, **body: Any) -> httpx.Response:
    async with server.client() as http:
        return await http.post(f"{ROBOT}/master", json={"type": "script", "path": name, **body})


async def scripted(start_server: Start, tmp_path: Path) -> RunningServer:
    return await start_server(demo=True, script_dir=str(tmp_path / "scripts"))


async def test_a_script_moves_the_hand_to_three_poses_through_the_master_path(
    start_server: Start, tmp_path: Path
) -> None:
    server = await scripted(start_server, tmp_path)
    write(tmp_path / "scripts", "three.py", THREE_POSES)
    robot = server.app.manager.get("demo-arm")
    model = load_robot_model("so-arm100")
    hand = hand_for(model)
    assert hand is not None
    start = hand.pose({j.name: j.goal for j in robot.snapshot().joints})
    assert start is not None
    with robot.subscribe(kinds=[CommandHandled, StateChanged, FaultReported]) as events:
        answer = await attach(server, "three.py")
        assert answer.status_code == 201, answer.text
        assert answer.json() == {"id": "script:three.py", "type": "script"}
        # The script hands the robot back when it ends.
        with trio.fail_after(WAIT):
            while robot.snapshot().master is not None:
                await trio.sleep(0.05)
        faults = [e for e in events.drain() if isinstance(e, FaultReported)]
        assert not faults, faults
    async with server.client() as http:
        stopped = (await http.post("/api/recordings/current/stop")).json()["stopped"]
    recording = read_recording(Path(server.app.recorder.folder) / stopped)
    commands = [
        m.data
        for m in recording.messages
        if m.kind == "command" and m.data.get("source") == "script:three.py"
    ]
    assert len(commands) == 3, commands
    # Each command's joints put the hand at its pose, within the solver's tolerance.
    goals = {j.name: j.goal for j in robot.snapshot().joints}
    steps = [(0.02, 0.0, 0.0), (0.0, 0.02, 0.0), (0.0, 0.0, 0.03)]
    for command, step in zip(commands, steps, strict=True):
        joints = dict(goals)
        joints.update({j["name"]: j["value"] for j in command["joints"]})
        reached = hand.pose(joints)
        assert reached is not None
        wanted = [a + b for a, b in zip(start.position, step, strict=True)]
        assert math.dist(reached.position, wanted) < 0.001
