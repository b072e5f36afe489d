"""Recordings to LeRobot datasets and back, checked with LeRobot's own loader.

A real session (server on 127.0.0.1, a test-pattern camera, a WebSocket master, episodes) is
exported with `arena export --format lerobot`; `LeRobotDataset(repo_id, root=...)` loads it.
Every value is compared with what the test itself reads out of the recording.
"""

from __future__ import annotations

import json
import math
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import trio
from trio.testing import MockClock
from trio_websocket import open_websocket_url

from arena import cli
from arena.recording import images
from arena.recording.mcap_file import read_recording
from arena.recording.replay import ReplayMaster, recorded_commands
from arena.robot.manager import open_manager
from arena.robot.model import load_robot_model
from arena.robot.motion import Command
from arena.sensors.sources import read_pattern_counter
from tests.conftest import RecordingSlave, RunningServer, eventually, need
from tests.scenarios import record_scenario
from tests.test_cameras import TEST_CAMERA, jpeg_rgb
from tests.test_recording import session_scenario

lerobot_dataset = need("lerobot.datasets.lerobot_dataset", "lerobot")

MODEL = load_robot_model("so-arm100")
JOINTS = [joint.name for joint in MODEL.joints]
FEATURES = [
    "shoulder_pan.pos",
    "shoulder_lift.pos",
    "elbow_flex.pos",
    "wrist_flex.pos",
    "wrist_roll.pos",
    "gripper.pos",
]
FPS = 30
#: Degrees within which a replayed stream's targets pass by each of its actions (4.0 at worst
#: measured: the trajectory rounds off the recorded 20 fps steps; see
#: `test_import_then_replay_under_mock_clock_gives_the_dataset_actions`).
PASSES_BY = 4.5
JAW = MODEL.joint("Jaw")
assert JAW is not None


def pose(t: float) -> list[dict[str, float]]:
    """A gentle sweep of every joint (degrees), well inside the limits and the workspace."""
    values = [10 * math.sin(2 * math.pi * t), 5 * math.sin(t), -5 * math.sin(t), 5, 0, 0]
    values[5] = JAW.lower + (JAW.upper - JAW.lower) * (0.5 + 0.3 * math.sin(3 * t))
    return [{"name": name, "value": value} for name, value in zip(JOINTS, values, strict=True)]


async def drive(master: Any, seconds: float) -> None:
    """Send poses at about 50 a second (the rate only sets how dense the data is)."""
    start = trio.current_time()
    while (now := trio.current_time() - start) < seconds:
        await master.send_message(json.dumps({"type": "command", "data": {"joints": pose(now)}}))
        await trio.sleep(0.02)


@pytest.fixture
async def session_file(start_server: Callable[..., Any]) -> AsyncIterator[Path]:
    """Two kept episodes and a discarded one, with a camera and a WebSocket master."""
    server: RunningServer = await start_server(demo=True)
    base = "/api/robots/demo-arm"
    async with server.client() as http:
        assert (await http.post(f"{base}/cameras", json=TEST_CAMERA)).status_code == 201
        camera = server.app.cameras.get("demo-arm", "front")
        await eventually(lambda: camera.frames > 0)
        url = server.ws_url + "/ws/master/demo-arm?acks=false&joint_states=false"
        async with open_websocket_url(url) as master:
            # every stream has data before the first episode: a frame (above), a command, and
            # the slave's report of the pose it asked for
            first = pose(0.0)
            await master.send_message(json.dumps({"type": "command", "data": {"joints": first}}))
            robot = server.app.manager.get("demo-arm")
            jaw = next(goal["value"] for goal in first if goal["name"] == "Jaw")
            await eventually(lambda: robot.snapshot().joint("Jaw").real_value == jaw)
            for task, keep in (("pick up the cube", True), ("wave", False), ("stack", True)):
                started = await http.post(f"{base}/episodes/start", json={"task": task})
                assert started.status_code == 201
                await drive(master, 1.0)
                ended = await http.post(f"{base}/episodes/{'stop' if keep else 'discard'}")
                assert ended.status_code == 200
                await drive(master, 0.2)
        name = (await http.post("/api/recordings/current/stop")).json()["stopped"]
    yield Path(server.app.recorder.folder) / name


def newest(times: list[int], values: list[Any], at: int) -> Any:
    """The value recorded last at or before `at`."""
    found = [v for t, v in zip(times, values, strict=True) if t <= at]
    assert found, f"nothing recorded before {at}"
    return found[-1]


def lerobot_units(joints: dict[str, float]) -> list[float]:
    values = [joints[name] for name in JOINTS]
    values[5] = (values[5] - JAW.lower) / (JAW.upper - JAW.lower) * 100
    return values


async def test_export_is_a_lerobot_dataset_with_the_recorded_values(
    session_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "dataset"
    args = ["export", str(session_file), "--format", "lerobot", "--robot", "demo-arm"]
    code = cli.main([*args, "-o", str(out), "--fps", str(FPS), "--repo-id", "lab/so100-cube"])
    assert code == 0, capsys.readouterr().err
    assert "2 episodes" in capsys.readouterr().out

    recording = read_recording(session_file)
    messages = recording.messages
    assert all(m.data["accepted"] for m in messages if m.kind == "command")
    marks = [m for m in messages if m.kind == "episode"]
    kept = [
        (start, end)
        for start, end in zip(marks[::2], marks[1::2], strict=True)
        if end.data["change"] == "stop"
    ]
    assert [start.data["task"] for start, _ in kept] == ["pick up the cube", "stack"]
    commands = [m for m in messages if m.kind == "command"]
    states = [
        m for m in messages if m.kind == "joint_states" and m.data["slave_id"] == "demo-mock-slave"
    ]
    frames = [v for v in recording.views if v.topic == "/robots/demo-arm/cameras/front"]

    dataset = lerobot_dataset.LeRobotDataset("lab/so100-cube", root=out, video_backend="pyav")
    assert dataset.fps == FPS
    assert dataset.meta.robot_type == "so100_follower"
    assert dataset.meta.features["action"]["names"] == FEATURES
    assert dataset.meta.features["observation.state"]["names"] == FEATURES
    assert dataset.meta.video_keys == ["observation.images.front"]
    assert dataset.num_episodes == 2
    rows = list(dataset.hf_dataset.with_format(None))
    tasks = {
        int(i): t
        for t, i in zip(dataset.meta.tasks.index, dataset.meta.tasks["task_index"], strict=True)
    }
    step = 1e9 / FPS
    at = 0
    for episode, (start, end) in enumerate(kept):
        count = int((end.log_time - start.log_time) / step + 1e-6) + 1
        ours = [row for row in rows if row["episode_index"] == episode]
        assert len(ours) == count
        assert dataset.meta.episodes["dataset_from_index"][episode] == at
        assert dataset.meta.episodes["dataset_to_index"][episode] == at + count
        at += count
        assert {tasks[row["task_index"]] for row in ours} == {start.data["task"]}
        for row in ours:
            assert row["frame_index"] == round(row["timestamp"] * FPS)
            when = start.log_time + round(row["frame_index"] * step)
            commanded = newest(
                [c.log_time for c in commands],
                [{j["name"]: j["value"] for j in c.data["joints"]} for c in commands],
                when,
            )
            measured = newest(
                [s.log_time for s in states], [s.data["joints"] for s in states], when
            )
            assert np.allclose(row["action"], lerobot_units(commanded), atol=1e-4)
            assert np.allclose(row["observation.state"], lerobot_units(measured), atol=1e-4)

    # one decoded video frame: the right shape, and the camera frame of its time
    index = len(rows) - 5
    item = dataset[index]
    image = item["observation.images.front"]
    assert tuple(image.shape) == (3, TEST_CAMERA["height"], TEST_CAMERA["width"])
    row = rows[index]
    start = kept[row["episode_index"]][0]
    when = start.log_time + round(row["frame_index"] * step)
    jpeg = newest([f.log_time for f in frames], [f.data for f in frames], when)
    expected = read_pattern_counter(jpeg_rgb(images.decode(jpeg).data))
    pixels = (image.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
    assert read_pattern_counter(pixels) == expected


async def test_import_then_replay_under_mock_clock_gives_the_dataset_actions(
    session_file: Path, tmp_path: Path
) -> None:
    out = tmp_path / "dataset"
    args = ["export", str(session_file), "--format", "lerobot", "--robot", "demo-arm"]
    assert cli.main([*args, "-o", str(out), "--fps", "20"]) == 0
    imported = tmp_path / "episode1.mcap"
    assert cli.main(["import-dataset", str(out), "--episode", "1", "-o", str(imported)]) == 0

    dataset = lerobot_dataset.LeRobotDataset("local/dataset", root=out, episodes=[1])
    rows = [r for r in dataset.hf_dataset.with_format(None) if r["episode_index"] == 1]
    recording = read_recording(imported)
    commands = recorded_commands(recording, "dataset-arm")
    assert len(commands) == len(rows)
    for timed, row in zip(commands, rows, strict=True):
        assert timed.at == pytest.approx(row["timestamp"] - rows[0]["timestamp"], abs=1e-6)
        values = {goal.name: goal.value for goal in timed.command.joints}
        assert np.allclose(lerobot_units(values), row["action"], atol=1e-4)
    marks = [m.data["task"] for m in recording.messages if m.kind == "episode"]
    assert marks == ["stack", "stack"]

    def at_pose(slave: RecordingSlave, command: Command) -> Callable[[], bool]:
        """A check: the slave's newest target is the command's pose."""
        goals = {goal.name: goal.value for goal in command.joints}
        return lambda: (
            bool(slave.targets)
            and all(slave.targets[-1][1][name] == value for name, value in goals.items())
        )

    async def replay() -> list[dict[str, float]]:
        slave = RecordingSlave()
        async with trio.open_nursery() as nursery:
            async with open_manager() as manager:
                robot = await manager.create_robot("so-arm100", robot_id="dataset-arm")
                await robot.attach_slave(slave)
                await robot.command(commands[0].command)  # from the episode's first pose
                await eventually(at_pose(slave, commands[0].command), what="the first pose")
                master = ReplayMaster(commands)
                await robot.attach_master(master)
                await eventually(lambda: robot.snapshot().master is None, what="the replay")
                await eventually(at_pose(slave, commands[-1].command), what="the last pose")
            nursery.cancel_scope.cancel()
        return [joints for _, joints in slave.targets]

    def replay_alone() -> list[dict[str, float]]:  # a trio run of its own, on virtual time
        return trio.run(replay, clock=MockClock(autojump_threshold=0))

    first = await trio.to_thread.run_sync(replay_alone)
    second = await trio.to_thread.run_sync(replay_alone)
    assert first == second  # deterministic
    # The arm passes by every action, in order, and ends exactly on the last. By, not
    # through: the replay is a 20 fps stream, which the trajectory follows at the stream's
    # velocity instead of stopping at each action (specs/motion.md), so a target at the
    # 100 Hz ticks comes within `PASSES_BY` degrees of each action on every joint.
    # The episode's second action lies some 16 degrees from the first and from the third (its
    # Jaw 21 -> 5 -> 10 degrees in 0.1 s): a dip and back no jerk-limited arm makes, which
    # it cuts short (passing it 6-7 degrees off); every action from the third on is passed by.
    reached = 0
    for timed in commands[2:]:
        goal = {g.name: g.value for g in timed.command.joints}

        def off(targets: dict[str, float], goal: dict[str, float] = goal) -> float:
            return max(abs(targets[name] - value) for name, value in goal.items())

        near = [k for k in range(reached, len(first)) if off(first[k]) <= PASSES_BY]
        assert near, f"the replay never came near {goal}"
        reached = near[0]
    last = {g.name: g.value for g in commands[-1].command.joints}
    assert all(first[-1][name] == value for name, value in last.items())


async def test_export_says_what_is_missing(
    autojump_clock: MockClock, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (plain,) = await record_scenario(tmp_path / "plain", session_scenario, foxglove=False)
    args = ["export", str(plain), "--format", "lerobot", "--fps", "10"]
    # a robot that is not in the file
    assert cli.main([*args, "--robot", "nobody", "-o", str(tmp_path / "a")]) == 2
    err = capsys.readouterr().err
    assert "'nobody' (--robot) is not in" in err and "it holds arm" in err
    # no camera: a dataset of action and state, and a note that says so
    assert cli.main([*args, "--robot", "arm", "-o", str(tmp_path / "b")]) == 0
    assert "no camera was recorded for 'arm'" in capsys.readouterr().err
    whole = lerobot_dataset.LeRobotDataset("arena/arm", root=tmp_path / "b")
    assert whole.meta.video_keys == [] and whole.num_episodes == 1
    assert list(whole.meta.tasks.index) == ["teleoperation"]
    # a file cut by a crash: exported up to its last complete record, with a note
    cut = tmp_path / "cut.mcap"
    data = plain.read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    assert (
        cli.main([*args[:1], str(cut), *args[2:], "--robot", "arm", "-o", str(tmp_path / "c")]) == 0
    )
    assert "cut.mcap was cut short" in capsys.readouterr().err
    part = lerobot_dataset.LeRobotDataset("arena/arm", root=tmp_path / "c")
    assert 0 < part.num_frames < whole.num_frames
    # a folder in use, and two files for csv
    assert cli.main([*args, "--robot", "arm", "-o", str(tmp_path / "b")]) == 2
    assert "is not empty" in capsys.readouterr().err
    assert cli.main(["export", str(plain), str(plain)]) == 2
    assert "csv, jsonl and ros2 take one file" in capsys.readouterr().err
    # import: not a dataset, no such episode
    assert cli.main(["import-dataset", str(tmp_path), "-o", str(tmp_path / "x.mcap")]) == 2
    assert "not a LeRobot dataset" in capsys.readouterr().err
    assert cli.main(["import-dataset", str(tmp_path / "b"), "--episode", "7", "-o", "x.mcap"]) == 2
    assert "episode 7" in capsys.readouterr().err


async def commanded_and_reported(server: RunningServer, http: Any) -> None:
    """A command and the slave's report of it: every stream has data before an episode."""
    robot = server.app.manager.get("demo-arm")
    moved = await http.put(
        "/api/robots/demo-arm/joints", json={"joints": [{"name": "Jaw", "value": 5}]}
    )
    assert moved.is_success, moved.text
    await eventually(lambda: robot.snapshot().joint("Jaw").real_value == 5)


async def camera_running(server: RunningServer, http: Any, body: dict[str, Any]) -> Any:
    """Attach the camera `body` to demo-arm and return it once it delivers frames."""
    made = await http.post("/api/robots/demo-arm/cameras", json=body)
    assert made.status_code == 201, made.text
    camera = server.app.cameras.get("demo-arm", body["name"])
    await eventually(lambda: camera.frames > 3, what="the camera's first frames")
    return camera


async def test_a_camera_that_changed_size_is_refused_before_anything_is_written(
    start_server: Callable[..., Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    server: RunningServer = await start_server(demo=True)
    base = "/api/robots/demo-arm"
    async with server.client() as http:
        await commanded_and_reported(server, http)
        for width, height in ((64, 48), (32, 32)):  # the same camera, re-attached smaller
            body = {**TEST_CAMERA, "width": width, "height": height}
            camera = await camera_running(server, http, body)
            assert (await http.post(f"{base}/episodes/start", json={"task": "t"})).is_success
            await eventually(lambda camera=camera: camera.frames > 10)  # type: ignore[misc]
            assert (await http.post(f"{base}/episodes/stop")).is_success
            assert (await http.delete(f"{base}/cameras/front")).is_success
        name = (await http.post("/api/recordings/current/stop")).json()["stopped"]
    recording = Path(server.app.recorder.folder) / name
    out = tmp_path / "dataset"
    args = ["export", str(recording), "--format", "lerobot", "--robot", "demo-arm", "-o"]
    assert cli.main([*args, str(out), "--fps", "10"]) == 2
    err = capsys.readouterr().err
    assert "Camera 'front' is 32x32 in episode 1 but 64x48 in episode 0" in err, err
    assert not out.exists()  # nothing half-written blocks a retry


async def test_an_episode_of_one_frame_is_left_out_with_a_note(
    start_server: Callable[..., Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # A sentry detached just after an episode began, or a start and stop clicked at once: one
    # frame at the dataset's rate. LeRobot's writer cannot finish a video episode of one frame.
    server: RunningServer = await start_server(demo=True)
    base = "/api/robots/demo-arm"
    async with server.client() as http:
        camera = await camera_running(server, http, TEST_CAMERA)
        await commanded_and_reported(server, http)
        assert (await http.post(f"{base}/episodes/start", json={"task": "long"})).is_success
        # at least three samples at 1 fps: frames of 2.1 s recorded (the data itself, however
        # slowly a loaded machine delivers it)
        seen = camera.frames
        more = round(2.1 * TEST_CAMERA["fps"])
        await eventually(lambda: camera.frames >= seen + more, what="2.1 s of frames")
        assert (await http.post(f"{base}/episodes/stop")).is_success
        assert (await http.post(f"{base}/episodes/start", json={"task": "blink"})).is_success
        assert (await http.post(f"{base}/episodes/stop")).is_success
        name = (await http.post("/api/recordings/current/stop")).json()["stopped"]
    recording = Path(server.app.recorder.folder) / name
    marks = [m for m in read_recording(recording).messages if m.kind == "episode"]
    blink = marks[-1].log_time - marks[-2].log_time
    out = tmp_path / "dataset"
    args = ["export", str(recording), "--format", "lerobot", "--robot", "demo-arm", "-o"]
    assert cli.main([*args, str(out), "--fps", "1"]) == 0, capsys.readouterr().err
    err = capsys.readouterr().err
    lerobot_dataset = pytest.importorskip("lerobot.datasets.lerobot_dataset")
    dataset = lerobot_dataset.LeRobotDataset("arena/demo-arm", root=out, video_backend="pyav")
    if blink < 1e9:  # one sample at 1 fps (a loaded machine may take a second to stop it)
        assert dataset.num_episodes == 1, err
        assert "episode 1 has one frame at 1 fps: left out" in err, err
    else:
        assert dataset.num_episodes == 2, err
