"""Sessions that end cleanly: a master's `release`, a client whose every call ends, and who
may take a robot over (and the displaced master told who did). Real servers on port 0."""

from __future__ import annotations

import base64
import contextlib
import hashlib
import json
import re
from collections.abc import Awaitable, Callable
from functools import partial
from pathlib import Path
from typing import Any

import httpx
import pytest
import trio
from trio_websocket import open_websocket_url

from arena import cli
from arena.client import ClientTimeout, MasterSession, Refused
from arena.recording.mcap_file import read_recording
from arena.recording.replay import recorded_commands
from arena.robot.handle import Robot
from arena.robot.motion import Command
from tests.conftest import RecordingSlave, RunningServer, eventually
from tests.scenarios import behaviour, record_scenario, replay_session

StartServer = Callable[..., Awaitable[RunningServer]]
README = Path(__file__).resolve().parent.parent / "README.md"
CLIENT_SPEC = README.with_name("specs") / "client.md"
GOLDEN = Path(__file__).resolve().parent.parent / "recordings" / "golden" / "gentle-wave.mcap"


def readme_agent() -> Callable[..., Awaitable[None]]:
    """specs/client.md's agent example, as its `agent` function."""
    block = re.search(r"## Agent example\s+```python\n(.*?)```", CLIENT_SPEC.read_text(), re.S)
    assert block is not None
    namespace: dict[str, Any] = {}
    exec(
        compile(block.group(1).replace("trio.run(agent)", ""), "specs/client.md", "exec"), namespace
    )
    agent: Callable[..., Awaitable[None]] = namespace["agent"]
    return agent


async def receive(ws: Any) -> dict[str, Any]:
    message: dict[str, Any] = json.loads(await ws.get_message())
    return message


async def until_type(ws: Any, kind: str) -> dict[str, Any]:
    """The next message of type `kind` (others skipped)."""
    with trio.fail_after(10):
        while True:
            message = await receive(ws)
            if message["type"] == kind:
                return message


# --- release ----------------------------------------------------------------------------------


async def test_after_the_readme_agent_the_robot_is_free_and_the_file_says_released(
    server: RunningServer, capsys: pytest.CaptureFixture[str]
) -> None:
    await readme_agent()(server.url, "demo-arm", 2)
    assert len(capsys.readouterr().out.strip().splitlines()) == 2  # the agent ran
    async with server.client() as http:
        status = (await http.get("/api/robots/demo-arm/status")).json()
        assert (status["state"], status["has_master"], status["estop_reason"]) == (
            "idle",
            False,
            None,
        )
        # The README's next requests: manual control, then a sequence.
        moved = await http.put(
            "/api/robots/demo-arm/joints", json={"joints": [{"name": "Jaw", "value": 3}]}
        )
        assert moved.status_code == 200, moved.text
        played = await http.post("/api/robots/demo-arm/play-sequence/gentle-wave")
        assert played.status_code == 200, played.text
        name = (await http.post("/api/recordings/current/stop")).json()["stopped"]
    recording = read_recording(Path(server.app.recorder.folder) / name)
    peers = [m.data for m in recording.messages if m.kind == "peer" and m.data["role"] == "master"]
    agent = next(p["peer_id"] for p in peers if p["kind"] == "websocket")
    assert [p["change"] for p in peers if p["peer_id"] == agent] == ["attached", "released"]
    states = [m.data for m in recording.messages if m.kind == "state"]
    assert not any(s["mode"] == "estopped" for s in states)
    released = [s for s in states if s["cause"] == "released by the master"]
    assert [(s["mode"], s["owner"]) for s in released] == [("idle", None)]


async def test_release_with_hold_stops_the_arm_and_a_socket_closed_without_release_estops(
    server: RunningServer,
) -> None:
    robot = server.app.manager.get("demo-arm")
    url = server.ws_url + "/ws/master/demo-arm?id=agent"
    async with open_websocket_url(url) as ws:
        # A move long enough that no machine finishes it before the release below.
        command = {"joints": [{"name": "Rotation", "value": 40}], "duration": 60_000}
        await ws.send_message(json.dumps({"type": "command", "data": command}))
        assert (await until_type(ws, "ack"))["data"]["status"] == "accepted"
        await eventually(lambda: (robot.snapshot().joint("Rotation").real_value or 0) > 1)
        await ws.send_message(json.dumps({"type": "release", "data": {"hold": True}}))
        answer = await until_type(ws, "released")
        assert answer["data"] == {"robot_id": "demo-arm", "mode": "idle"}
        held = robot.snapshot().joint("Rotation")
        assert 0 < held.goal < 40  # held where it was, not carried on to 40
        with trio.fail_after(10):  # then the server closes, normally
            while True:
                try:
                    await ws.get_message()
                except Exception as closed:
                    assert closed.reason.code == 1000  # type: ignore[attr-defined]
                    break
    await master_connections_closed(server)
    after = robot.snapshot()
    assert (str(after.mode), after.owner) == ("idle", None)
    assert after.joint("Rotation").goal == held.goal
    # Without a release, losing the master is what it was: an e-stop.
    async with open_websocket_url(url) as ws:
        await until_type(ws, "state")
    await eventually(lambda: str(robot.snapshot().mode) == "estopped", what="the e-stop")
    assert "master 'agent' lost" in (robot.snapshot().estop_reason or "")


@pytest.mark.parametrize(
    ("release", "rotation"),
    [
        ({"type": "release"}, 90.0),  # the accepted move completes
        ({"type": "release", "data": {"hold": True}}, None),  # stopped where it was
    ],
)
async def test_a_release_lets_the_accepted_move_complete_unless_it_asks_to_hold(
    mock_clock: trio.testing.MockClock,
    start_server: StartServer,
    release: dict[str, Any],
    rotation: float | None,
) -> None:
    # Trio's clock stands still but when the test moves it: held, the arm is where its
    # trajectory had got it 0.1 s after the command when the master let go, short of 90.
    server = await start_server(record=False)
    robot = await server.app.manager.create_robot("so-arm100", robot_id="arm")
    slave = RecordingSlave()
    await robot.attach_slave(slave)
    async with open_websocket_url(server.ws_url + "/ws/master/arm") as ws:
        command = {"joints": [{"name": "Rotation", "value": 90}]}
        await ws.send_message(json.dumps({"type": "command", "data": command}))
        assert (await until_type(ws, "ack"))["data"]["status"] == "accepted"
        mock_clock.jump(0.1)
        await ws.send_message(json.dumps(release))
        answer = await receive(ws)
        while answer["type"] in ("state", "joint_states"):
            answer = await receive(ws)
        assert (answer["type"], answer["data"]) == ("released", {"robot_id": "arm", "mode": "idle"})
    for _ in range(100):  # 2 s, tick by tick: time enough for the move
        mock_clock.jump(0.02)
        await trio.testing.wait_all_tasks_blocked()
    joint = robot.snapshot().joint("Rotation")
    if rotation is None:  # held: stopped on its way, where the last target put it
        rotation = joint.virtual_value
        assert 5.0 < rotation < 30.0  # 0.1 s of a jerk-limited start (200 deg/s at most)
    assert joint.virtual_value == pytest.approx(rotation, abs=0.5)
    assert joint.goal == pytest.approx(rotation, abs=0.5)
    assert slave.targets[-1][1]["Rotation"] == pytest.approx(rotation, abs=0.5)
    assert str(robot.snapshot().mode) == "idle" and robot.estop_count == 0


async def test_a_group_master_releases_every_member(start_server: StartServer) -> None:
    server = await start_server()
    async with server.client() as http:
        for robot in ("left", "right"):
            assert (await http.post("/api/robots", json={"id": robot})).status_code == 201
        made = await http.post("/api/groups", json={"id": "pair", "members": ["left", "right"]})
        assert made.status_code == 201
    async with MasterSession.open(server.url, "pair") as master:
        await master.command({"Rotation": 5})
    assert master.released == {
        "robot_id": "pair",
        "mode": "idle",
        "members": {"left": "idle", "right": "idle"},
    }
    for robot in ("left", "right"):
        snapshot = server.app.manager.get(robot).snapshot()
        assert (str(snapshot.mode), snapshot.master) == ("idle", None)


async def test_a_session_that_ends_with_an_exception_does_not_release(
    server: RunningServer,
) -> None:
    with pytest.raises(KeyError):  # the block's own exception, as it was raised
        async with MasterSession.open(server.url, "demo-arm", master_id="crashing") as master:
            await master.command({"Rotation": 5})
            raise KeyError("the agent's bug")
    robot = server.app.manager.get("demo-arm")
    await eventually(lambda: str(robot.snapshot().mode) == "estopped", what="the e-stop")
    assert "crashing" in (robot.snapshot().estop_reason or "")


async def released_mid_move(robot: Robot, *, hold: bool) -> None:
    """A master starts a slow move and releases the robot half-way."""
    link = await robot.connect_master("agent")
    await link.command(Command.of({"Rotation": 40.0}, duration=4.0))
    await trio.sleep(1.005)  # between two control ticks: the same order on replay
    await link.release(hold=hold)
    await trio.sleep(4.0)


@pytest.mark.parametrize("hold", [False, True])
async def test_a_release_is_recorded_and_replays_the_same(
    autojump_clock: trio.testing.MockClock, tmp_path: Path, hold: bool
) -> None:
    (path,) = await record_scenario(tmp_path, partial(released_mid_move, hold=hold))
    recording = read_recording(path)
    peers = [m.data for m in recording.messages if m.kind == "peer" and m.data["role"] == "master"]
    assert [(p["peer_id"], p["change"]) for p in peers] == [
        ("agent", "attached"),
        ("agent", "released"),
    ]
    original = behaviour(recording, "arm")
    last = original[-1][2]["Rotation"]
    if hold:
        assert 0 < last < 40  # the move stopped where the release found it
    else:
        assert last == pytest.approx(40.0)  # the move accepted completed
    copy = await replay_session(recording, "arm")
    assert behaviour(copy, "arm") == original


async def test_arena_replay_releases_the_robot_at_its_end(
    server: RunningServer, capsys: pytest.CaptureFixture[str]
) -> None:
    args = ["replay", str(GOLDEN), "--robot", "arm", "--speed", "20"]
    args += ["--to", server.ws_url + "/ws/master/demo-arm"]
    assert await trio.to_thread.run_sync(cli.main, args) == 0
    assert "0 refused" in capsys.readouterr().out
    robot = server.app.manager.get("demo-arm")
    await master_connections_closed(server)  # a loss would show by then
    snapshot = robot.snapshot()
    assert (str(snapshot.mode), snapshot.master, robot.estop_count) == ("idle", None, 0)
    # The release let the last move complete: the arm heads for the recording's last pose.
    last: dict[str, float] = {}
    for timed in recorded_commands(read_recording(GOLDEN), "arm"):
        last.update({goal.name: goal.value for goal in timed.command.joints})
    assert {name: snapshot.joint(name).goal for name in last} == pytest.approx(last)


async def test_arena_replay_onto_a_robot_with_a_master_is_refused_unless_it_takes_over(
    server: RunningServer, capsys: pytest.CaptureFixture[str]
) -> None:
    """A robot another master drives: `arena replay` said "sent 1 commands, 0 refused" and
    exited 0 though the server had refused it; now one line naming --takeover, exit 2, and
    `--takeover` replaces the master."""
    async with httpx.AsyncClient(base_url=server.url) as http:
        looping = {"type": "mock-sequence", "sequences": ["gentle-wave"], "loop": True}
        started = await http.post("/api/robots/demo-arm/master", json=looping)
        assert started.status_code == 201, started.text
    args = ["replay", str(GOLDEN), "--robot", "arm", "--speed", "20"]
    args += ["--to", server.ws_url + "/ws/master/demo-arm"]
    assert await trio.to_thread.run_sync(cli.main, args) == 2
    out, err = capsys.readouterr()
    last = err.splitlines()[-1]
    assert last.startswith("arena replay: ") and "--takeover" in last, err
    assert "sent" not in out, out
    robot = server.app.manager.get("demo-arm")
    assert robot.snapshot().master is not None  # the sequence still drives
    assert await trio.to_thread.run_sync(cli.main, [*args, "--takeover"]) == 0
    assert "0 refused" in capsys.readouterr().out
    await master_connections_closed(server)
    assert (str(robot.snapshot().mode), robot.snapshot().master) == ("idle", None)


async def test_arena_replay_taken_over_while_it_plays_ends_without_an_error(
    server: RunningServer, capsys: pytest.CaptureFixture[str]
) -> None:
    """A takeover closes the replay's socket with 4409, MASTER_ACTIVE's close code too, after
    `detached TAKEN_OVER`: that is the server ending it (said, exit 0), not a refusal."""
    args = ["replay", str(GOLDEN), "--robot", "arm", "--loop"]
    args += ["--to", server.ws_url + "/ws/master/demo-arm"]
    robot = server.app.manager.get("demo-arm")
    async with trio.open_nursery() as nursery:
        status: list[int] = []

        async def replay() -> None:
            status.append(await trio.to_thread.run_sync(cli.main, args))

        nursery.start_soon(replay)
        await eventually(lambda: robot.snapshot().master is not None, what="the replay drives")
        async with httpx.AsyncClient(base_url=server.url) as http:
            taken = await http.post("/api/robots/demo-arm/play-sequence/gentle-wave")
            assert taken.status_code == 200, taken.text
    assert status == [0]
    err = capsys.readouterr().err
    assert "server: " in err and "took over" in err and "arena replay:" not in err, err


async def master_connections_closed(server: RunningServer) -> None:
    """Wait until the server has finished with every master WebSocket (a master lost shows by
    then: the server tells the robot before it counts the connection closed)."""
    await eventually(lambda: server.app.metrics.connections["master"] == 0, what="masters closed")


# --- a client that never hangs --------------------------------------------------------------


@pytest.mark.parametrize("value", [float("nan"), float("inf"), None, "ten", True])
async def test_a_value_that_is_no_finite_number_is_refused_before_sending(
    server: RunningServer, value: Any
) -> None:
    async with MasterSession.open(server.url, "demo-arm") as master:
        with pytest.raises(ValueError, match="'Rotation'"):
            await master.command({"Rotation": value})
        # nothing went out: the connection is as good as before
        assert (await master.command({"Rotation": 1}))["data"]["status"] == "accepted"
        with pytest.raises(ValueError):  # not in the other fields either
            await master.command({"Rotation": 2}, duration=float("nan"))
        with pytest.raises(ValueError, match=r"metadata\.note"):
            await master.command({"Rotation": 2}, metadata={"note": [float("inf")]})
        with pytest.raises(ValueError, match="speed"):  # a field the protocol does not have
            await master.command({"Rotation": 2}, speed=5)
        assert (await master.command({"Rotation": 2}))["data"]["status"] == "accepted"


async def test_a_second_master_session_is_refused_with_the_servers_code(
    server: RunningServer,
) -> None:
    async with MasterSession.open(server.url, "demo-arm") as first:
        with pytest.raises(Refused) as second:
            async with MasterSession.open(server.url, "demo-arm"):
                pytest.fail("a second master was let in")
        assert second.value.code == "MASTER_ACTIVE"
        assert (await first.command({"Rotation": 2}))["data"]["status"] == "accepted"
    with pytest.raises(Refused) as unknown:
        async with MasterSession.open(server.url, "no-such-arm"):
            pass
    assert unknown.value.code == "UNKNOWN_ROBOT"


async def test_refusals_and_errors_raise_with_the_servers_code(server: RunningServer) -> None:
    async with MasterSession.open(server.url, "demo-arm") as master:
        with pytest.raises(Refused) as unknown:
            await master.command({"Elbowz": 3})
        assert unknown.value.code == "UNKNOWN_JOINT" and "Elbow" in unknown.value.message
        with pytest.raises(Refused) as invalid:  # answered with an `error`, not an ack
            await master.play({"commands": "not a list"})
        assert invalid.value.code == "INVALID_MESSAGE"
        await master.estop("test")
        with pytest.raises(Refused) as stopped:
            await master.command({"Rotation": 3})
        assert stopped.value.code == "ESTOPPED"
        await master.reset()
        assert (await master.command({"Rotation": 3}))["data"]["status"] == "accepted"
        # Taken over: whatever waits ends with the notice's code.
        async with open_websocket_url(server.ws_url + "/ws/master/demo-arm?takeover=1"):
            with pytest.raises(Refused) as taken:
                await master.command({"Rotation": 4})
            assert taken.value.code in ("TAKEN_OVER", "DISCONNECTED", "NOT_OWNER")


async def silent_server(nursery: trio.Nursery, received: trio.Event) -> str:
    """A server that accepts the WebSocket handshake and the master (its first `state`), then
    never answers anything; sets `received` once the first frame after the handshake came in."""

    async def serve(stream: trio.SocketStream) -> None:
        request = b""
        while b"\r\n\r\n" not in request:
            request += await stream.receive_some(4096)
        key = re.search(rb"Sec-WebSocket-Key: (\S+)", request, re.I)
        assert key is not None
        magic = b"258EAFA5-E914-47DA-95CA-C5AB0DC85B11"
        accept = base64.b64encode(hashlib.sha1(key.group(1) + magic).digest())
        await stream.send_all(
            b"HTTP/1.1 101 Switching Protocols\r\nUpgrade: websocket\r\n"
            b"Connection: Upgrade\r\nSec-WebSocket-Accept: " + accept + b"\r\n\r\n"
        )
        state = json.dumps({"type": "state", "data": {}}).encode()
        await stream.send_all(bytes([0x81, len(state)]) + state)  # a text frame, unmasked
        while await stream.receive_some(4096):  # read, never answer
            received.set()

    listeners = await nursery.start(partial(trio.serve_tcp, serve, 0, host="127.0.0.1"))
    port = listeners[0].socket.getsockname()[1]
    return f"http://127.0.0.1:{port}"


async def test_a_server_that_never_answers_times_out_on_trios_clock(
    nursery: trio.Nursery, mock_clock: trio.testing.MockClock
) -> None:
    received = trio.Event()
    url = await silent_server(nursery, received)
    async with MasterSession.open(url, "arm", release=False) as master:
        outcome: list[BaseException] = []

        async def command() -> None:
            try:
                await master.command({"Rotation": 1})
            except ClientTimeout as error:
                outcome.append(error)

        async with trio.open_nursery() as waiting:
            waiting.start_soon(command)
            await received.wait()  # the command is out; from here on virtual time runs
            started = trio.current_time()
            mock_clock.autojump_threshold = 0
        (error,) = outcome
        assert error.code == "TIMEOUT" and isinstance(error, TimeoutError)
        assert trio.current_time() - started == pytest.approx(5.0, abs=0.01)  # the default
        with pytest.raises(ClientTimeout):  # a release is bounded too
            await master.release(timeout=2.0)


# --- who may take over ------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("path", "body", "kind", "description", "by_default"),
    [
        (
            "/api/robots/demo-arm/master",
            {"type": "mock-sequence", "sequences": ["tiny-flex"]},
            "mock-sequence",
            "sequence 'tiny-flex'",
            True,  # the seed's demo sequences: "automatic master takeover"
        ),
        (
            "/api/robots/demo-arm/master",
            {"type": "replay", "recording": "golden.mcap"},
            "replay",
            "replay of 'golden.mcap'",
            False,
        ),
        (
            "/api/robots/demo-arm/replay",
            {"recording": "golden.mcap"},
            "replay",
            "replay of 'golden.mcap'",
            False,
        ),
    ],
)
async def test_rest_masters_take_over_only_when_asked_and_say_who_they_are(
    server: RunningServer,
    path: str,
    body: dict[str, Any],
    kind: str,
    description: str,
    by_default: bool,
) -> None:
    folder = Path(server.app.recorder.folder)
    folder.mkdir(parents=True, exist_ok=True)  # (made with the first file otherwise)
    (folder / "golden.mcap").write_bytes(GOLDEN.read_bytes())
    robot = server.app.manager.get("demo-arm")
    url = server.ws_url + "/ws/master/demo-arm?id=alice"
    async with open_websocket_url(url) as alice, server.client() as http:
        await until_type(alice, "state")
        # A path that takes over by default refuses when told not to; the others refuse unless
        # they ask.
        refused = await http.post(path, json={**body, "takeover": False} if by_default else body)
        assert refused.status_code == 409, refused.text
        error = refused.json()["error"]
        assert error["code"] == "MASTER_ACTIVE" and '"takeover": true' in error["message"]
        assert robot.snapshot().owner == "alice"  # nothing changed
        taken = await http.post(path, json=body if by_default else {**body, "takeover": True})
        assert taken.status_code == 201, taken.text
        told = await until_type(alice, "detached")
    new_id = taken.json().get("id") or taken.json()["master"]
    assert told["data"]["code"] == "TAKEN_OVER"
    assert told["data"]["by"] == {"id": new_id, "kind": kind, "description": description}
    assert description in told["data"]["message"] and repr(new_id) in told["data"]["message"]


async def test_play_sequence_takes_over_by_itself_and_names_the_sequence(
    server: RunningServer,
) -> None:
    url = server.ws_url + "/ws/master/demo-arm?id=alice"
    async with open_websocket_url(url) as alice, server.client() as http:
        await until_type(alice, "state")
        played = await http.post("/api/robots/demo-arm/play-sequence/gentle-wave")
        assert played.status_code == 200, played.text
        told = await until_type(alice, "detached")
    master = played.json()["master"]
    assert told["data"] == {
        "code": "TAKEN_OVER",
        "message": f"Master {master!r} (sequence 'gentle-wave') took over the robot.",
        "by": {"id": master, "kind": "mock-sequence", "description": "sequence 'gentle-wave'"},
    }


async def test_a_websocket_takeover_names_the_person_who_took_over(server: RunningServer) -> None:
    url = server.ws_url + "/ws/master/demo-arm"
    async with open_websocket_url(url + "?id=alice") as alice:
        await until_type(alice, "state")
        async with open_websocket_url(url + "?id=bob") as bob:  # no takeover: refused
            refused = await until_type(bob, "error")
        assert refused["data"]["code"] == "MASTER_ACTIVE"
        async with open_websocket_url(url + "?id=carol&takeover=1"):
            told = await until_type(alice, "detached")
    assert told["data"]["by"] == {
        "id": "carol",
        "kind": "websocket",
        "description": "WebSocket client",
    }
    assert "'carol'" in told["data"]["message"]


# --- what the master is, in the robot's details ----------------------------------------------


@pytest.mark.parametrize(
    ("start", "kind", "description"),
    [
        (
            ("/api/robots/demo-arm/master", {"type": "mock-sequence", "loop": True}),
            "mock-sequence",
            "sequences 'gentle-wave', 'small-scan', 'tiny-flex' in a loop",
        ),
        (
            ("/api/robots/demo-arm/replay", {"recording": "golden.mcap", "loop": True}),
            "replay",
            "replay of 'golden.mcap' in a loop",
        ),
        (None, "websocket", "WebSocket client"),
    ],
    ids=["sequences", "replay", "websocket"],
)
async def test_the_robot_details_and_its_viewers_say_what_the_master_is(
    server: RunningServer,
    start: tuple[str, dict[str, Any]] | None,
    kind: str,
    description: str,
) -> None:
    folder = Path(server.app.recorder.folder)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "golden.mcap").write_bytes(GOLDEN.read_bytes())
    viewer_url = server.ws_url + "/ws/robots/demo-arm/state"
    async with (
        open_websocket_url(viewer_url) as viewer,
        server.client() as http,
        contextlib.AsyncExitStack() as held,
    ):
        assert (await until_type(viewer, "state"))["data"]["master"] is None
        if start is None:  # a person's WebSocket, held open while the details are read
            url = server.ws_url + "/ws/master/demo-arm?id=alice"
            await held.enter_async_context(open_websocket_url(url))
            master_id = "alice"
        else:  # looping, so that it still plays when the details are read
            answer = await http.post(start[0], json=start[1])
            assert answer.status_code in (200, 201), answer.text
            master_id = answer.json().get("id") or answer.json()["master"]
        expected = {"id": master_id, "kind": kind, "description": description}
        assert (await until_type(viewer, "state"))["data"]["master"] == expected
        shown = [
            (await http.get("/api/robots/demo-arm")).json()["master"],
            (await http.get("/api/robots/demo-arm/status")).json()["master"],
            *[r["master"] for r in (await http.get("/api/robots")).json() if r["id"] == "demo-arm"],
        ]
    assert len(shown) == 3
    for entry in shown:
        assert {key: entry[key] for key in expected} == expected
        assert entry["type"] == kind and entry["connected"] is True
