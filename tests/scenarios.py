"""Recorded scenarios and deterministic replay, as helpers the tests share.

`record_scenario(folder, scenario)` runs a scenario on a fresh robot with a mock slave and
records it; `behaviour(recording, robot_id)` reduces a recording to what a robot decided: the
accepted commands and the targets it sent, with times relative to the first input;
`replay_session` re-drives a recorded session into a fresh robot and returns its recording.
Under `trio.testing.MockClock` the two behaviours match message for message.
"""

from __future__ import annotations

import tempfile
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import trio

from arena.drivers.mock_slave import MockSlave
from arena.recording.mcap_file import Recording, read_recording
from arena.recording.recorder import Recorder
from arena.recording.replay import redrive_session
from arena.robot.handle import Robot
from arena.robot.manager import open_manager

#: Decimal places kept when comparing times (virtual time is exact; this absorbs float noise).
TIME_DECIMALS = 9


def behaviour(recording: Recording, robot_id: str) -> list[tuple[float, str, Any]]:
    """Accepted commands and targets of one robot, times relative to its first input."""
    mine = [m for m in recording.messages if m.robot_id == robot_id]
    inputs = [m for m in mine if m.kind in ("command", "peer", "state")]
    if not inputs:
        return []
    origin = min(float(m.data["t"]) for m in inputs)
    trace: list[tuple[float, str, Any]] = []
    for message in mine:
        at = round(float(message.data["t"]) - origin, TIME_DECIMALS)
        if message.kind == "command" and message.data["accepted"]:
            goals = [(j["name"], j["value"]) for j in message.data["joints"]]
            trace.append((at, "command", (goals, message.data["duration"])))
        elif message.kind == "targets":
            targets = {k: round(v, 9) for k, v in message.data["joints"].items()}
            trace.append((at, "targets", targets))
    return trace


async def record_scenario(
    folder: Path,
    scenario: Callable[[Robot], Awaitable[None]],
    *,
    robot_type: str = "so-arm100",
    robot_id: str = "arm",
    **recorder_options: Any,
) -> list[Path]:
    """Run `scenario` on a fresh robot with a mock slave, recording into `folder`; the files."""
    recorder = Recorder(folder, flush_interval=0.05, **recorder_options)
    async with trio.open_nursery() as nursery:
        await nursery.start(recorder.run)
        async with open_manager() as manager:
            manager.on_create.append(recorder.follow)
            robot = await manager.create_robot(robot_type, robot_id=robot_id)
            await robot.attach_slave(MockSlave())
            await scenario(robot)
        nursery.cancel_scope.cancel()
    return recorder.writer.files


async def replay_session(recording: Recording, source: str, *, settle: float = 5.0) -> Recording:
    """Re-drive `source`'s session into a fresh robot of the same type; its recording."""
    robot_type = recording.metadata.get(f"robot/{source}", {}).get("robot_type", "so-arm100")

    async def redrive(robot: Robot) -> None:
        await redrive_session(recording, source, robot)
        await trio.sleep(settle)

    with tempfile.TemporaryDirectory() as scratch:
        (path,) = await record_scenario(
            Path(scratch), redrive, robot_type=robot_type, robot_id=source
        )
        return read_recording(path)
