"""A tiny LeRobot policy (random weights, saved by tests/tiny_policy.py in a process of its own)
run as a robot's master through a real server, in a real worker process, with the mock and the
physics slaves: commands flow at its fps and are recorded with its identity, each inference is
recorded, the run exports as an evaluation dataset, an e-stop stops them and the worker, a
killed worker trips the watchdog, NaN and huge jumps move nothing beyond the limits, what is not
a policy the robot can feed is refused with POLICY_INVALID, and torch never enters the server's
process.

These wait for events (the robot's own, answers over HTTP), never for a time to pass."""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import httpx
import pytest
import trio

from arena import cli
from arena.protocol.errors import ArenaError, ErrorCode
from arena.recording.mcap_file import read_recording
from arena.robot.events import (
    CommandHandled,
    FaultReported,
    JointStatesReceived,
    RobotEvent,
    StateChanged,
    TargetsSent,
)
from arena.robot.mailbox import EventQueue
from arena.robot.safety import Mode
from arena.server.config import ServerConfig
from tests.conftest import REPOSITORY, RunningServer, need
from tests.serve_process import serving

CAMERA = {"name": "front", "source": "test-pattern", "fps": 30, "width": 64, "height": 48}
ROBOT = "/api/robots/demo-arm"
#: Bounds on waits that only a broken feature reaches (loading imports torch: seconds).
LOAD = 120.0
WAIT = 60.0

Start = Callable[..., Awaitable[RunningServer]]


def make_policy(folder: Path, *args: str, python: str = sys.executable) -> Path:
    """Save a tiny policy in `folder` (tests/tiny_policy.py's options) with the LeRobot of
    `python`."""
    subprocess.run(
        [python, str(REPOSITORY / "tests" / "tiny_policy.py"), str(folder), *args],
        check=True,
        env={**os.environ, "PYTHONPATH": str(REPOSITORY)},
        capture_output=True,
        timeout=300,
    )
    return folder


@pytest.fixture(scope="session")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny ACT policy: 6 joints and a 32x32 camera `front`, actions near LeRobot's 0."""
    need("lerobot", "lerobot")
    return make_policy(tmp_path_factory.mktemp("policy") / "act")


def variant(tiny: Path, folder: Path, mean: float, std: float) -> Path:
    """`tiny` with other action statistics: its unnormalizer's state file rewritten."""
    from safetensors.numpy import load_file, save_file

    shutil.copytree(tiny, folder)
    name = next(folder.glob("policy_postprocessor_step_*_unnormalizer_processor.safetensors"))
    tensors = load_file(str(name))
    for key, value in tensors.items():
        value[...] = mean if key.endswith("mean") else std
    save_file(tensors, str(name))
    return folder


def checkpoint(path: Path) -> str:
    return hashlib.sha256((path / "model.safetensors").read_bytes()).hexdigest()[:12]


def workers() -> list[int]:
    """This process's children that are policy workers."""
    found = []
    for task in Path(f"/proc/{os.getpid()}/task").iterdir():
        for pid in (task / "children").read_text().split():
            try:
                command = Path(f"/proc/{pid}/cmdline").read_bytes()
            except OSError:
                continue
            if b"arena.policy.worker" in command:
                found.append(int(pid))
    return found


async def next_event(events: EventQueue[RobotEvent], check: Callable[[RobotEvent], bool]) -> Any:
    with trio.fail_after(WAIT):
        while True:
            event = await events.get()
            if check(event):
                return event


async def ready(server: RunningServer, camera: bool = True) -> Any:
    async with server.client() as http:
        if camera:
            created = await http.post(f"{ROBOT}/cameras", json=CAMERA)
            assert created.status_code == 201, created.text
    return server.app.manager.get("demo-arm")


async def attach(server: RunningServer, path: Path, **body: Any) -> Any:
    async with httpx.AsyncClient(base_url=server.url, timeout=LOAD) as http:
        return await http.post(
            f"{ROBOT}/master", json={"type": "policy", "path": str(path), **body}
        )


async def test_a_policy_drives_the_arm_and_an_estop_stops_it(
    start_server: Start, tiny: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    server = await start_server(demo=True)
    robot = await ready(server)
    identity = f"policy:act:{checkpoint(tiny)}"
    with robot.subscribe(kinds=[CommandHandled, StateChanged]) as events:
        answer = await attach(server, tiny, task="wave", fps=30)
        assert answer.status_code == 201, answer.text
        assert answer.json() == {"id": identity, "type": "policy"}
        async with server.client() as http:
            master = (await http.get(ROBOT)).json()["master"]
        assert master["id"] == identity and master["type"] == "policy"
        for _ in range(20):
            command = await next_event(events, lambda e: isinstance(e, CommandHandled))
            assert command.source == identity and command.result.accepted
        (worker,) = workers()
        async with server.client() as http:
            assert (await http.post(f"{ROBOT}/estop", json={"reason": "test"})).status_code == 200
        await next_event(events, lambda e: isinstance(e, StateChanged) and e.mode is Mode.ESTOPPED)
        # The master was detached at the e-stop itself: nothing of the policy's comes after it.
        # (Events come in the order the actor handled them.)
        after = events.drain()
        assert not [e for e in after if isinstance(e, CommandHandled)]
    with trio.fail_after(WAIT):
        while workers():
            await trio.sleep(0.05)
    assert not Path(f"/proc/{worker}").exists() or worker not in workers()
    async with server.client() as http:
        assert (await http.get(ROBOT)).json()["master"] is None
        stopped = (await http.post("/api/recordings/current/stop")).json()["stopped"]
    recording = read_recording(Path(server.app.recorder.folder) / stopped)
    commands = [
        m for m in recording.messages if m.kind == "command" and m.data.get("source") == identity
    ]
    assert len(commands) >= 20
    span = (commands[-1].log_time - commands[0].log_time) / 1e9
    # Never faster than the policy's fps. The slack: the loop keeps its schedule through a
    # delay under half a period, and the actor handles each command a little after it left.
    assert len(commands) <= 30 * span + 3
    # Each inference is on /robots/demo-arm/policy with its latency and chunk size.
    inferences = [m for m in recording.messages if m.topic == "/robots/demo-arm/policy"]
    assert len(inferences) >= 3
    for inference in inferences:
        data = inference.data
        assert data["policy"] == identity and data["chunk_size"] == 10
        assert 0 <= data["kept"] <= 10
        assert 0 < data["inference"] <= data["latency"] < WAIT
        assert data["frame_age"] is not None and 0 <= data["frame_age"] < WAIT
    steps = [m.data["timestep"] for m in inferences]
    assert steps == sorted(steps) and steps[-1] > 0
    check_evaluation_export(recording.path, identity, tmp_path, capsys)


def check_evaluation_export(
    path: Path, identity: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The policy's run exported for LeRobot is an evaluation dataset: named `eval_...` as
    LeRobot names them, and a name that says otherwise is refused."""
    lerobot_dataset = need("lerobot.datasets.lerobot_dataset", "lerobot")
    args = ["export", str(path), "--format", "lerobot", "--robot", "demo-arm"]
    assert cli.main([*args, "--repo-id", "lab/cube", "-o", str(tmp_path / "plain")]) == 2
    said = capsys.readouterr().err
    assert identity in said and "starts with 'eval_'" in said
    out = tmp_path / "eval"
    assert cli.main([*args, "-o", str(out)]) == 0, capsys.readouterr().err
    printed = capsys.readouterr().out
    assert "arena/eval_demo-arm" in printed and f"an evaluation of {identity}" in printed
    dataset = lerobot_dataset.LeRobotDataset("arena/eval_demo-arm", root=out, video_backend="pyav")
    assert dataset.num_episodes == 1 and dataset.num_frames > 0
    assert dataset.meta.video_keys == ["observation.images.front"]
    assert json.loads((out / "meta" / "arena.json").read_text())["policies"] == [identity]


async def test_with_the_physics_twin_as_slave_commands_are_recorded_and_an_estop_ends_them(
    start_server: Start, tiny: Path
) -> None:
    """The MuJoCo twin in real time as the robot's only slave: the policy's commands reach it
    at no more than the policy's fps, recorded with their source; after the e-stop the file
    holds no command and no target of the policy, and the twin's reports go on (it holds)."""
    need("mujoco", "physics")
    server = await start_server()
    base = "/api/robots/sim"
    async with server.client() as http:
        made = await http.post("/api/robots", json={"robot_type": "so-arm100", "id": "sim"})
        assert made.status_code == 201, made.text
        slave = await http.post(f"{base}/slaves", json={"type": "physics-slave"})
        assert slave.status_code == 201, slave.text
        assert (await http.post(f"{base}/cameras", json=CAMERA)).status_code == 201
    robot = server.app.manager.get("sim")
    identity = f"policy:act:{checkpoint(tiny)}"
    with robot.subscribe(kinds=[CommandHandled, StateChanged, JointStatesReceived]) as events:
        async with httpx.AsyncClient(base_url=server.url, timeout=LOAD) as http:
            body = {"type": "policy", "path": str(tiny), "fps": 20}
            answer = await http.post(f"{base}/master", json=body)
        assert answer.status_code == 201, answer.text
        for _ in range(20):
            command = await next_event(events, lambda e: isinstance(e, CommandHandled))
            assert command.source == identity
        async with server.client() as http:
            assert (await http.post(f"{base}/estop", json={"reason": "test"})).status_code == 200
        await next_event(events, lambda e: isinstance(e, StateChanged) and e.mode is Mode.ESTOPPED)
        # the twin goes on reporting after the e-stop: it holds where it is
        await next_event(events, lambda e: isinstance(e, JointStatesReceived))
    async with server.client() as http:
        stopped = (await http.post("/api/recordings/current/stop")).json()["stopped"]
    messages = read_recording(Path(server.app.recorder.folder) / stopped).messages
    messages = [m for m in messages if m.robot_id == "sim"]
    estop = next(
        i for i, m in enumerate(messages) if m.kind == "state" and m.data["mode"] == "estopped"
    )
    commands = [m for m in messages[:estop] if m.kind == "command"]
    assert len(commands) >= 20 and {m.data["source"] for m in commands} == {identity}
    assert sum(m.data["accepted"] for m in commands) >= 10
    span = (commands[-1].log_time - commands[0].log_time) / 1e9
    assert len(commands) <= 20 * span + 3  # never faster than the policy's fps (as above)
    after = messages[estop + 1 :]
    assert not [m for m in after if m.kind in ("command", "targets")]
    assert [m for m in after if m.kind == "joint_states"]


async def test_a_killed_worker_trips_the_watchdog(start_server: Start, tiny: Path) -> None:
    server = await start_server(demo=True)
    robot = await ready(server)
    with robot.subscribe(kinds=[CommandHandled, FaultReported]) as events:
        assert (await attach(server, tiny)).status_code == 201
        await next_event(events, lambda e: isinstance(e, CommandHandled))
        (worker,) = workers()
        os.kill(worker, signal.SIGKILL)
        # (on a loaded machine an inference slower than the fps may stall it before: a fault
        # of its own, the same code saying so)
        fault = await next_event(
            events, lambda e: isinstance(e, FaultReported) and "died (SIGKILL)" in e.message
        )
    assert fault.code == ErrorCode.POLICY_STALLED and fault.severity == "warning"
    assert "holds where it is" in fault.message
    with trio.fail_after(WAIT):
        while robot.snapshot().master is not None:
            await trio.sleep(0.05)


async def test_nan_and_huge_jumps_move_nothing_beyond_the_limits(
    start_server: Start, tiny: Path, tmp_path: Path
) -> None:
    server = await start_server(demo=True)
    robot = await ready(server)
    nan = variant(tiny, tmp_path / "nan", math.nan, 1.0)
    with robot.subscribe(
        kinds=[CommandHandled, FaultReported, TargetsSent, JointStatesReceived]
    ) as events:
        assert (await attach(server, nan)).status_code == 201
        fault = await next_event(events, lambda e: isinstance(e, FaultReported))
        assert fault.code == ErrorCode.POLICY_OUTPUT_INVALID, fault.message
        assert not [e for e in events.drain() if isinstance(e, CommandHandled)]
        async with server.client() as http:
            assert (await http.delete(f"{ROBOT}/master")).status_code == 200
        before = {j.name: j.virtual_value for j in robot.snapshot().joints}
        huge = variant(tiny, tmp_path / "huge", 0.0, 1e4)
        assert (await attach(server, huge, max_relative_target=3.0)).status_code == 201
        # The step limit holds each target near the measured position the policy saw: one
        # of those reported since its last command (or the last one before).
        with trio.fail_after(WAIT):
            await check_steps(robot, events, before, 3.0)


async def check_steps(
    robot: Any, events: EventQueue[RobotEvent], before: dict[str, float], limit: float
) -> None:
    """Follow 15 commands: each target within `limit` of a measured position the policy may
    have seen, every target sent within the joint's limits. (A policy of huge random jumps
    soon walks the arm to where the collision guard refuses each next step.)"""
    measured = {name: [value] for name, value in before.items()}
    handled = accepted = 0
    while handled < 15:
        event = await events.get()
        if isinstance(event, TargetsSent):
            for joint in robot.model.joints:
                value = event.joints.get(joint.name, 0.0)
                assert joint.lower - 1e-9 <= value <= joint.upper + 1e-9
        elif isinstance(event, JointStatesReceived):
            for name, value in event.joints.items():
                measured[name].append(value)
        elif isinstance(event, CommandHandled):
            assert event.result.accepted or event.result.code == "COLLISION", event.result
            for goal in event.command.joints:
                near = min(abs(goal.value - value) for value in measured[goal.name])
                assert near <= limit + 1e-6, (goal, measured[goal.name])
            accepted += event.result.accepted
            handled += 1
            measured = {name: values[-1:] for name, values in measured.items()}
    assert accepted


async def test_what_the_robot_cannot_run_is_refused(
    start_server: Start, tiny: Path, tmp_path: Path
) -> None:
    server = await start_server(demo=True)
    await ready(server, camera=False)
    answer = await attach(server, tiny)
    assert answer.status_code == 422
    error = answer.json()["error"]
    assert error["code"] == "POLICY_INVALID"
    assert "observation.images.front" in error["message"]
    assert workers() == []
    assert server.app.manager.get("demo-arm").snapshot().master is None


async def test_a_relative_path_is_the_servers_and_a_refusal_names_it_in_full(
    start_server: Start, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The folder is on the server's machine: a relative path (the whole server's admin's, as
    # here with no keys) is taken from the folder the server was started in, and the answer
    # says which folder that was.
    monkeypatch.chdir(tmp_path)
    server = await start_server(demo=True)
    answer = await attach(server, Path("policies/act"))
    assert answer.status_code == 422, answer.text
    error = answer.json()["error"]
    assert error["code"] == "POLICY_INVALID", error
    assert error["message"] == f"{tmp_path / 'policies' / 'act'}: not a directory.", error
    assert workers() == []


async def test_a_tenant_names_a_policy_of_its_own_policy_folder(
    start_server: Start, tiny: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Where a user puts a policy: a folder of `policies/` (a tenant's: `policies/<tenant>/`)
    # in the folder the server runs in, named in the body by its name alone.
    from tests.test_users import SECRET, bearer, token

    monkeypatch.chdir(tmp_path)
    shutil.copytree(tiny, tmp_path / "policies" / "acme" / "cube")
    (tmp_path / "jwt-secret").write_bytes(SECRET)
    server = await start_server(jwt_secret_file=str(tmp_path / "jwt-secret"))
    admin = bearer(token("admin", tenant="acme"))
    operator = bearer(token("operator", tenant="acme"))
    arm = "/api/robots/acme-arm"
    async with httpx.AsyncClient(base_url=server.url, timeout=LOAD) as http:
        assert (await http.post("/api/robots", json={"id": "acme-arm"}, headers=admin)).is_success
        body = {"type": "mock-slave"}
        assert (await http.post(f"{arm}/slaves", json=body, headers=admin)).is_success
        assert (await http.post(f"{arm}/cameras", json=CAMERA, headers=admin)).is_success
        body = {"type": "policy", "path": "cube", "task": "wave"}
        answer = await http.post(f"{arm}/master", json=body, headers=operator)
        assert answer.status_code == 201, answer.text
        assert answer.json()["id"] == f"policy:act:{checkpoint(tiny)}"
        assert (await http.delete(f"{arm}/master", headers=operator)).is_success
    with trio.fail_after(WAIT):
        while workers():
            await trio.sleep(0.05)


@pytest.mark.parametrize(
    ("broken", "said"),
    [
        ("missing", ": not a directory."),
        ("empty", ": no config.json in it"),
        ("config", "config.json is not a LeRobot policy config"),
        ("class-step", "step 0 is not one of LeRobot's registered steps"),
        ("state-path", "step 0's state_file '/etc/passwd' is not a file's name"),
    ],
)
async def test_a_directory_that_is_not_a_policy_is_refused_with_the_reason(
    start_server: Start, tmp_path: Path, broken: str, said: str
) -> None:
    server = await start_server(demo=True)
    folder = tmp_path / "policy"
    if broken != "missing":
        folder.mkdir()
    if broken in ("config", "class-step", "state-path"):
        for name in ("config.json", "model.safetensors", "policy_postprocessor.json"):
            (folder / name).write_text("{}" if name != "config.json" else '{"type": "nope"}')
        step: dict[str, str] = {"registry_name": "x"}
        if broken == "class-step":
            step = {"class": "os.system"}
        elif broken == "state-path":  # (LeRobot would read any file a path names)
            step["state_file"] = "/etc/passwd"
        (folder / "policy_preprocessor.json").write_text(json.dumps({"steps": [step]}))
        (folder / "policy_postprocessor.json").write_text(json.dumps({"steps": []}))
    if broken == "config":
        need("lerobot", "lerobot")
    answer = await attach(server, folder)
    assert answer.status_code == 422, answer.text
    error = answer.json()["error"]
    assert error["code"] == "POLICY_INVALID" and said in error["message"], error
    assert workers() == []


async def test_without_lerobot_a_policy_master_is_not_installed(
    start_server: Start, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name == "lerobot" else real(name, *a)
    )
    server = await start_server(demo=True)
    answer = await attach(server, tmp_path)
    assert answer.status_code == 501, answer.text
    assert "pip install 'arena[lerobot]'" in answer.json()["error"]["message"]
    assert workers() == []


def native_libraries(pid: int) -> set[str]:
    """The shared libraries process `pid` has mapped (torch's are libtorch*.so)."""
    maps = Path(f"/proc/{pid}/maps").read_text()
    return {Path(line.split()[-1]).name for line in maps.splitlines() if ".so" in line}


def accepted_commands(url: str) -> int:
    metrics = httpx.get(f"{url}/metrics", timeout=10).text
    found = re.search(r'^arena_commands_total\{result="accepted"\} (\d+)', metrics, re.M)
    return int(found.group(1)) if found else 0


def test_torch_never_enters_the_servers_process(tiny: Path, tmp_path: Path) -> None:
    """`arena serve` as a process of its own runs a policy: torch (which LeRobot imports) is
    mapped into the worker, never into the server."""
    env = {**os.environ, "PYTHONPATH": str(REPOSITORY)}
    with serving(["--demo", "--port", "0", "--no-record"], cwd=tmp_path, env=env) as served:
        url, server = served.url, served.process.pid
        assert httpx.post(f"{url}{ROBOT}/cameras", json=CAMERA, timeout=WAIT).status_code == 201
        before = accepted_commands(url)
        body = {"type": "policy", "path": str(tiny)}
        answer = httpx.post(f"{url}{ROBOT}/master", json=body, timeout=LOAD)
        assert answer.status_code == 201, answer.text
        deadline = time.monotonic() + WAIT  # only a broken policy master reaches it
        while accepted_commands(url) < before + 20:
            assert time.monotonic() < deadline, served.log
            time.sleep(0.05)
        children = [
            int(pid)
            for task in Path(f"/proc/{server}/task").iterdir()
            for pid in (task / "children").read_text().split()
        ]
        (worker,) = [
            pid
            for pid in children
            if b"arena.policy.worker" in Path(f"/proc/{pid}/cmdline").read_bytes()
        ]
        assert any(name.startswith("libtorch") for name in native_libraries(worker))
        assert not any(name.startswith("libtorch") for name in native_libraries(server))


async def test_a_policy_a_newer_lerobot_saved_loads_and_what_would_change_it_is_refused(
    start_server: Start, tiny: Path, tmp_path: Path
) -> None:
    """LeRobot 0.6 writes `pretrained_revision` into every config, 0.4.4 knows no such field:
    the worker drops a later field that holds its neutral value and names any other."""

    def saved_with(folder: Path, **fields: Any) -> Path:
        shutil.copytree(tiny, folder)
        config = json.loads((folder / "config.json").read_text())
        (folder / "config.json").write_text(json.dumps({**config, **fields}))
        return folder

    server = await start_server(demo=True)
    await ready(server)
    newer = saved_with(tmp_path / "newer", pretrained_revision=None, use_relative_actions=False)
    loaded = await attach(server, newer)
    assert loaded.status_code == 201, loaded.text
    async with server.client() as http:
        assert (await http.delete(f"{ROBOT}/master")).status_code == 200
    changes = saved_with(tmp_path / "relative", use_relative_actions=True, new_knob=3)
    refused = await attach(server, changes)
    error = refused.json()["error"]
    assert (refused.status_code, error["code"]) == (422, "POLICY_INVALID"), error
    assert "'use_relative_actions' = true, 'new_knob' = 3" in error["message"]
    assert "LeRobot 0.4.4, which this worker runs" in error["message"]
    assert "--policy-python" in error["message"]


def python_without_arena(folder: Path) -> Path:
    """A virtualenv whose Python finds this one's packages (LeRobot, torch, msgspec) but not
    Arena: its site-packages named in a `.pth` file, whose own `.pth` files (Arena's editable
    install among them) are then never read."""
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(folder)], check=True)
    ours = next(p for p in sys.path if p.endswith("site-packages") and Path(p).is_dir())
    theirs = next((folder / "lib").glob("python3*/site-packages"))
    (theirs / "packages.pth").write_text(ours + "\n")
    return folder / "bin" / "python"


async def test_a_worker_runs_in_a_python_of_the_user_s_that_has_no_arena(
    start_server: Start, tiny: Path, tmp_path: Path
) -> None:
    python = python_without_arena(tmp_path / "venv")
    cannot = subprocess.run([str(python), "-I", "-c", "import arena"], capture_output=True)
    assert b"No module named 'arena'" in cannot.stderr
    server = await start_server(demo=True, policy_python=str(python))
    robot = await ready(server)
    with robot.subscribe(kinds=[CommandHandled]) as events:
        assert (await attach(server, tiny)).status_code == 201
        await next_event(events, lambda e: isinstance(e, CommandHandled))
    (worker,) = workers()
    assert Path(f"/proc/{worker}/cmdline").read_bytes().split(b"\0")[:2] == [
        str(python).encode(),
        b"-I",
    ]


def test_a_policy_python_that_is_no_program_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ArenaError, match="is not a program"):
        ServerConfig(policy_python=str(tmp_path / "nothing")).check()


async def test_a_diffusion_policy_drives_the_arm_from_its_recent_observations(
    start_server: Start, tmp_path: Path
) -> None:
    """Diffusion predicts from its last `n_obs_steps` observations (kept in the policy's
    queues, which LeRobot's async inference leaves empty): the worker fills them."""
    need("diffusers", "lerobot")
    diffusion = make_policy(tmp_path / "diffusion", "--type", "diffusion")
    server = await start_server(demo=True)
    robot = await ready(server)
    with robot.subscribe(kinds=[CommandHandled]) as events:
        answer = await attach(server, diffusion)
        assert answer.status_code == 201, answer.text
        assert answer.json()["id"].startswith("policy:diffusion:")
        handled = [  # past several chunks (10 actions each, the next asked for at half)
            await next_event(events, lambda e: isinstance(e, CommandHandled)) for _ in range(20)
        ]
    assert sum(event.result.accepted for event in handled) >= 10
    async with server.client() as http:
        assert (await http.delete(f"{ROBOT}/master")).status_code == 200
