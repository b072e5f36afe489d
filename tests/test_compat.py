"""Against LeRobot 0.6 itself (`make compat`, which builds its Python with tools/compat.sh and
runs these; `make test` leaves them out: marker `compat`).

ACT and diffusion policies saved by LeRobot 0.6 and by Arena's own 0.4.4 are run by a real server
whose worker is either, the two workers answer one observation with the same actions, and
datasets go both ways.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
import trio

from arena import cli
from arena.policy.process import PolicyProcess, worker_command
from arena.policy.wire import Observe
from arena.recording.mcap_file import read_recording
from arena.recording.replay import recorded_commands
from arena.robot.events import CommandHandled
from arena.sensors.sources import JpegEncoder, pattern_image
from tests.conftest import REPOSITORY, missing, need
from tests.test_dataset import session_file
from tests.test_policy_server import Start, attach, make_policy, next_event, ready

pytestmark = pytest.mark.compat
__all__ = ["session_file"]  # the fixture, from tests/test_dataset.py

#: The LeRobot 0.6 Python tools/compat.sh makes (or another, named by ARENA_COMPAT_PYTHON).
COMPAT_PYTHON = Path(os.environ.get("ARENA_COMPAT_PYTHON", REPOSITORY / ".compat" / "python"))


@pytest.fixture(scope="module")
def newer() -> str:
    """The LeRobot 0.6 Python."""
    need("lerobot", "lerobot")
    if not COMPAT_PYTHON.exists():
        missing(f"no {COMPAT_PYTHON}: `make compat` builds it")
    return str(COMPAT_PYTHON)


@pytest.fixture(scope="module")
def saved(newer: str, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The same tiny ACT and diffusion policies saved by Arena's LeRobot (0.4.4) and by 0.6."""
    folder = tmp_path_factory.mktemp("saved")
    return {
        f"{kind}-{by}": make_policy(
            folder / f"{kind}{by}", "--type", kind, python=newer if by == "0.6" else sys.executable
        )
        for kind in ("act", "diffusion")
        for by in ("0.4", "0.6")
    }


@pytest.mark.parametrize("kind", ["act", "diffusion"])
@pytest.mark.parametrize("by", ["0.4", "0.6"])
@pytest.mark.parametrize("worker", ["0.4", "0.6"])
async def test_a_policy_either_lerobot_saved_runs_in_a_worker_of_either(
    start_server: Start, saved: dict[str, Path], newer: str, kind: str, by: str, worker: str
) -> None:
    server = await start_server(demo=True, policy_python=newer if worker == "0.6" else None)
    robot = await ready(server)
    with robot.subscribe(kinds=[CommandHandled]) as events:
        answer = await attach(server, saved[f"{kind}-{by}"])
        assert answer.status_code == 201, answer.text
        handled = await next_event(events, lambda e: isinstance(e, CommandHandled))
    assert handled.result.accepted


async def test_arena_policy_runs_a_06_policy_remotely_in_the_users_python(
    start_server: Start, saved: dict[str, Path], newer: str
) -> None:
    """`arena policy --url --policy-python`: the remote worker is the user's LeRobot 0.6, and
    the server records its inferences."""
    from arena.policy.master import PolicySettings
    from arena.policy.remote import run_remote
    from arena.robot.events import PolicyInferred

    server = await start_server(demo=True)
    robot = await ready(server)
    settings = PolicySettings(saved["act-0.6"], python=newer)
    done = trio.Event()

    async def remote() -> None:
        await run_remote(settings, server.url, "demo-arm")
        done.set()

    with robot.subscribe(kinds=[CommandHandled, PolicyInferred]) as events:
        async with trio.open_nursery() as nursery:
            nursery.start_soon(remote)
            inferred = await next_event(events, lambda e: isinstance(e, PolicyInferred))
            handled = await next_event(events, lambda e: isinstance(e, CommandHandled))
            async with server.client() as http:
                await http.post("/api/robots/demo-arm/estop", json={"reason": "test"})
            with trio.fail_after(120):
                await done.wait()
    assert inferred.policy.startswith("policy:act:") and handled.result.accepted


async def test_both_workers_answer_an_observation_with_the_same_actions(
    saved: dict[str, Path], newer: str
) -> None:
    jpeg = JpegEncoder(32, 32, 30).encode_rgb(pattern_image(7, 32, 32))  # the policy's size
    observation = Observe(0, (10.0, -20.0, 30.0, 5.0, -5.0, 40.0), {"front": jpeg}, "")
    chunks = []
    for python in (None, newer):
        worker = await PolicyProcess.start(worker_command(python))
        try:
            with trio.fail_after(120):
                loaded = await worker.load(saved["act-0.6"])
                chunks.append((loaded.lerobot, (await worker.act(observation)).actions))
        finally:
            await worker.close()
    (old, ours), (new, theirs) = chunks
    assert old.startswith("0.4") and new.startswith("0.6")
    assert len(ours) == len(theirs) == loaded.chunk_size
    # JPEG decoded by FFmpeg (0.4.4's worker has PyAV) and by Pillow (0.6's): a pixel's worth
    # of difference at most, far below an action's scale (about 30 degrees a unit here)
    for a, b in zip(ours, theirs, strict=True):
        for x, y in zip(a, b, strict=True):
            assert math.isclose(x, y, abs_tol=0.5), (ours, theirs)


#: Read in LeRobot 0.6 (by `make compat`'s Python): what a test compares with LeRobot 0.4.4's.
READ_DATASET = """
import json, sys
from lerobot.datasets.lerobot_dataset import LeRobotDataset
dataset = LeRobotDataset(sys.argv[1], root=sys.argv[2])
rows = list(dataset.hf_dataset.with_format(None))
item = dataset[len(rows) - 1]
print(json.dumps({
    "episodes": dataset.num_episodes, "fps": dataset.fps, "robot": dataset.meta.robot_type,
    "actions": [list(map(float, row["action"])) for row in rows],
    "image": list(item["observation.images.front"].shape),
}))
"""

#: Written by LeRobot 0.6: two episodes of a so-101's joints, no video.
WRITE_DATASET = """
import sys
import numpy as np
from lerobot.datasets.lerobot_dataset import LeRobotDataset
names = ["shoulder_pan.pos", "shoulder_lift.pos", "elbow_flex.pos", "wrist_flex.pos",
         "wrist_roll.pos", "gripper.pos"]
feature = {"dtype": "float32", "shape": (6,), "names": names}
dataset = LeRobotDataset.create(sys.argv[1], fps=10, root=sys.argv[2], robot_type="so101_follower",
                                features={"action": feature, "observation.state": feature},
                                use_videos=False)
for episode in range(2):
    for step in range(5):
        value = np.array([episode * 10 + step, -step, step, 0, 0, 50], np.float32)
        dataset.add_frame({"action": value, "observation.state": value, "task": "wave"})
    dataset.save_episode()
dataset.finalize()
"""


async def test_an_exported_dataset_reads_the_same_in_lerobot_06(
    session_file: Path, tmp_path: Path, newer: str
) -> None:
    lerobot_dataset = need("lerobot.datasets.lerobot_dataset", "lerobot")
    out = tmp_path / "dataset"
    args = ["export", str(session_file), "--format", "lerobot", "--robot", "demo-arm"]
    assert cli.main([*args, "-o", str(out), "--repo-id", "lab/cube"]) == 0
    read = subprocess.run(
        [newer, "-c", READ_DATASET, "lab/cube", str(out)], capture_output=True, timeout=300
    )
    assert read.returncode == 0, read.stderr.decode()[-2000:]
    theirs = json.loads(read.stdout.decode().strip().splitlines()[-1])
    ours = lerobot_dataset.LeRobotDataset("lab/cube", root=out, video_backend="pyav")
    rows = list(ours.hf_dataset.with_format(None))
    assert (theirs["episodes"], theirs["fps"], theirs["robot"]) == (
        ours.num_episodes,
        ours.fps,
        ours.meta.robot_type,
    )
    assert theirs["actions"] == [[float(v) for v in row["action"]] for row in rows]
    assert theirs["image"] == list(ours[len(rows) - 1]["observation.images.front"].shape)


#: `arena learn`'s training (arena/gym/train.py, which imports only numpy, torch and LeRobot)
#: run by LeRobot 0.6's Python on a dataset Arena exported: a few steps, saved as LeRobot saves.
TRAIN = """
import importlib.util, sys
from pathlib import Path
spec = importlib.util.spec_from_file_location("train", sys.argv[1])
train = sys.modules["train"] = importlib.util.module_from_spec(spec)
spec.loader.exec_module(train)
settings = train.TrainSettings(steps=3, batch_size=4, dim_model=32, dim_feedforward=64)
loss = train.train_act(Path(sys.argv[2]), sys.argv[4], Path(sys.argv[3]), settings, print)
print("loss", loss)
"""


async def test_arena_learns_training_runs_on_lerobot_06(tmp_path: Path, newer: str) -> None:
    """`arena learn reach`'s own data (two expert episodes in the twin, exported as it exports
    them), trained on by its training code in LeRobot 0.6."""
    need("mujoco", "physics")
    from arena.gym.learn import REPO_ID, TWIN_ROBOT, LearnSettings, collect
    from arena.recording.dataset import export_lerobot

    settings = LearnSettings(tmp_path, episodes=2)
    targets = await trio.to_thread.run_sync(collect, settings, print)
    dataset, out = tmp_path / "dataset", tmp_path / "policy"
    recordings = sorted((tmp_path / "recordings").glob("*.mcap"))
    export_lerobot(recordings, TWIN_ROBOT, dataset, fps=30, repo_id=REPO_ID, environment=targets)
    train = REPOSITORY / "arena" / "gym" / "train.py"
    ran = subprocess.run(
        [newer, "-c", TRAIN, str(train), str(dataset), str(out), REPO_ID],
        capture_output=True,
        timeout=600,
    )
    assert ran.returncode == 0, ran.stderr.decode()[-2000:]
    assert math.isfinite(float(ran.stdout.decode().split("loss")[-1]))
    # What it saved loads in either LeRobot's worker.
    for python in (newer, None):
        worker = await PolicyProcess.start(worker_command(python))
        try:
            loaded = await worker.load(out)
        finally:
            await worker.close()
        assert loaded.policy_type == "act" and loaded.chunk_size == 10


async def test_a_dataset_lerobot_06_wrote_imports_as_a_recording(
    tmp_path: Path, newer: str
) -> None:
    out = tmp_path / "written"
    wrote = subprocess.run(
        [newer, "-c", WRITE_DATASET, "lab/wave", str(out)], capture_output=True, timeout=300
    )
    assert wrote.returncode == 0, wrote.stderr.decode()[-2000:]
    imported = tmp_path / "episode1.mcap"
    assert cli.main(["import-dataset", str(out), "--episode", "1", "-o", str(imported)]) == 0
    recording = read_recording(imported)
    (robot,) = {m.robot_id for m in recording.messages if m.kind == "command"}
    commands = recorded_commands(recording, robot)
    assert len(commands) == 5
    pans = [next(g.value for g in c.command.joints if g.name == "Rotation") for c in commands]
    assert pans == pytest.approx([10, 11, 12, 13, 14], abs=1e-3)


def test_lerobots_teleoperation_loop_runs_the_bench_sweep(newer: str) -> None:
    """`arena bench teleop`'s LeRobot side: `lerobot-teleoperate`'s loop (SO-101 leader and
    follower, LeRobot 0.6 with its feetech extra) on two simulated buses follows the leader."""
    from arena.bench import teleop

    sweep = teleop.lerobot_sweep(Path(newer), [(30.0, 0.4), (-30.0, 0.35)], rest=1.0)
    figures = teleop.summarise(sweep, "lerobot")
    assert figures["lerobot_lag_samples"] > 10
    assert figures["lerobot_unreached_samples"] == 0
    assert figures["lerobot_no_reaction_moves"] == 0
    # It sends the leader's value as it is: never past it, and it settles where the leader did.
    assert figures["lerobot_overshoot_max_deg"] == 0
    assert figures["lerobot_end_error_max_deg"] == 0
