"""Corrections are data: a session on a real server where a WebSocket master intervenes twice
on a playing sequence is recorded (the intervention's start and end on their own channel),
exported with `arena export --format lerobot` and read back by LeRobot's own
`LeRobotDataset`: the feature `intervention` is true exactly on the frames the intervening
master commanded, and `--corrections-only` writes each correction as an episode of its own
holding the human's commands. Every expectation is read out of the recording by the test."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import trio
from trio_websocket import open_websocket_url

from arena import cli
from arena.recording.mcap_file import RecordedMessage, read_recording
from tests.conftest import RunningServer, eventually, need
from tests.test_dataset import FPS, drive, lerobot_units, newest
from tests.test_server_ws import receive

lerobot_dataset = need("lerobot.datasets.lerobot_dataset", "lerobot")

BASE = "/api/robots/demo-arm"
SEQUENCE = {"type": "mock-sequence", "sequences": ["gentle-wave"], "loop": True}
STEP = 1e9 / FPS


def windows(messages: list[RecordedMessage]) -> list[tuple[int, int]]:
    """Each intervention from the first command of its master the robot accepted to its end."""
    found = []
    for started in [m for m in messages if m.kind == "intervention"]:
        if started.data["change"] != "started":
            continue
        master = started.data["master"]
        ended = next(
            m
            for m in messages
            if m.kind == "intervention"
            and m.data["change"] == "ended"
            and m.log_time >= started.log_time
        )
        first = next(
            m
            for m in messages
            if m.kind == "command"
            and m.data["source"] == master
            and m.data["accepted"]
            and m.log_time >= started.log_time
        )
        found.append((first.log_time, ended.log_time))
    return found


def flag(row: dict[str, Any]) -> bool:
    return bool(np.asarray(row["intervention"]).reshape(-1)[0])


@pytest.fixture
async def corrected(start_server: Callable[..., Any]) -> Path:
    """An episode of a looping sequence corrected twice over a WebSocket, then one without."""
    server: RunningServer = await start_server(demo=True)
    robot = server.app.manager.get("demo-arm")
    async with server.client() as http:
        assert (await http.post(f"{BASE}/master", json=SEQUENCE)).status_code == 201
        # every stream has data before the episode: the sequence's commands, the slave's report
        await eventually(lambda: robot.snapshot().joint("Jaw").real_value is not None)
        assert (await http.post(f"{BASE}/episodes/start", json={"task": "wave"})).is_success
        await trio.sleep(0.4)
        url = f"{server.ws_url}/ws/master/demo-arm?intervene=1&id=fixer&acks=false"
        for _ in range(2):
            async with open_websocket_url(url) as ws:
                await receive(ws, "state")
                await drive(ws, 0.5)
                await ws.send_message(json.dumps({"type": "release"}))
                assert (await receive(ws, "released"))["data"]["mode"] == "mastered"
            await trio.sleep(0.4)
        assert (await http.post(f"{BASE}/episodes/stop")).is_success
        assert (await http.post(f"{BASE}/episodes/start", json={"task": "rest"})).is_success
        await trio.sleep(0.4)
        assert (await http.post(f"{BASE}/episodes/stop")).is_success
        name = (await http.post("/api/recordings/current/stop")).json()["stopped"]
    return Path(server.app.recorder.folder) / name


async def test_the_intervention_frames_are_marked_and_corrections_export_alone(
    corrected: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    messages = read_recording(corrected).messages
    marks = [m for m in messages if m.kind == "episode"]
    episodes = [(marks[0].log_time, marks[1].log_time), (marks[2].log_time, marks[3].log_time)]
    fixes = windows(messages)
    assert len(fixes) == 2 and all(episodes[0][0] < a < b < episodes[0][1] for a, b in fixes)
    commands = [m for m in messages if m.kind == "command" and m.data["accepted"]]

    # The whole session: `intervention` true exactly where the intervening master commanded.
    out = tmp_path / "all"
    args = ["export", str(corrected), "--format", "lerobot", "--robot", "demo-arm"]
    assert cli.main([*args, "-o", str(out), "--fps", str(FPS)]) == 0, capsys.readouterr().err
    dataset = lerobot_dataset.LeRobotDataset("arena/demo-arm", root=out)
    feature = dataset.meta.features["intervention"]
    assert feature["dtype"] == "bool" and tuple(feature["shape"]) == (1,)
    rows = list(dataset.hf_dataset.with_format(None))
    marked = 0
    for episode, (start, _) in enumerate(episodes):
        ours = [row for row in rows if row["episode_index"] == episode]
        assert ours
        for row in ours:
            when = start + round(row["frame_index"] * STEP)
            expected = any(a <= when < b for a, b in fixes)
            assert flag(row) is expected, (episode, row["frame_index"])
            marked += expected
    assert marked >= 2 * 0.4 * FPS  # both corrections, most of their half second each

    # Only the corrections: each an episode of its own, every frame the human's command.
    alone = tmp_path / "corrections"
    code = cli.main([*args, "-o", str(alone), "--fps", str(FPS), "--corrections-only"])
    assert code == 0, capsys.readouterr().err
    assert "2 episodes" in capsys.readouterr().out
    dataset = lerobot_dataset.LeRobotDataset("arena/demo-arm", root=alone)
    assert dataset.num_episodes == 2
    rows = list(dataset.hf_dataset.with_format(None))
    for episode, (start, end) in enumerate(fixes):
        ours = [row for row in rows if row["episode_index"] == episode]
        assert len(ours) == int((end - start) / STEP + 1e-6) + 1
        for row in ours:
            assert flag(row)
            when = start + round(row["frame_index"] * STEP)
            source, joints = newest(
                [c.log_time for c in commands],
                [
                    (c.data["source"], {j["name"]: j["value"] for j in c.data["joints"]})
                    for c in commands
                ],
                when,
            )
            assert source == "fixer"
            assert np.allclose(row["action"], lerobot_units(joints), atol=1e-4)


async def test_each_correction_exported_alone_keeps_its_episodes_environment_state(
    corrected: Path, tmp_path: Path
) -> None:
    """`--corrections-only` with a task state per episode (a reach target, as `arena learn
    reach --dagger` exports its corrections): each correction's frames carry the state of
    the episode it corrected, not of the episode its own number happens to name."""
    from arena.recording.dataset import export_lerobot

    messages = read_recording(corrected).messages
    starts = [m for m in messages if m.kind == "episode" and m.data["change"] == "start"]
    corrected_index, other_index = (int(m.data["index"]) for m in starts)
    states = {corrected_index: [0.1, 0.2, 0.3], other_index: [0.9, 0.8, 0.7]}
    out = tmp_path / "corrections"
    exported = export_lerobot(
        [corrected],
        "demo-arm",
        out,
        fps=FPS,
        environment=states,
        corrections_only=True,
        say=lambda line: None,
    )
    assert len(exported.episodes) == 2
    dataset = lerobot_dataset.LeRobotDataset(exported.repo_id, root=out)
    rows = list(dataset.hf_dataset.with_format(None))
    assert {row["episode_index"] for row in rows} == {0, 1}
    for row in rows:  # both corrections were made in the first episode
        assert np.allclose(row["observation.environment_state"], states[corrected_index])
        assert flag(row)
