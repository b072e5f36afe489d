"""Every offline command (`inspect`, `timeline`, `export`, `plot`, `recover`) on recordings of
every kind the server writes: one real recording made by a running server that holds every
record kind (episodes, policy inferences, faults, a group's e-stop, who did what, a guard's
stop, camera frames, Foxglove's view), and the golden files shipped in recordings/golden."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import httpx
import pytest
import trio
from trio_websocket import open_websocket_url

from arena import cli
from arena.policy.master import PolicyMaster, PolicySettings
from arena.recording.mcap_file import read_recording
from arena.recording.records import RECORD_TYPES, camera_of_topic
from arena.robot.events import MotionStopped, TargetsSent
from arena.server.config import ServerConfig
from arena.server.run import run_server
from tests.conftest import eventually, need
from tests.test_guard_stops import SLOW, block_the_way
from tests.test_policy_master import FakeWorker, frames

GOLDEN = Path(__file__).resolve().parent.parent / "recordings" / "golden"


async def record_every_kind(folder: Path) -> Path:
    """A running server (real sockets, real recorder) driven through every kind of record it
    writes: two robots, slaves, a camera, an episode, a policy master and an intervention on it,
    a slave's fault, a group's e-stop and reset, a motion the guard stops on its way; the
    finished file."""
    config = ServerConfig(port=0, recordings_dir=str(folder))
    stop, done = trio.Event(), trio.Event()
    async with trio.open_nursery() as nursery:

        async def serve(task_status: trio.TaskStatus[tuple[Any, list[str]]]) -> None:
            try:
                await run_server(config, stop=stop, task_status=task_status)
            finally:
                done.set()

        app, urls = await nursery.start(serve)
        url = urls[0]
        ws_url = "ws" + url[len("http") :]
        async with httpx.AsyncClient(base_url=url, timeout=30) as http:

            async def ok(method: str, path: str, body: object = None) -> Any:
                reply = await http.request(method, path, json=body)
                assert reply.status_code < 300, (path, reply.text)
                return reply.json()

            await ok("POST", "/api/robots", {"robot_type": "so-arm100", "id": "arm"})
            await ok("POST", "/api/robots", {"robot_type": "so-101", "id": "follower"})
            for robot in ("arm", "follower"):
                await ok("POST", f"/api/robots/{robot}/slaves", {"type": "mock-slave"})
            camera = {"name": "front", "source": "test-pattern", "fps": 10}
            await ok("POST", "/api/robots/arm/cameras", camera | {"width": 32, "height": 32})
            await ok("POST", "/api/robots/arm/episodes/start", {"task": "wave"})
            body = {"joints": [{"name": "Rotation", "value": 10}], "duration": 200}
            await ok("PUT", "/api/robots/arm/joints", body)
            await ok(
                "PUT", "/api/robots/follower/joints", {"joints": [{"name": "gripper", "value": 60}]}
            )

            async def framed() -> bool:
                return int((await ok("GET", "/api/robots/arm/cameras/front"))["frames"]) >= 2

            await eventually(framed, timeout=30)
            await ok("POST", "/api/robots/arm/episodes/stop")
            # A slave's fault, as a WebSocket arm reports it.
            async with open_websocket_url(ws_url + "/ws/slave/arm") as slave:
                fault = {"code": "SERVO_HOT", "message": "Elbow is warm", "severity": "warning"}
                await slave.send_message(
                    json.dumps({"type": "error", "data": fault | {"joint": "Elbow"}})
                )

                async def faulted() -> bool:
                    slaves = (await ok("GET", "/api/robots/arm"))["slaves"]
                    return any(s["last_error"] for s in slaves)

                await eventually(faulted, timeout=30)
            await ok("POST", "/api/robots/arm/reset")  # (a slave that goes is a loss)
            # A policy master (its worker stood in for: torch stays out of this process).
            robot = app.manager.get("arm")
            worker = FakeWorker(latency=0.01)

            async def start() -> FakeWorker:
                return worker

            policy = PolicyMaster(
                PolicySettings(Path("unused"), task="wave", fps=30.0),
                robot.model,
                frames(("front",)),
                start,
            )
            await policy.prepare()
            await robot.attach_master(policy, master_id=policy.master_id)
            await eventually(lambda: len(worker.observations) >= 3, timeout=30)
            # An operator's correction of it (an intervention, started and ended).
            await ok("POST", "/api/robots/arm/intervention", {})
            await ok("DELETE", "/api/robots/arm/intervention")
            await ok("DELETE", "/api/robots/arm/master")
            # A group's e-stop and reset.
            await ok("POST", "/api/groups", {"id": "line", "members": ["arm", "follower"]})
            await ok("POST", "/api/groups/line/estop", {"reason": "line stop"})
            await ok("POST", "/api/groups/line/reset")
            # A motion the guard stops on its way: a slow turn, then a pillar in its way.
            with robot.subscribe(kinds=[TargetsSent, MotionStopped]) as seen:
                await ok("PUT", "/api/robots/arm/joints", SLOW)
                await block_the_way(http, robot, seen)
                with trio.fail_after(30):
                    while not isinstance(await seen.get(), MotionStopped):
                        pass
            stopped = await ok("POST", "/api/recordings/current/stop")
        stop.set()
        await done.wait()
    assert stopped["stopped"], stopped
    return folder / str(stopped["stopped"])


@pytest.fixture(scope="module")
def every_kind(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The recording of `record_every_kind`, made once for the module."""
    return trio.run(record_every_kind, tmp_path_factory.mktemp("every-kind"))


def test_the_recording_holds_every_kind_the_server_writes(every_kind: Path) -> None:
    # So that the commands below meet each of them (a kind added later must be added there).
    recording = read_recording(every_kind)
    assert {m.kind for m in recording.messages} == set(RECORD_TYPES)
    assert any(camera_of_topic(view.topic) for view in recording.views)
    assert {view.topic.rsplit("/", 1)[1] for view in recording.views} >= {"tf", "log"}
    assert {m.robot_id for m in recording.messages} == {"arm", "follower"}


RECORDINGS = ["every-kind", "gentle-wave", "manual-estop-reset"]


@pytest.fixture(params=RECORDINGS)
def recording_file(request: pytest.FixtureRequest, every_kind: Path) -> Path:
    name = request.param
    return every_kind if name == "every-kind" else GOLDEN / f"{name}.mcap"


def run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    """`arena ARGV` in this process, which must succeed: its standard output."""
    status = cli.main(argv)
    out, err = capsys.readouterr()
    assert status == 0, err
    return out


def test_inspect(recording_file: Path, capsys: pytest.CaptureFixture[str]) -> None:
    recording = read_recording(recording_file)
    out = run(["inspect", str(recording_file)], capsys)
    assert out.startswith(f"file       {recording_file.name}")
    summary = json.loads(run(["inspect", str(recording_file), "--json"], capsys))
    assert summary["arena_messages"] == len(recording.messages)
    assert set(summary["robots"]) == {m.robot_id for m in recording.messages}
    faults = [m for m in recording.messages if m.kind == "fault" and not m.data.get("cleared")]
    assert len(summary["faults"]) == len(faults)


def test_timeline(recording_file: Path, capsys: pytest.CaptureFixture[str]) -> None:
    recording = read_recording(recording_file)
    lines = run(["timeline", str(recording_file)], capsys).splitlines()
    assert len(lines) == len(recording.messages)
    # one line per record, each naming its robot and kind
    for line, message in zip(lines, recording.messages, strict=True):
        assert line.split()[1:3] == [message.robot_id, message.kind]
    robot = recording.messages[0].robot_id
    mine = run(["timeline", str(recording_file), "--robot", robot, "--to", "1"], capsys)
    assert all(line.split()[1] == robot for line in mine.splitlines())


def test_timeline_says_what_episodes_and_policies_did(
    every_kind: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    lines = run(["timeline", str(every_kind), "--robot", "arm"], capsys).splitlines()
    episodes = [line for line in lines if line.split()[2] == "episode"]
    assert "start episode 0: wave" in episodes[0] and "stop episode 0: wave" in episodes[1]
    policy = next(line for line in lines if line.split()[2] == "policy")
    assert "policy:act:0123456789ab step" in policy and "chunk 10" in policy


@pytest.mark.parametrize("fmt", ["csv", "jsonl"])
def test_export(recording_file: Path, fmt: str, capsys: pytest.CaptureFixture[str]) -> None:
    recording = read_recording(recording_file)
    out = run(["export", str(recording_file), "--format", fmt], capsys)
    rows = out.splitlines()
    assert len(rows) == len(recording.messages) + (fmt == "csv")
    if fmt == "jsonl":
        assert [json.loads(row)["topic"] for row in rows] == [m.topic for m in recording.messages]


def test_export_ros2(
    recording_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    need("rosbags", "ros2")
    out = tmp_path / "bag.mcap"
    counts = run(["export", str(recording_file), "--format", "ros2", "-o", str(out)], capsys)
    assert out.stat().st_size > 0 and "joint_states" in counts


def test_export_lerobot(
    recording_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    need("lerobot", "lerobot")
    robot = read_recording(recording_file).messages[0].robot_id
    folder = tmp_path / "data"
    argv = ["export", str(recording_file), "--format", "lerobot", "--robot", robot]
    run([*argv, "-o", str(folder), "--fps", "10"], capsys)
    assert (folder / "meta" / "info.json").exists()


def test_plot(recording_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    need("matplotlib", "plot")
    for robot in dict.fromkeys(m.robot_id for m in read_recording(recording_file).messages):
        image = tmp_path / f"{robot}.png"
        run(["plot", str(recording_file), "--robot", robot, "-o", str(image)], capsys)
        assert image.read_bytes().startswith(b"\x89PNG")


def test_recover(recording_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    original = read_recording(recording_file)
    out = tmp_path / "again.mcap"
    run(["recover", str(recording_file), "-o", str(out)], capsys)
    again = read_recording(out)
    assert [(m.topic, m.data) for m in again.messages] == [
        (m.topic, m.data) for m in original.messages
    ]
    assert len(again.views) == len(original.views)
