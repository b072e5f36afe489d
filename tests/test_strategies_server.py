"""The rollout strategies through a real server (specs/policy.md, "Rollout strategies"): a tiny
LeRobot policy (random weights, in a real worker process) runs `episodic`, then `sentry` with an
operator's correction in it, then `highlight`; the recording holds each episode with its task,
the highlight marked at the times it began and ended; `arena export --format lerobot` writes
them all and LeRobot's `LeRobotDataset` reads them back. With the recorder off, a highlight
writes the kept seconds and nothing else is written.

These wait for events (the robot's own, answers over HTTP), never for a time to pass."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
import trio

from arena import cli
from arena.recording.mcap_file import read_recording
from arena.robot.events import CommandHandled, EpisodeChanged
from arena.robot.handle import Robot
from tests.conftest import eventually, need
from tests.test_policy_server import (
    LOAD,
    ROBOT,
    WAIT,
    Start,
    attach,
    checkpoint,
    next_event,
    ready,
    tiny,  # noqa: F401 (the fixture)
    workers,
)

lerobot_dataset = need("lerobot.datasets.lerobot_dataset", "lerobot")


async def commands(robot: Robot, source: str, count: int) -> None:
    """Wait for `count` accepted commands of `source`."""
    with robot.subscribe(kinds=[CommandHandled]) as events:
        for _ in range(count):
            await next_event(
                events,
                lambda e: e.source == source and e.result.accepted,  # type: ignore[attr-defined]
            )


async def strategy(server: Any, policy: Path, body: dict[str, Any]) -> None:
    answer = await attach(server, policy, task="ignored", strategy=body)
    assert answer.status_code == 201, answer.text


def elapsed(robot: Robot) -> float:
    """Seconds the running episode has run (-1: none runs)."""
    active = robot.episodes.active
    return -1.0 if active is None else trio.current_time() - active.started


def spans(path: Path) -> list[tuple[str, int, int]]:
    """(task, start, end) of each episode, in log time, from the recording's marks."""
    marks = sorted(
        (m for m in read_recording(path).messages if m.kind == "episode"),
        key=lambda m: m.log_time,
    )
    started = {m.data["index"]: m for m in marks if m.data["change"] == "start"}
    return [
        (str(m.data["task"]), started[m.data["index"]].log_time, m.log_time)
        for m in marks
        if m.data["change"] == "stop"
    ]


def read_back(path: Path, out: Path, capsys: pytest.CaptureFixture[str]) -> Any:
    args = ["export", str(path), "--format", "lerobot", "--robot", "demo-arm", "-o", str(out)]
    assert cli.main(args) == 0, capsys.readouterr().err
    return lerobot_dataset.LeRobotDataset("arena/eval_demo-arm", root=out, video_backend="pyav")


def tasks_of(dataset: Any) -> list[str]:
    """Each episode's task, in order."""
    names = {
        int(i): str(t)
        for t, i in zip(dataset.meta.tasks.index, dataset.meta.tasks["task_index"], strict=True)
    }
    found: dict[int, str] = {}
    for row in dataset.hf_dataset.with_format(None):
        found.setdefault(int(row["episode_index"]), names[int(row["task_index"])])
    return [found[i] for i in sorted(found)]


async def test_the_three_strategies_make_episodes_that_lerobot_reads(
    start_server: Start,
    tiny: Path,  # noqa: F811 (the fixture)
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    server = await start_server(demo=True)
    robot = await ready(server)
    identity = f"policy:act:{checkpoint(tiny)}"

    # episodic: two episodes of a second, a reset between them, and the master ends.
    with robot.subscribe(kinds=[EpisodeChanged]) as events:
        body = {"type": "episodic", "episodes": 2, "episode_s": 1.0, "reset_s": 5, "task": "reach"}
        await strategy(server, tiny, body)
        for _ in range(4):
            await next_event(events, lambda e: isinstance(e, EpisodeChanged))
    await eventually(lambda: robot.snapshot().master is None, WAIT, "the episodic master ends")

    # sentry, with an operator's correction in its first episode.
    await strategy(server, tiny, {"type": "sentry", "episode_s": 2.0, "task": "watch"})
    await commands(robot, identity, 3)
    async with httpx.AsyncClient(base_url=server.url, timeout=LOAD) as http:
        assert (await http.post(f"{ROBOT}/intervention", json={})).status_code == 201
        joint = robot.snapshot().joints[0]
        for step in range(5):
            value = (joint.real_value or joint.virtual_value) + 0.5 * (step + 1)
            put = await http.put(
                f"{ROBOT}/joints", json={"joints": [{"name": joint.name, "value": value}]}
            )
            assert put.status_code == 200, put.text
            await trio.sleep(0.05)
        assert (await http.delete(f"{ROBOT}/intervention")).status_code == 200
        await eventually(lambda: robot.episodes.kept >= 4, WAIT, "two sentry episodes")
        # Left well inside an episode: one the detach cuts to a frame or two trips LeRobot's
        # writer (its image statistics; see the report), which is not what this test is about.
        await eventually(lambda: 0.3 <= elapsed(robot) <= 0.8, WAIT, "inside an episode")
        assert (await http.delete(f"{ROBOT}/master")).status_code == 200
        assert robot.episodes.active is None  # the running one was stopped as it left

        # highlight: nothing is an episode until asked; then the last second is one.
        kept = robot.episodes.kept
        await strategy(server, tiny, {"type": "highlight", "keep_s": 1.0, "task": "grasp"})
        await commands(robot, identity, 45)
        assert robot.episodes.kept == kept
        saved = await http.post(f"{ROBOT}/highlight")
        assert saved.status_code == 201, saved.text
        assert saved.json()["task"] == "grasp" and 0.9 <= saved.json()["duration"] <= 1.0
        assert (await http.delete(f"{ROBOT}/master")).status_code == 200
        refused = await http.post(f"{ROBOT}/highlight")
        assert refused.status_code == 409 and refused.json()["error"]["code"] == "NO_HIGHLIGHT"
        name = (await http.post("/api/recordings/current/stop")).json()["stopped"]
    path = Path(server.app.recorder.folder) / name

    found = spans(path)
    tasks = [task for task, _, _ in found]
    assert tasks[:2] == ["reach", "reach"] and tasks[-1] == "grasp"
    assert set(tasks[2:-1]) == {"watch"} and len(tasks[2:-1]) >= 2
    _, start, end = found[-1]
    # marked where it began, a second before its end (log times are whole ns: 1 us of rounding)
    assert 0.9e9 <= end - start <= 1.0e9 + 1e3
    messages = read_recording(path).messages
    inside = [m for m in messages if m.kind == "command" and start <= m.log_time <= end]
    assert len(inside) >= 5 and {m.data["source"] for m in inside} == {identity}

    dataset = read_back(path, tmp_path / "all", capsys)
    assert dataset.num_episodes == len(found)
    assert tasks_of(dataset) == tasks
    flags = [
        bool(np.asarray(row["intervention"]).reshape(-1)[0])
        for row in dataset.hf_dataset.with_format(None)
    ]
    assert any(flags) and not all(flags)  # the correction, tagged as in any episode


async def test_with_the_recorder_off_a_highlight_writes_its_seconds_and_nothing_else(
    start_server: Start,
    tiny: Path,  # noqa: F811 (the fixture)
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    server = await start_server(demo=True, record=False)
    robot = await ready(server)
    identity = f"policy:act:{checkpoint(tiny)}"
    folder = Path(server.app.recorder.folder)
    await strategy(server, tiny, {"type": "highlight", "keep_s": 1.0, "task": "grasp"})
    await commands(robot, identity, 75)  # 2.5 s of the policy: more than is kept
    assert not list(folder.glob("*.mcap"))  # nothing is written
    async with server.client() as http:
        saved = await http.post(f"{ROBOT}/highlight")
        assert saved.status_code == 201, saved.text
    (path,) = folder.glob("*.mcap")
    ((task, start, end),) = spans(path)
    assert task == "grasp" and 0.9e9 <= end - start <= 1.0e9 + 1e3
    messages = [m for m in read_recording(path).messages if m.robot_id == "demo-arm"]
    # Only the kept second, at the times it happened, the policy's commands in it.
    assert all(start <= m.log_time <= end for m in messages)
    policy = [m for m in messages if m.kind == "command"]
    assert len(policy) >= 5 and {m.data["source"] for m in policy} == {identity}
    dataset = read_back(path, tmp_path / "highlight", capsys)
    assert dataset.num_episodes == 1 and 20 <= dataset.num_frames <= 31
    assert dataset.meta.video_keys == ["observation.images.front"]  # its frames were kept too


async def test_a_strategy_is_checked_at_the_edge_with_clear_errors(
    start_server: Start,
    tiny: Path,  # noqa: F811 (the fixture)
) -> None:
    server = await start_server(demo=True)
    robot = await ready(server)
    name = robot.model.joints[0].name
    upper = robot.model.joints[0].upper
    bad: list[tuple[dict[str, Any], int, str, str]] = [
        (
            {"type": "episodic", "episodes": 0, "episode_s": 1, "task": "t"},
            422,
            "INVALID_BODY",
            "episodes",
        ),
        (
            {"type": "episodic", "episodes": 2, "episode_s": 1e9, "task": "t"},
            422,
            "INVALID_BODY",
            "episode_s",
        ),
        ({"type": "sentry", "episode_s": 0, "task": "t"}, 422, "INVALID_BODY", "episode_s"),
        ({"type": "highlight", "keep_s": 301, "task": "t"}, 422, "INVALID_BODY", "keep_s"),
        ({"type": "highlight", "keep_s": 5}, 422, "INVALID_BODY", "task"),
        ({"type": "dagger", "task": "t"}, 422, "INVALID_BODY", "sentry"),
        (
            {"type": "sentry", "episode_s": 1, "task": "t", "every": 2},
            400,
            "UNKNOWN_FIELD",
            "every",
        ),
        ({"type": "sentry", "episode_s": 1, "task": "  "}, 422, "INVALID_VALUE", "blank"),
        (
            {
                "type": "episodic",
                "episodes": 2,
                "episode_s": 1,
                "task": "t",
                "start_pose": {"Elbow2": 0},
            },
            422,
            "INVALID_VALUE",
            "Elbow2",
        ),
        (
            {
                "type": "episodic",
                "episodes": 2,
                "episode_s": 1,
                "task": "t",
                "start_pose": {name: upper + 1},
            },
            422,
            "INVALID_VALUE",
            "outside its limits",
        ),
    ]
    async with httpx.AsyncClient(base_url=server.url, timeout=LOAD) as http:
        for body, status, code, words in bad:
            answer = await http.post(
                f"{ROBOT}/master", json={"type": "policy", "path": str(tiny), "strategy": body}
            )
            assert answer.status_code == status, (body, answer.text)
            error = answer.json()["error"]
            assert error["code"] == code and words in error["message"], (body, error)
        # A strategy makes its own episodes: refused while one runs, before anything loads.
        assert (
            await http.post(f"{ROBOT}/episodes/start", json={"task": "mine"})
        ).status_code == 201
        sentry = {"type": "sentry", "episode_s": 1, "task": "t"}
        answer = await http.post(
            f"{ROBOT}/master", json={"type": "policy", "path": str(tiny), "strategy": sentry}
        )
        assert answer.status_code == 409 and answer.json()["error"]["code"] == "EPISODE_ACTIVE"
        assert workers() == []
    assert robot.snapshot().master is None
