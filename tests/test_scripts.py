"""Scripts as masters (specs/scripts.md): a script in a worker process of its own drives a robot
of a real server through every rule; its errors are faults with its line; an e-stop kills it;
only a file of the tenant's scripts folder runs; `arena script` runs one from another machine."""

from __future__ import annotations

import itertools
import math
import os
import sys
import textwrap
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import httpx
import pytest
import trio

from arena.recording.mcap_file import read_recording
from arena.robot.cartesian import hand_for
from arena.robot.events import CommandHandled, FaultReported, StateChanged
from arena.robot.model import load_robot_model
from arena.robot.safety import Mode
from tests.conftest import RunningServer
from tests.serve_process import serving
from tests.test_policy_server import next_event

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


async def wait_for_no_master(server: RunningServer) -> None:
    robot = server.app.manager.get("demo-arm")
    with trio.fail_after(WAIT):
        while robot.snapshot().master is not None:
            await trio.sleep(0.05)


async def test_a_script_that_raises_is_a_fault_naming_its_file_and_line(
    start_server: Start, tmp_path: Path
) -> None:
    server = await scripted(start_server, tmp_path)
    path = write(
        tmp_path / "scripts",
        "bad.py",
        """\
        from arena.script import move_joints

        move_joints({"Rotation": 5})
        values = {"Pitch": 1}
        print(values["Roll"])
        """,
    )
    robot = server.app.manager.get("demo-arm")
    with robot.subscribe(kinds=[FaultReported]) as events:
        answer = await attach(server, "bad.py")
        assert answer.status_code == 201, answer.text
        fault = await next_event(events, lambda e: isinstance(e, FaultReported))
    assert fault.code == "SCRIPT_FAILED" and fault.peer_id == "script:bad.py"
    assert fault.message == f"{path.resolve()}, line 5: KeyError: 'Roll'"
    await wait_for_no_master(server)
    assert robot.snapshot().joint("Rotation").goal == 5  # what it did before is done
    # Over REST too, once it has gone: the robot's details keep why its last master ended.
    async with server.client() as http:
        shown = (await http.get(ROBOT)).json()
    assert shown["master"] is None
    last = shown["last_master"]
    assert last["id"] == "script:bad.py" and last["type"] == "script", last
    assert last["ended"] == "detached" and last["reason"] == "driver finished", last
    assert last["error"] == f"SCRIPT_FAILED: {fault.message}", last


async def test_a_refused_command_raises_in_the_script_which_may_catch_it(
    start_server: Start, tmp_path: Path
) -> None:
    server = await scripted(start_server, tmp_path)
    write(
        tmp_path / "scripts",
        "far.py",
        """\
        from arena.script import ScriptError, move_joints, move_to_pose

        try:
            move_to_pose([5.0, 0.0, 0.0])
        except ScriptError as error:
            print("refused", error.code)
            move_joints({"Rotation": 7})
        move_joints({"Nope": 1})
        """,
    )
    robot = server.app.manager.get("demo-arm")
    with robot.subscribe(kinds=[FaultReported]) as events:
        assert (await attach(server, "far.py")).status_code == 201
        fault = await next_event(events, lambda e: isinstance(e, FaultReported))
    assert "far.py, line 8: ScriptError: UNKNOWN_JOINT" in fault.message, fault.message
    await wait_for_no_master(server)
    assert robot.snapshot().joint("Rotation").goal == 7


async def test_an_estop_during_a_script_kills_its_worker_at_once(
    start_server: Start, tmp_path: Path
) -> None:
    server = await scripted(start_server, tmp_path)
    write(
        tmp_path / "scripts",
        "loop.py",
        """\
        from arena.script import move_joints

        angle = 0
        while True:
            angle = 10 - angle
            move_joints({"Rotation": angle}, duration=0.2)
        """,
    )
    robot = server.app.manager.get("demo-arm")
    before = set(script_workers())
    with robot.subscribe(kinds=[CommandHandled, StateChanged]) as events:
        assert (await attach(server, "loop.py")).status_code == 201
        await next_event(events, lambda e: isinstance(e, CommandHandled))
        (worker,) = set(script_workers()) - before
        async with server.client() as http:
            estop = await http.post(f"{ROBOT}/estop", json={"reason": "test"})
            assert estop.status_code == 200
        await next_event(events, lambda e: isinstance(e, StateChanged) and e.mode is Mode.ESTOPPED)
        after = events.drain()
        assert not [e for e in after if isinstance(e, CommandHandled)]
    # The worker was killed as the master was detached (the script loops for ever: it never
    # ends by itself).
    with trio.fail_after(WAIT):
        while worker in script_workers():
            await trio.sleep(0.05)
    assert robot.snapshot().master is None


@pytest.mark.parametrize(
    ("name", "status", "code"),
    [
        ("../outside.py", 403, "FORBIDDEN"),
        ("/etc/hostname", 403, "FORBIDDEN"),
        ("sub/inner.py", 403, "FORBIDDEN"),
        ("link.py", 403, "FORBIDDEN"),
        ("missing.py", 422, "SCRIPT_INVALID"),
        ("notes.txt", 422, "SCRIPT_INVALID"),
    ],
)
async def test_only_a_script_of_the_tenants_folder_runs(
    start_server: Start, tmp_path: Path, name: str, status: int, code: str
) -> None:
    server = await scripted(start_server, tmp_path)
    write(tmp_path, "outside.py", "print('outside')\n")
    write(tmp_path / "scripts" / "sub", "inner.py", "print('inner')\n")
    write(tmp_path / "scripts", "notes.txt", "print('notes')\n")
    (tmp_path / "scripts" / "link.py").symlink_to(tmp_path / "outside.py")
    before = set(script_workers())
    answer = await attach(server, name)
    assert (answer.status_code, answer.json()["error"]["code"]) == (status, code)
    message = answer.json()["error"]["message"]
    assert message.endswith(".") and name in message
    assert set(script_workers()) == before  # nothing ran
    assert server.app.manager.get("demo-arm").snapshot().master is None


async def test_a_tenant_runs_the_scripts_of_its_own_folder_only(
    start_server: Start, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Where the server's owner puts a script: `scripts/` (a tenant's: `scripts/<tenant>/`) in
    # the folder the server runs in; a tenant's operator runs it by its name.
    from tests.test_users import SECRET, bearer, token

    monkeypatch.chdir(tmp_path)
    write(tmp_path / "scripts" / "acme", "mine.py", "from arena.script import wait\nwait(0)\n")
    write(tmp_path / "scripts", "default.py", "from arena.script import wait\nwait(0)\n")
    (tmp_path / "jwt-secret").write_bytes(SECRET)
    server = await start_server(jwt_secret_file=str(tmp_path / "jwt-secret"))
    admin = bearer(token("admin", tenant="acme"))
    operator = bearer(token("operator", tenant="acme"))
    viewer = bearer(token("viewer", tenant="acme"))
    arm = "/api/robots/acme-arm"
    async with server.client() as http:
        assert (await http.post("/api/robots", json={"id": "acme-arm"}, headers=admin)).is_success
        body = {"type": "script", "path": "default.py"}  # the default tenant's: not acme's
        answer = await http.post(f"{arm}/master", json=body, headers=operator)
        assert (answer.status_code, answer.json()["error"]["code"]) == (422, "SCRIPT_INVALID")
        assert "scripts/acme" in answer.json()["error"]["message"]
        body = {"type": "script", "path": "mine.py"}
        assert (await http.post(f"{arm}/master", json=body, headers=viewer)).status_code == 403
        answer = await http.post(f"{arm}/master", json=body, headers=operator)
        assert answer.status_code == 201, answer.text
    robot = server.app.manager.get("acme-arm")
    with trio.fail_after(WAIT):
        while robot.snapshot().master is not None:
            await trio.sleep(0.05)


async def test_pause_holds_a_script_and_resume_finishes_its_move(
    start_server: Start, tmp_path: Path
) -> None:
    server = await scripted(start_server, tmp_path)
    write(
        tmp_path / "scripts",
        "slow.py",
        """\
        from arena.script import move_joints

        move_joints({"Rotation": 30}, duration=5)
        move_joints({"Pitch": 10})
        """,
    )
    robot = server.app.manager.get("demo-arm")
    with robot.subscribe(kinds=[CommandHandled]) as events:
        assert (await attach(server, "slow.py")).status_code == 201
        first = await next_event(events, lambda e: isinstance(e, CommandHandled))
        async with server.client() as http:
            assert (await http.post(f"{ROBOT}/master/pause")).status_code == 200
            held = robot.snapshot().joint("Rotation").virtual_value
            assert held < 30
            await trio.sleep(0.5)  # (nothing may come meanwhile: checked below)
            assert not [e for e in events.drain() if isinstance(e, CommandHandled)]
            assert robot.snapshot().joint("Rotation").virtual_value == held
            assert (await http.post(f"{ROBOT}/master/resume")).status_code == 200
        await wait_for_no_master(server)
        rest = [e for e in events.drain() if isinstance(e, CommandHandled)]
    assert first.result.accepted
    # On the resume the move was sent again (the arm held where the pause found it), finished,
    # and the script went on to its next move.
    joints = [[(g.name, g.value) for g in e.command.joints] for e in rest]
    assert joints == [[("Rotation", 30)], [("Pitch", 10)]], joints
    assert all(e.result.accepted for e in rest)
    assert robot.snapshot().joint("Rotation").virtual_value == pytest.approx(30, abs=0.1)


class StandIn:
    """A `ScriptArm` that accepts every command at once and moves nothing (for the bounds)."""

    paused = False
    pauses = 0
    stops = 0
    last_stop = ""

    def __init__(self) -> None:
        self.commands: list[Any] = []
        self.faults: list[tuple[str, str]] = []

    def joint_values(self) -> tuple[dict[str, float], dict[str, float]]:
        return {"Rotation": 0.0}, {}

    async def command(self, command: Any) -> Any:
        from arena.robot.motion import CommandResult

        self.commands.append((trio.current_time(), command))
        return CommandResult(True)

    async def pose(self, data: Any, source: str) -> Any:
        raise AssertionError("not asked")

    async def planned(self, request: Any, source: str) -> Any:
        from arena.protocol.errors import ArenaError, ErrorCode
        from arena.script.master import NO_PLANNER

        raise ArenaError(ErrorCode.NOT_INSTALLED, NO_PLANNER)

    async def wait_resumed(self) -> None:
        pass

    def fault(self, source: str, code: Any, message: str, severity: Any) -> None:
        self.faults.append((str(code), message))


async def run_stand_in(tmp_path: Path, text: str, **settings: Any) -> tuple[Any, StandIn, float]:
    from arena.script.master import ScriptMaster, ScriptSettings

    path = write(tmp_path, "bounded.py", text)
    master = ScriptMaster(ScriptSettings(path, **settings), load_robot_model("so-arm100"))
    arm = StandIn()
    started = trio.current_time()
    # (no deadline: the mock clock would jump to it while the worker starts; marked real_io)
    await master.drive(arm)
    return master, arm, trio.current_time() - started


class PausedBetweenLooks(StandIn):
    """A pause and a resume that come and go right after the first command, before the script
    looks again: only the count of pauses tells."""

    async def command(self, command: Any) -> Any:
        if not self.commands:
            self.pauses += 1
        return await super().command(command)


@pytest.mark.real_io
async def test_a_pause_over_before_the_script_looks_still_sends_the_move_again(
    autojump_clock: trio.testing.MockClock, tmp_path: Path
) -> None:
    from arena.script.master import ScriptMaster, ScriptSettings

    path = write(
        tmp_path, "one.py", 'from arena.script import move_joints\nmove_joints({"Rotation": 10})\n'
    )
    master = ScriptMaster(ScriptSettings(path), load_robot_model("so-arm100"))
    arm = PausedBetweenLooks()
    await master.drive(arm)
    assert master.outcome == "" and not arm.faults
    # The arm held where the pause found it: the move went again after it.
    goals = [[(g.name, g.value) for g in c.joints] for _, c in arm.commands]
    assert goals == [[("Rotation", 10)], [("Rotation", 10)]] and master.counters.pauses == 1


@pytest.mark.real_io
async def test_a_script_in_a_tight_loop_is_slowed_to_its_request_rate(
    autojump_clock: trio.testing.MockClock, tmp_path: Path
) -> None:
    master, arm, took = await run_stand_in(
        tmp_path,
        """\
        from arena.script import move_joints, paused

        for i in range(100):
            paused()
            move_joints({"Rotation": i % 10}, wait=False)
        """,
        rate=50.0,
    )
    assert master.outcome == "" and not arm.faults
    assert master.counters.requests == 200 and len(arm.commands) == 100
    # 200 requests at 50 a second: never faster (on trio's clock, which the pacing uses).
    assert took >= 199 / 50 - 1e-6
    times = [t for t, _ in arm.commands]
    assert min(b - a for a, b in itertools.pairwise(times)) >= 2 / 50 - 1e-9


@pytest.mark.real_io
async def test_a_script_that_prints_without_end_is_slowed_and_its_lines_bounded(
    autojump_clock: trio.testing.MockClock, tmp_path: Path
) -> None:
    master, _, took = await run_stand_in(
        tmp_path,
        """\
        for i in range(300):
            print("line", i, "x" * 5000)
        """,
        lines_rate=20.0,
        lines_burst=50,
    )
    # A line goes in pieces of at most 1000 characters: each print of 5007 as six lines,
    # none lost; the newest 100 are kept.
    assert master.outcome == "" and master.counters.lines == 300 * 6
    assert len(master.lines) == 100 and max(len(line) for line in master.lines) == 1000
    assert master.lines[-1].startswith("x") and master.lines[-2] == "x" * 1000
    # After a burst of 50, at most 20 lines a second (on trio's clock, which the bound uses).
    assert took >= (1800 - 50) / 20 - 1e-6


@pytest.mark.real_io
async def test_a_planned_move_where_the_server_plans_none_says_so(
    autojump_clock: trio.testing.MockClock, tmp_path: Path
) -> None:
    _, arm, _ = await run_stand_in(
        tmp_path,
        """\
        from arena.script import move

        move({"Rotation": 10}, plan=True)
        """,
    )
    ((code, message),) = arm.faults
    assert code == "SCRIPT_FAILED" and "line 3: ScriptError: NOT_INSTALLED" in message
    assert "plans no moves" in message and not arm.commands


async def run_arena_script(server: RunningServer, path: Path, *args: str) -> Any:
    """`arena script` in a process of its own (another machine, as far as the API goes)."""
    command = [sys.executable, "-m", "arena", "script", str(path), "--url", server.url]
    return await trio.run_process(
        [*command, "--robot", "demo-arm", *args],
        capture_stdout=True,
        capture_stderr=True,
        check=False,
    )


async def test_arena_script_runs_a_script_from_another_machine_over_the_master_socket(
    start_server: Start, tmp_path: Path
) -> None:
    server = await start_server(demo=True)
    path = write(tmp_path, "remote.py", THREE_POSES)
    robot = server.app.manager.get("demo-arm")
    hand = hand_for(robot.model)
    assert hand is not None
    start = hand.pose({j.name: j.goal for j in robot.snapshot().joints})
    assert start is not None
    with robot.subscribe(kinds=[CommandHandled]) as events:
        with trio.fail_after(WAIT):
            done = await run_arena_script(server, path)
        handled = [e for e in events.drain() if isinstance(e, CommandHandled)]
    assert done.returncode == 0, done.stderr.decode()
    out = done.stdout.decode().splitlines()
    assert out[-1] == "script:remote.py: 9 requests, 3 commands accepted, 0 refused", out
    assert out[-2].startswith("done ['Elbow', 'Jaw', 'Pitch'")
    # The three poses went as the master's `pose` messages, solved and checked by the server.
    assert [e.result.accepted for e in handled] == [True] * 3
    final = hand.pose({j.name: j.goal for j in robot.snapshot().joints})
    assert final is not None
    wanted = [a + b for a, b in zip(start.position, (0.0, 0.0, 0.03), strict=True)]
    assert math.dist(final.position, wanted) < 0.001
    assert robot.snapshot().master is None  # released when the script ended


async def test_an_estop_ends_a_remote_script_and_kills_its_worker(
    start_server: Start, tmp_path: Path
) -> None:
    server = await start_server(demo=True)
    path = write(
        tmp_path,
        "loop.py",
        """\
        from arena.script import move_joints

        while True:
            move_joints({"Rotation": 10}, duration=0.2)
            move_joints({"Rotation": 0}, duration=0.2)
        """,
    )
    robot = server.app.manager.get("demo-arm")
    async with trio.open_nursery() as nursery:
        result: list[Any] = []

        async def run() -> None:
            result.append(await run_arena_script(server, path))

        with robot.subscribe(kinds=[CommandHandled]) as events:
            nursery.start_soon(run)
            await next_event(events, lambda e: isinstance(e, CommandHandled))
        await robot.estop("test")
    with trio.fail_after(WAIT):
        while result == []:
            await trio.sleep(0.05)
    (done,) = result
    assert done.returncode == 1
    assert "arena script: the robot was e-stopped (test): the script ended" in done.stderr.decode()
    assert not [pid for pid in script_workers() if pid != os.getpid()]


def test_a_script_master_of_the_configuration_file_is_checked_as_it_loads(
    tmp_path: Path,
) -> None:
    from arena.protocol.errors import ArenaError
    from arena.server.config import ServerConfig
    from arena.server.declared import read_setup

    text = '[[robots]]\nid = "arm"\ntenant = "lab"\n\n[robots.master]\ntype = "script"\n'
    path = write(tmp_path, "lab.toml", text + 'path = "pick.py"\n')
    config = ServerConfig(config_file=path, script_dir=str(tmp_path / "scripts"))
    with pytest.raises(ArenaError, match=r"lab.toml:7: robots\[0\]\.master\.path: No script"):
        read_setup(config)
    write(tmp_path / "scripts" / "lab", "pick.py", "print('pick')\n")
    (robot,) = read_setup(config).robots.values()
    assert robot.master is not None and robot.tenant == "lab"
    outside = write(tmp_path, "out.toml", text + 'path = "/tmp/pick.py"\n')
    with pytest.raises(ArenaError, match=r"out.toml:7: robots\[0\]\.master\.path: Script "):
        read_setup(ServerConfig(config_file=outside, script_dir=str(tmp_path / "scripts")))


@pytest.mark.real_io
async def test_a_script_that_does_not_parse_is_a_fault_naming_its_line(
    autojump_clock: trio.testing.MockClock, tmp_path: Path
) -> None:
    master, arm, _ = await run_stand_in(tmp_path, "from arena.script import wait\n\nwait(0\n")
    ((code, message),) = arm.faults
    assert code == "SCRIPT_FAILED" and message.startswith(f"{tmp_path / 'bounded.py'}, line 3: ")
    assert "SyntaxError" in message and master.outcome == message


async def test_pause_holds_a_remote_script_and_resume_finishes_its_move(
    start_server: Start, tmp_path: Path
) -> None:
    server = await start_server(demo=True)
    path = write(
        tmp_path,
        "slow.py",
        """\
        from arena.script import move_joints

        move_joints({"Rotation": 30}, duration=5)
        move_joints({"Pitch": 10})
        """,
    )
    robot = server.app.manager.get("demo-arm")
    result: list[Any] = []
    async with trio.open_nursery() as nursery:

        async def run() -> None:
            result.append(await run_arena_script(server, path))

        with robot.subscribe(kinds=[CommandHandled]) as events:
            nursery.start_soon(run)
            await next_event(events, lambda e: isinstance(e, CommandHandled))
            async with server.client() as http:
                assert (await http.post(f"{ROBOT}/master/pause")).status_code == 200
                await trio.sleep(0.5)  # (nothing may come meanwhile: checked below)
                paused = [e for e in events.drain() if isinstance(e, CommandHandled)]
                assert (await http.post(f"{ROBOT}/master/resume")).status_code == 200
            with trio.fail_after(WAIT):
                while not result:
                    await trio.sleep(0.05)
            rest = [e for e in events.drain() if isinstance(e, CommandHandled)]
    (done,) = result
    assert done.returncode == 0, done.stderr.decode()
    # While paused the script sent nothing (a command refused MASTER_PAUSED would show here);
    # on the resume its move went again, then its next one.
    assert not paused
    joints = [[(g.name, g.value) for g in e.command.joints] for e in rest]
    assert joints == [[("Rotation", 30)], [("Pitch", 10)]], joints
    assert robot.snapshot().joint("Rotation").virtual_value == pytest.approx(30, abs=0.1)


def test_arena_serve_takes_its_script_and_policy_folders_as_flags(tmp_path: Path) -> None:
    """`--script-dir` and `--policy-dir` (a real `arena serve`, started where neither default
    folder is): a script of the folder given runs, and a missing policy is looked for in the
    policy folder given. They were settings of the file and the environment only."""
    mine, policies = tmp_path / "mine", tmp_path / "models"
    write(mine, "hello.py", 'print("hello")\n')
    argv = ["--demo", "--port", "0", "--no-record"]
    argv += ["--script-dir", str(mine), "--policy-dir", str(policies)]
    with serving(argv, cwd=tmp_path) as served, httpx.Client(base_url=served.url) as http:
        ran = http.post(f"{ROBOT}/master", json={"type": "script", "path": "hello.py"})
        assert ran.status_code == 201, ran.text
        missing = http.post(f"{ROBOT}/master", json={"type": "policy", "path": "cube"})
        assert missing.status_code == 422, missing.text
        assert f"{policies}/cube/config.json" in missing.json()["error"]["message"]
