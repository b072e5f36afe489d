"""The setup a configuration file declares: checked whole naming the line, brought up by the
REST code paths, parts that cannot come up retried with backoff, reloaded without touching what
stays, and written back in the file's form (specs/declared-setup.md)."""

from __future__ import annotations

import os
import signal
import tomllib
from collections.abc import Awaitable, Callable, Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
import trio

from arena import cli
from arena.feetech import registers as reg
from arena.protocol.errors import ArenaError, ErrorCode
from arena.recording.recorder import Recorder
from arena.robot.events import PeerChanged
from arena.robot.manager import RobotManager
from arena.server import declared as declared_module
from arena.server import parts
from arena.server.app import create_app
from arena.server.config import ServerConfig, load_config
from arena.server.declared import DeclaredSetup, read_setup
from arena.server.run import run_server
from arena.servo.sim_pty import PtySimBus
from tests.conftest import RunningServer, eventually
from tests.hardware import running_sim, wait_joined

Start = Callable[..., Awaitable[RunningServer]]

TWO_ROBOTS = """\
port = 0

[[robots]]
id = "left"
name = "Left arm"

[robots.workspace]
floor = 0.0

[[robots.slaves]]
id = "sim"
type = "mock-slave"

[[robots.cameras]]
name = "top"
source = "test-pattern"
fps = 5

[robots.master]
type = "mock-sequence"
sequences = ["gentle-wave"]
loop = true
takeover = false

[[robots]]
id = "right"
robot_type = "koch"

[[robots.slaves]]
type = "mock-slave"
simulateLatency = 5

[[groups]]
id = "pair"
members = ["left", "right"]
stopTogether = true
"""


def write(path: Path, text: str) -> str:
    path.write_text(text, encoding="utf-8")
    return str(path)


async def start_from(start_server: Start, path: str, tmp_path: Path, **more: Any) -> RunningServer:
    """A server as `arena serve --config PATH` starts it (port 0, recordings in the test's)."""
    config = load_config(path, environ={}, port=0, recordings_dir=str(tmp_path / "rec"))
    settings = {name: getattr(config, name) for name in ServerConfig.__dataclass_fields__}
    return await start_server(**{**settings, **more})


# -- checked whole, naming the line --------------------------------------------------------


@pytest.mark.parametrize(
    ("change", "line", "words"),
    [
        (("simulateLatency = 5", "simulatLatency = 5"), 31, "unknown field `simulatLatency`"),
        (("port = 0", "prot = 0"), 1, "unknown setting 'prot'"),
        (('members = ["left", "right"]', 'members = ["left", "rigth"]'), 35, "no robot 'rigth'"),
        (('robot_type = "koch"', 'robot_type = "kochh"'), 27, "kochh"),
        (('sequences = ["gentle-wave"]', 'sequences = ["gentle-wav"]'), 21, "gentle-wav"),
        (('source = "test-pattern"', 'source = "twin"'), 16, "names no physics-slave"),
        (('id = "right"', 'id = "left"'), 26, "a robot of this id comes earlier"),
        (("fps = 5", 'fps = "5"'), 17, "Expected `int | null`, got `str`"),
        (('source = "test-pattern"', 'source = "webcam"'), 14, '"source" must be'),
    ],
)
def test_a_file_is_refused_whole_in_one_line_naming_its_line(
    tmp_path: Path, change: tuple[str, str], line: int, words: str
) -> None:
    assert change[0] in TWO_ROBOTS
    path = write(tmp_path / "lab.toml", TWO_ROBOTS.replace(change[0], change[1]))
    with pytest.raises(ArenaError) as refused:
        read_setup(load_config(path, environ={}))
    assert refused.value.code is ErrorCode.INVALID_CONFIG
    message = refused.value.message
    assert message.startswith(f"{path}:{line}: "), message
    assert words in message and "\n" not in message


def test_the_readmes_lab_file_is_a_valid_setup_and_its_mistake_is_on_the_line_it_says(
    tmp_path: Path,
) -> None:
    root = Path(__file__).resolve().parent.parent
    readme = (root / "README.md").read_text(encoding="utf-8")
    spec = (root / "specs" / "declared-setup.md").read_text(encoding="utf-8")
    text = spec.split("## A lab Pi's file", 1)[1].split("```toml\n", 1)[1].split("```", 1)[0]
    setup = read_setup(ServerConfig(config_file=write(tmp_path / "lab.toml", text)))
    (robot,) = setup.robots.values()
    assert (list(robot.slaves), robot.master is not None, list(robot.cameras)) == (
        ["follower"],
        True,
        ["front"],
    )
    assert "`lab.toml:7: robots[0].slaves[0].prot: ...`" in " ".join(readme.split())
    wrong = write(tmp_path / "lab.toml", text.replace("port =", "prot =", 1))
    with pytest.raises(ArenaError, match=r"lab.toml:7: robots\[0\]\.slaves\[0\]\.prot: "):
        read_setup(ServerConfig(config_file=wrong))


def test_a_policy_master_is_named_in_its_robots_tenant_folder(tmp_path: Path) -> None:
    text = '[[robots]]\nid = "arm"\ntenant = "lab"\n\n[robots.master]\ntype = "policy"\n'
    path = write(tmp_path / "lab.toml", text + 'path = "act_cube"\n')
    config = ServerConfig(config_file=path, policy_dir=str(tmp_path / "policies"))
    with pytest.raises(ArenaError, match=r"lab.toml:7: robots\[0\]\.master\.path: No policy"):
        read_setup(config)
    (tmp_path / "policies" / "act_cube").mkdir(parents=True)  # the default tenant's: not lab's
    (tmp_path / "policies" / "act_cube" / "config.json").write_text("{}")
    with pytest.raises(ArenaError, match="No policy 'act_cube' in this tenant's policy folder"):
        read_setup(config)
    (tmp_path / "policies" / "lab").mkdir()
    (tmp_path / "policies" / "act_cube").rename(tmp_path / "policies" / "lab" / "act_cube")
    (robot,) = read_setup(config).robots.values()
    assert robot.master is not None and robot.tenant == "lab"


def test_arena_serve_refuses_a_bad_file_before_anything_moves(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = write(tmp_path / "lab.toml", TWO_ROBOTS.replace('"right"]', '"nobody"]'))
    recordings = tmp_path / "rec"
    argv = ["serve", "--config", path, "--recordings-dir", str(recordings)]
    assert cli.main(argv) == 2
    error = capsys.readouterr().err.strip()
    assert error.count("\n") == 0 and f"{path}:35: groups[0].members[1]" in error, error
    assert not recordings.exists()  # nothing began: no recording, no robot


# -- brought up as REST would ----------------------------------------------------------------


async def test_the_declared_setup_comes_up_as_if_made_over_rest(
    start_server: Start, tmp_path: Path
) -> None:
    server = await start_from(start_server, write(tmp_path / "lab.toml", TWO_ROBOTS), tmp_path)
    async with server.client() as http:
        left = (await http.get("/api/robots/left")).json()
        assert (left["name"], left["robot_type"], left["pending"]) == ("Left arm", "so-arm100", [])
        assert [(s["id"], s["type"]) for s in left["slaves"]] == [("sim", "mock-slave")]
        assert left["master"]["type"] == "mock-sequence"
        right = (await http.get("/api/robots/right")).json()
        assert right["robot_type"] == "koch"
        assert [(s["id"], s["type"]) for s in right["slaves"]] == [("mock-slave", "mock-slave")]
        workspace = (await http.get("/api/robots/left/workspace")).json()
        assert workspace["floor"] == 0.0
        cameras = (await http.get("/api/robots/left/cameras")).json()["cameras"]
        assert [(c["name"], c["fps"]) for c in cameras] == [("top", 5)]
        frame = await http.get("/api/robots/left/cameras/top/frame")
        assert frame.headers["content-type"] == "image/jpeg"
        group = (await http.get("/api/groups/pair")).json()
        assert (group["members"], group["stopTogether"]) == (["left", "right"], True)
        assert (await http.get("/readyz")).status_code == 200
        # The same bodies as REST: what the file made is saved back as made by hand.
        saved = tomllib.loads((await http.get("/api/config")).text)
    assert saved["robots"][1]["slaves"] == [
        {"id": "mock-slave", "type": "mock-slave", "simulateLatency": 5.0}
    ]


# -- a part that cannot come up ------------------------------------------------------------


@pytest.fixture
def later_sim(tmp_path: Path) -> Iterator[Callable[[], PtySimBus]]:
    """Plug a simulated bus in at tmp_path/ttySIM0 when the test says so."""
    started: list[Iterator[PtySimBus]] = []

    def plug() -> PtySimBus:
        running = running_sim(tmp_path)
        started.append(running)
        return next(running)

    yield plug
    for running in started:
        running.close()


ONE_ARM = """\
[[robots]]
id = "arm"

[[robots.slaves]]
id = "bus"
type = "usb-slave"
port = "{port}"

[[robots.cameras]]
name = "wrist"
source = "{camera}"
"""


async def test_an_adapter_plugged_in_later_is_enough(
    start_server: Start, tmp_path: Path, later_sim: Callable[[], PtySimBus]
) -> None:
    port = tmp_path / "ttySIM0"  # no adapter there yet
    text = ONE_ARM.format(port=port, camera="test-pattern")
    text += '\n[[robots]]\nid = "other"\n\n[[robots.slaves]]\ntype = "mock-slave"\n'
    server = await start_from(start_server, write(tmp_path / "lab.toml", text), tmp_path)
    async with server.client() as http:
        arm = (await http.get("/api/robots/arm")).json()
        assert arm["slaves"] == []
        (pending,) = arm["pending"]
        assert (pending["part"], pending["id"]) == ("slave", "bus")
        assert pending["error"].startswith("PORT_NOT_FOUND") and str(port) in pending["error"]
        assert pending["attempts"] >= 1 and 0 <= pending["retry_in"] <= 30
        # The rest is up: the camera of the same robot, and the other robot's slave.
        assert (await http.get("/api/robots/arm/cameras/wrist/frame")).status_code == 200
        other = (await http.get("/api/robots/other")).json()
        assert [s["connected"] for s in other["slaves"]] == [True]
        ready = await http.get("/readyz")
        assert ready.status_code == 503
        assert any("robot arm: slave bus is not up" in r for r in ready.json()["reasons"])
        sim = later_sim()
        robot = server.app.manager.get("arm")
        await eventually(lambda: robot.snapshot().slaves, timeout=60, what="the retried attach")
        await wait_joined(robot)
        arm = (await http.get("/api/robots/arm")).json()
        assert arm["pending"] == [] and arm["slaves"][0]["connected"]
        assert (await http.get("/readyz")).status_code == 200
    with sim.paused() as bus:  # held: torque on, each goal where the servo is
        assert {s.peek(reg.TORQUE_ENABLE) for s in bus.servos.values()} == {1}


async def test_a_leader_arm_plugged_in_later_becomes_the_master(
    start_server: Start, tmp_path: Path, later_sim: Callable[[], PtySimBus]
) -> None:
    follower = later_sim()
    leader_port = tmp_path / "leader" / "ttySIM0"
    text = ONE_ARM.format(port=follower.link, camera="test-pattern")
    text += f'\n[robots.master]\ntype = "usb-master"\nport = "{leader_port}"\n'
    server = await start_from(start_server, write(tmp_path / "lab.toml", text), tmp_path)
    robot = server.app.manager.get("arm")
    await wait_joined(robot)
    async with server.client() as http:
        arm = (await http.get("/api/robots/arm")).json()
        assert arm["master"] is None and [p["part"] for p in arm["pending"]] == ["master"]
        running = running_sim(tmp_path / "leader")
        next(running)  # the leader's adapter plugged in
        try:
            await eventually(lambda: robot.snapshot().master, timeout=60, what="the leader")
            arm = (await http.get("/api/robots/arm")).json()
            assert (arm["master"]["type"], arm["pending"]) == ("usb-master", [])
            saved = tomllib.loads((await http.get("/api/config")).text)
            assert saved["robots"][0]["master"] == {"type": "usb-master", "port": str(leader_port)}
        finally:
            running.close()


async def test_retries_wait_1_s_doubling_to_30_s_until_the_part_comes_up(
    autojump_clock: trio.testing.MockClock,
    manager: RobotManager,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    app = create_app(manager, ServerConfig(), Recorder(tmp_path, {}, active=False))
    tries: list[float] = []
    plugged = trio.Event()
    attach = parts.attach_slave

    async def attach_slave(*args: Any) -> str:
        tries.append(trio.current_time())
        if not plugged.is_set():
            raise ArenaError(ErrorCode.NO_HARDWARE, "No adapter found.")
        return await attach(*args)

    monkeypatch.setattr(declared_module.parts, "attach_slave", attach_slave)
    text = '[[robots]]\nid = "arm"\n[[robots.slaves]]\ntype = "mock-slave"\n'
    path = write(tmp_path / "lab.toml", text)
    declared = DeclaredSetup(app, path)
    app.declared = declared
    start = trio.current_time()
    await declared.apply(read_setup(ServerConfig(config_file=path)))
    await trio.sleep(200)
    assert [round(t - start, 6) for t in tries] == [0, 1, 3, 7, 15, 31, 61, 91, 121, 151, 181]
    (pending,) = declared.pending_of("arm")
    assert (pending["attempts"], pending["error"]) == (11, "NO_HARDWARE: No adapter found.")
    assert pending["retry_in"] == pytest.approx(11)  # the next at 211 s
    plugged.set()
    await trio.sleep(15)
    assert declared.pending_of("arm") == [] and len(tries) == 12
    assert [s.peer_id for s in manager.get("arm").snapshot().slaves] == ["mock-slave"]
    await trio.sleep(100)
    assert len(tries) == 12  # up: tried no more


async def test_a_robot_id_taken_by_hand_gets_none_of_the_files_parts_until_it_is_free(
    autojump_clock: trio.testing.MockClock, manager: RobotManager, tmp_path: Path
) -> None:
    app = create_app(manager, ServerConfig(), Recorder(tmp_path, {}, active=False))
    hand = await manager.create_robot("so-arm100", robot_id="arm")
    text = '[[robots]]\nid = "arm"\n[[robots.slaves]]\nid = "sim"\ntype = "mock-slave"\n'
    path = write(tmp_path / "lab.toml", text)
    declared = app.declared = DeclaredSetup(app, path)
    start = trio.current_time()
    await declared.apply(read_setup(ServerConfig(config_file=path)))
    assert [p.split(" (")[0] for p in declared.not_ready()] == [
        "robot arm is not up",
        "robot arm: slave sim is not up",
    ]
    await trio.sleep(2)
    assert hand.snapshot().slaves == ()  # never the hand-made robot's
    await parts.delete_robot(app, hand)  # freed at 2 s: the file's is made at its 3 s try
    await eventually(lambda: not declared.pending, what="the robot and its slave up")
    assert trio.current_time() - start == pytest.approx(3, abs=0.1)
    robot = manager.get("arm")
    assert robot is not hand and [s.peer_id for s in robot.snapshot().slaves] == ["sim"]


async def test_a_part_whose_robot_is_deleted_by_hand_is_no_longer_tried(
    autojump_clock: trio.testing.MockClock,
    manager: RobotManager,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    app = create_app(manager, ServerConfig(), Recorder(tmp_path, {}, active=False))

    async def attach_slave(*args: Any) -> str:
        raise ArenaError(ErrorCode.PORT_NOT_FOUND, "No adapter.")

    monkeypatch.setattr(declared_module.parts, "attach_slave", attach_slave)
    text = '[[robots]]\nid = "arm"\n[[robots.slaves]]\ntype = "mock-slave"\n'
    path = write(tmp_path / "lab.toml", text)
    declared = app.declared = DeclaredSetup(app, path)
    await declared.apply(read_setup(ServerConfig(config_file=path)))
    assert len(declared.pending_of("arm")) == 1
    await parts.delete_robot(app, manager.get("arm"))
    await trio.sleep(1.5)
    assert declared.not_ready() == []


# -- reload ------------------------------------------------------------------------------


async def test_reload_changes_what_changed_and_never_rejoins_an_arm_that_stays(
    start_server: Start, tmp_path: Path, later_sim: Callable[[], PtySimBus]
) -> None:
    sim = later_sim()
    lab = tmp_path / "lab.toml"
    first = ONE_ARM.format(port=sim.link, camera="test-pattern") + TWO_ROBOTS.replace(
        "port = 0\n", ""
    )
    server = await start_from(start_server, write(lab, first), tmp_path)
    arm = server.app.manager.get("arm")
    await wait_joined(arm)
    driver = server.app.hardware.find("arm", "bus", {"bus"})[1]
    sim.bus.write_log = []
    # The arm's robot stays as it was; robot right changes its slave, left loses its camera,
    # the group goes, a robot comes.
    second = first.replace("simulateLatency = 5", "simulateLatency = 7")
    second = second.replace('name = "top"\nsource = "test-pattern"\nfps = 5\n', "")
    second = second.replace("[[robots.cameras]]\n\n[robots.master]", "[robots.master]")
    second = second[: second.index("[[groups]]")]
    second += '[[robots]]\nid = "new"\n\n[[robots.slaves]]\ntype = "mock-slave"\n'
    write(lab, second)
    with arm.subscribe(kinds=[PeerChanged]) as events:
        async with server.client() as http:
            reloaded = await http.post("/api/config/reload")
            assert reloaded.status_code == 200, reloaded.text
            changes = reloaded.json()
            assert await http.get("/api/groups/pair") is not None
            assert (await http.get("/api/robots/left/cameras")).json()["cameras"] == []
            right = (await http.get("/api/robots/right")).json()
            assert [s["id"] for s in right["slaves"]] == ["mock-slave"]
            assert (await http.get("/api/robots/new")).status_code == 200
            assert (await http.get("/api/groups/pair")).status_code == 404
        await trio.sleep(0.5)  # a re-join would have begun by now
        seen = events.drain()
    # The arm that stays: the same robot and driver, no event about it, servos never let go.
    assert server.app.manager.get("arm") is arm
    assert server.app.hardware.find("arm", "bus", {"bus"})[1] is driver
    assert seen == []
    torque = reg.TORQUE_ENABLE.address
    assert [w for w in sim.bus.write_log if w[2] == torque] == []
    assert not any(s.joining for s in arm.snapshot().slaves)
    assert changes["added"] == ["robot new", "robot new: slave mock-slave"]
    assert changes["changed"] == ["robot right: slave mock-slave"]
    assert changes["removed"] == ["robot left: camera top", "group pair"]
    assert "robot arm: slave bus" in changes["unchanged"]
    assert "robot arm: camera wrist" in changes["unchanged"]


async def test_a_robot_renamed_in_the_file_is_made_anew_with_its_parts_and_groups(
    autojump_clock: trio.testing.MockClock, manager: RobotManager, tmp_path: Path
) -> None:
    # (no camera: its capture process runs on the real clock)
    text = TWO_ROBOTS.replace('[[robots.cameras]]\nname = "top"\nsource = "test-pattern"\n', "")
    text = text.replace("fps = 5\n", "")
    path = write(tmp_path / "lab.toml", text)
    config = ServerConfig(config_file=path)
    app = create_app(manager, config, Recorder(tmp_path, {}, active=False))
    declared = app.declared = DeclaredSetup(app, path)
    await declared.apply(read_setup(ServerConfig(config_file=path)))
    left, right = manager.get("left"), manager.get("right")
    write(Path(path), text.replace('name = "Left arm"', 'name = "Bench arm"'))
    changes = await declared.reload()
    assert changes["changed"] == [
        "robot left",
        "robot left: workspace",
        "robot left: slave sim",
        "robot left: master",
        "group pair",
    ]
    assert changes["unchanged"] == ["robot right", "robot right: slave mock-slave"]
    assert manager.get("right") is right and manager.get("left") is not left
    snapshot = manager.get("left").snapshot()
    assert (snapshot.name, [s.peer_id for s in snapshot.slaves]) == ("Bench arm", ["sim"])
    assert app.groups.get("pair").members == ("left", "right")
    assert declared.pending == {}


async def test_a_refused_reload_changes_nothing_and_needs_the_whole_servers_admin(
    start_server: Start, tmp_path: Path
) -> None:
    lab = tmp_path / "lab.toml"
    server = await start_from(
        start_server,
        write(lab, TWO_ROBOTS),
        tmp_path,
        api_keys=("admin-key",),
        viewer_keys=("viewer-key",),
    )
    admin = {"Authorization": "Bearer admin-key"}
    write(lab, TWO_ROBOTS.replace('"right"]', '"gone"]').replace("port = 0\n", ""))
    async with server.client() as http:
        refused = await http.post("/api/config/reload", headers=admin)
        assert refused.status_code == 422
        assert refused.json()["error"]["message"].startswith(f"{lab}:34: groups[0].members[1]")
        viewer = {"Authorization": "Bearer viewer-key"}
        assert (await http.post("/api/config/reload", headers=viewer)).status_code == 403
        assert (await http.get("/api/config", headers=viewer)).status_code == 403
        assert (await http.get("/api/config")).status_code == 401
        page = {**admin, "Origin": "http://evil.example"}
        assert (await http.post("/api/config/reload", headers=page)).status_code == 403
        group = await http.get("/api/groups/pair", headers=admin)
        assert group.json()["members"] == ["left", "right"]  # as it was


async def test_sighup_reloads_the_file(nursery: trio.Nursery, tmp_path: Path) -> None:
    lab = tmp_path / "lab.toml"
    write(lab, '[[robots]]\nid = "a"\n')
    config = load_config(str(lab), environ={}, port=0, recordings_dir=str(tmp_path / "rec"))
    done = trio.Event()

    async def run(task_status: trio.TaskStatus[Any]) -> None:
        try:
            await run_server(config, handle_signals=True, task_status=task_status)
        finally:
            done.set()

    app, _ = await nursery.start(run)
    assert [r.robot_id for r in app.manager.robots()] == ["a"]
    write(lab, '[[robots]]\nid = "b"\n')
    os.kill(os.getpid(), signal.SIGHUP)
    await eventually(lambda: [r.robot_id for r in app.manager.robots()] == ["b"], what="reload")
    os.kill(os.getpid(), signal.SIGTERM)
    with trio.fail_after(30):
        await done.wait()


async def test_sighup_without_a_file_is_said_and_the_server_runs_on(
    nursery: trio.Nursery, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    config = ServerConfig(port=0, recordings_dir=str(tmp_path / "rec"))
    done = trio.Event()

    async def run(task_status: trio.TaskStatus[Any]) -> None:
        try:
            await run_server(config, handle_signals=True, task_status=task_status)
        finally:
            done.set()

    _, urls = await nursery.start(run)
    os.kill(os.getpid(), signal.SIGHUP)  # (its default would end the process)
    await eventually(lambda: "no file to reload" in caplog.text, what="the refusal logged")
    async with httpx.AsyncClient(base_url=urls[0], timeout=10) as http:
        assert (await http.get("/healthz")).status_code == 200
        refused = await http.post("/api/config/reload")
        assert refused.json()["error"]["code"] == "INVALID_CONFIG"
    os.kill(os.getpid(), signal.SIGTERM)
    with trio.fail_after(30):
        await done.wait()


# -- written back ---------------------------------------------------------------------------


async def test_the_running_setup_saved_starts_the_same_setup(
    start_server: Start, tmp_path: Path
) -> None:
    first = await start_from(start_server, write(tmp_path / "lab.toml", TWO_ROBOTS), tmp_path)
    async with first.client() as http:  # and some by hand
        made = await http.post("/api/robots", json={"id": "hand", "name": "By hand"})
        assert made.status_code == 201
        slave = {"type": "mock-slave", "responseDelay": 3}
        assert (await http.post("/api/robots/hand/slaves", json=slave)).status_code == 201
        master = {"type": "mock-sequence", "sequences": ["gentle-wave"], "autoStart": False}
        assert (await http.post("/api/robots/hand/master", json=master)).status_code == 201
        camera = {"name": "side", "source": "test-pattern", "width": 320, "height": 240}
        assert (await http.post("/api/robots/hand/cameras", json=camera)).status_code == 201
        box = {"keep_out": [{"min": [0, 0, 0], "max": [0.1, 0.1, 0.1], "name": "cup"}]}
        assert (await http.put("/api/robots/hand/workspace", json=box)).status_code == 200
        group = {"id": "all", "members": ["left", "hand"]}
        assert (await http.post("/api/groups", json=group)).status_code == 201
        assert (await http.delete("/api/robots/right/slaves/mock-slave")).status_code == 200
        text = (await http.get("/api/config")).text
        before = await _described(http)
    saved = tomllib.loads(text)
    assert [r["id"] for r in saved["robots"]] == ["left", "right", "hand"]
    assert "slaves" not in saved["robots"][1]  # detached by hand: not saved
    second = await start_from(start_server, write(tmp_path / "saved.toml", text), tmp_path)
    async with second.client() as http:
        assert (await http.get("/api/config")).text == text
        assert await _described(http) == before


async def _described(http: httpx.AsyncClient) -> list[Any]:
    """What makes each robot what it is (no ids of the moment, no times)."""
    found: list[Any] = []
    for listed in (await http.get("/api/robots")).json():
        robot = (await http.get(f"/api/robots/{listed['id']}")).json()
        cameras = (await http.get(f"/api/robots/{listed['id']}/cameras")).json()["cameras"]
        workspace = (await http.get(f"/api/robots/{listed['id']}/workspace")).json()
        found.append(
            (
                robot["id"],
                robot["name"],
                robot["robot_type"],
                [(s["id"], s["type"]) for s in robot["slaves"]],
                robot["master"] and robot["master"]["type"],
                [(c["name"], c["source"], c["width"], c["height"]) for c in cameras],
                workspace,
            )
        )
    groups = (await http.get("/api/groups")).json()["groups"]
    found.append([(g["id"], g["members"], g["stopTogether"]) for g in groups])
    return found
