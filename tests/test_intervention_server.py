"""Pause, resume and intervention through a real server: a tiny LeRobot policy (random
weights, in a real worker process) paused and resumed without a reload; an operator who
intervenes over REST, a WebSocket master that intervenes and releases, a WebSocket master told
it is paused; the refusals, the roles and the e-stop that ends both masters.

These wait for events (the robot's own, answers over HTTP and WebSocket); the one real wait
("nothing comes while paused") can only pass more easily on a slow machine."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import httpx
import trio
from trio_websocket import open_websocket_url

from arena.client import MasterSession
from arena.robot.events import CommandHandled
from tests.conftest import RunningServer
from tests.test_intervention import SlowToLetGo
from tests.test_policy_server import (
    LOAD,
    ROBOT,
    Start,
    attach,
    next_event,
    ready,
    tiny,  # noqa: F401 (the fixture)
    workers,
)
from tests.test_server_ws import closed_with, command, receive
from tests.test_users import SECRET, bearer, token

SEQUENCE = {"type": "mock-sequence", "sequences": ["gentle-wave"], "loop": True}


async def details(http: httpx.AsyncClient, **headers: str) -> dict[str, Any]:
    answer = await http.get(ROBOT, headers=headers or None)
    assert answer.status_code == 200, answer.text
    result: dict[str, Any] = answer.json()
    return result


async def test_a_paused_policy_keeps_its_worker_and_resumes_within_the_step_limit(
    start_server: Start,
    tiny: Path,  # noqa: F811 (the fixture)
) -> None:
    server = await start_server(demo=True)
    robot = await ready(server)
    with robot.subscribe(kinds=[CommandHandled]) as events:
        answer = await attach(server, tiny, task="wave", fps=30)
        assert answer.status_code == 201, answer.text
        identity = answer.json()["id"]

        def policys(event: Any) -> bool:
            return isinstance(event, CommandHandled) and event.source == identity

        for _ in range(5):
            await next_event(events, policys)
        (pid,) = workers()
        async with httpx.AsyncClient(base_url=server.url, timeout=LOAD) as http:
            master = (await details(http))["master"]
            assert master["figures"]["loads"] == 1 and not master["paused"]
            paused = await http.post(f"{ROBOT}/master/pause")
            assert paused.status_code == 200, paused.text
            assert paused.json()["state"] == "paused" and paused.json()["master"]["paused"]
            # The answer counts the pause it made (it said 0 until the policy's control loop
            # had noticed it), and so does the robot's link: once.
            assert paused.json()["master"]["figures"]["pauses"] == 1, paused.json()
            link = robot._actor.peers.master.link
            assert link.pauses == 1
            shown = await details(http)
            assert shown["state"] == "paused" and shown["master"]["paused"] is True
            events.drain()
            await trio.sleep(1.0)  # several control periods: nothing may come
            assert not [e for e in events.drain() if policys(e) and e.result.accepted]
            assert workers() == [pid]  # the worker stays, loaded
            held = {j["name"]: j["real_value"] for j in (await http.get(f"{ROBOT}/joints")).json()}
            resumed = await http.post(f"{ROBOT}/master/resume")
            assert resumed.status_code == 200, resumed.text
            assert resumed.json()["state"] == "mastered"
            first = await next_event(events, lambda e: policys(e) and e.result.accepted)
            # The first step after the resume: within the step limit (10 degrees) of the pose
            # measured at the resume (the robot held it; the mock slave reports it).
            for goal in first.command.joints:
                assert abs(goal.value - held[goal.name]) <= 10.0 + 0.5, goal
            for _ in range(5):
                await next_event(events, policys)
            master = (await details(http))["master"]
            assert not master["paused"]
            assert master["figures"]["loads"] == 1 and master["figures"]["pauses"] == 1
        assert workers() == [pid]  # never reloaded: the same process


async def secured(start_server: Start, tmp_path: Path) -> RunningServer:
    (tmp_path / "jwt-secret").write_bytes(SECRET)
    return await start_server(demo=True, jwt_secret_file=str(tmp_path / "jwt-secret"))


ALICE = bearer(token("operator", sub="alice"))
BOB = bearer(token("operator", sub="bob"))
VIEWER = bearer(token("viewer", sub="carol"))


async def test_an_operator_intervenes_over_rest_and_hands_back(
    start_server: Start, tmp_path: Path
) -> None:
    server = await secured(start_server, tmp_path)
    joints = {"joints": [{"name": "Rotation", "value": 12}]}
    async with server.client() as http:
        nobody = await http.post(f"{ROBOT}/intervention", headers=ALICE)
        assert nobody.status_code == 409 and nobody.json()["error"]["code"] == "NO_MASTER"
        started = await http.post(f"{ROBOT}/master", json=SEQUENCE, headers=ALICE)
        assert started.status_code == 201, started.text
        refused = await http.post(f"{ROBOT}/intervention", headers=VIEWER)
        assert refused.status_code == 403
        taken = await http.post(f"{ROBOT}/intervention", json={}, headers=ALICE)
        assert taken.status_code == 201, taken.text
        assert taken.json()["intervening"] == "operator:alice"
        shown = await details(http, **ALICE)
        assert shown["state"] == "intervened"
        assert shown["master"]["id"] == "operator:alice" and not shown["master"]["paused"]
        assert shown["paused_master"]["kind"] == "mock-sequence"
        assert shown["paused_master"]["paused"] is True
        # The intervening operator commands over REST; anyone else is refused.
        moved = await http.put(f"{ROBOT}/joints", json=joints, headers=ALICE)
        assert moved.status_code == 200, moved.text
        other = await http.put(f"{ROBOT}/joints", json=joints, headers=BOB)
        assert other.status_code == 409 and other.json()["error"]["code"] == "MASTER_ACTIVE"
        for path in ("intervention", "master/pause", "master/resume"):
            busy = await http.post(f"{ROBOT}/{path}", headers=BOB)
            assert busy.status_code == 409, (path, busy.text)
            assert busy.json()["error"]["code"] == "INTERVENTION_ACTIVE"
        back = await http.request("DELETE", f"{ROBOT}/intervention", headers=ALICE)
        assert back.status_code == 200, back.text
        assert back.json()["state"] == "mastered"
        assert back.json()["master"]["kind"] == "mock-sequence"
        assert back.json()["paused_master"] is None and not back.json()["master"]["paused"]
        again = await http.request("DELETE", f"{ROBOT}/intervention", headers=ALICE)
        assert again.status_code == 409 and again.json()["error"]["code"] == "NO_INTERVENTION"
        # The operator's manual control is over with the intervention.
        late = await http.put(f"{ROBOT}/joints", json=joints, headers=ALICE)
        assert late.status_code == 409
        # Handed back without resuming: the master stays paused.
        await http.post(f"{ROBOT}/intervention", headers=ALICE)
        kept = await http.request(
            "DELETE", f"{ROBOT}/intervention", json={"resume": False}, headers=ALICE
        )
        assert kept.json()["state"] == "paused" and kept.json()["master"]["paused"]
        # An e-stop ends the intervention and the paused master both.
        assert (await http.post(f"{ROBOT}/master/resume", headers=ALICE)).status_code == 200
        await http.post(f"{ROBOT}/intervention", headers=ALICE)
        stopped = await http.post(f"{ROBOT}/estop", headers=BOB)
        assert stopped.status_code == 200
        shown = await details(http, **ALICE)
        assert shown["master"] is None and shown["paused_master"] is None
        assert (await http.post(f"{ROBOT}/reset", headers=BOB)).status_code == 200
        shown = await details(http, **ALICE)
        assert shown["state"] == "idle" and shown["master"] is None  # nothing resumed


async def test_a_websocket_master_intervenes_and_its_release_hands_back(
    server: RunningServer,
) -> None:
    async with server.client() as http:
        started = await http.post(f"{ROBOT}/master", json=SEQUENCE)
        assert started.status_code == 201, started.text
        robot = server.app.manager.get("demo-arm")
        async with open_websocket_url(
            f"{server.ws_url}/ws/master/demo-arm?intervene=1&id=fixer"
        ) as ws:
            await receive(ws, "state")
            shown = await details(http)
            assert shown["master"]["id"] == "fixer"
            assert shown["paused_master"]["kind"] == "mock-sequence"
            with robot.subscribe(kinds=[CommandHandled]) as events:
                ack = await command(ws, {"Rotation": 8.0})
                assert ack["data"]["status"] == "accepted", ack
                sources = {e.source for e in events.drain()}
                assert sources == {"fixer"}  # the paused sequence sent nothing meanwhile
            await ws.send_message(json.dumps({"type": "release"}))
            released = await receive(ws, "released")
            assert released["data"]["mode"] == "mastered"
            assert await closed_with(ws) == 1000
        shown = await details(http)
        assert shown["master"]["kind"] == "mock-sequence" and not shown["master"]["paused"]
        assert shown["paused_master"] is None


async def test_a_websocket_master_is_told_it_is_paused_and_its_commands_wait(
    server: RunningServer,
) -> None:
    async with (
        server.client() as http,
        open_websocket_url(f"{server.ws_url}/ws/master/demo-arm?id=remote") as ws,
    ):
        await receive(ws, "state")
        assert (await http.post(f"{ROBOT}/master/pause")).status_code == 200
        await receive(ws, "pause")
        refused = await command(ws, {"Rotation": 3.0})
        assert refused["data"]["status"] == "refused", refused
        assert refused["data"]["code"] == "MASTER_PAUSED"
        assert (await http.post(f"{ROBOT}/master/resume")).status_code == 200
        await receive(ws, "resume")
        ack = await command(ws, {"Rotation": 3.0})
        assert ack["data"]["status"] == "accepted", ack


async def test_a_client_master_session_knows_it_is_paused(server: RunningServer) -> None:
    """What `arena policy` (a policy on another machine) reads to send nothing while paused."""
    async with MasterSession.open(server.url, "demo-arm") as master, server.client() as http:
        assert not master.paused
        assert (await http.post(f"{ROBOT}/master/pause")).status_code == 200
        await master.wait_for(lambda session: session.paused)
        assert (await http.post(f"{ROBOT}/master/resume")).status_code == 200
        with trio.fail_after(10):
            await master.wait_resumed()
        assert not master.paused


def metric(text: str, name: str, robot: str = "demo-arm") -> float | None:
    """The value of `name{robot="..."}` in a /metrics text (None: not there)."""
    for line in text.splitlines():
        if line.startswith(f'{name}{{robot="{robot}"}} '):
            return float(line.split()[-1])
    return None


async def test_corrections_are_counted_per_episode_in_the_details_and_on_metrics(
    start_server: Start,
) -> None:
    server = await start_server(demo=True)
    async with server.client() as http:
        assert (await http.post(f"{ROBOT}/master", json=SEQUENCE)).status_code == 201
        assert (await details(http))["corrections"] == {"total": 0, "episode": None}

        async def correct() -> None:
            assert (await http.post(f"{ROBOT}/intervention", json={})).status_code == 201
            assert (await http.delete(f"{ROBOT}/intervention")).status_code == 200

        await correct()  # before any episode: counted in the total only
        started = await http.post(f"{ROBOT}/episodes/start", json={"task": "wave"})
        assert started.status_code == 201
        assert (await details(http))["corrections"] == {"total": 1, "episode": 0}
        await correct()
        await correct()
        assert (await details(http))["corrections"] == {"total": 3, "episode": 2}
        episodes = (await http.get(f"{ROBOT}/episodes")).json()
        assert episodes["active"]["corrections"] == 2
        text = (await http.get("/metrics")).text
        assert metric(text, "arena_interventions_total") == 3
        assert metric(text, "arena_episode_corrections") == 2
        # A new episode counts from zero; without one running, no episode figure.
        assert (await http.post(f"{ROBOT}/episodes/stop")).status_code == 200
        assert (await details(http))["corrections"] == {"total": 3, "episode": None}
        assert metric((await http.get("/metrics")).text, "arena_episode_corrections") is None
        assert (await http.post(f"{ROBOT}/episodes/start", json={"task": "again"})).is_success
        assert (await details(http))["corrections"] == {"total": 3, "episode": 0}


async def test_the_intervening_operator_moves_the_hand_over_rest_too(
    server: RunningServer,
) -> None:
    """`PUT .../pose` is manual control like `PUT .../joints`: the operator who intervenes
    (`{}`) moves the hand with it; it was refused MASTER_ACTIVE naming the operator itself."""
    async with server.client() as http:
        started = await http.post(f"{ROBOT}/master", json=SEQUENCE)
        assert started.status_code == 201, started.text
        taken = await http.post(f"{ROBOT}/intervention", json={})
        assert taken.status_code == 201, taken.text
        here = (await http.get(f"{ROBOT}/pose")).json()["commanded"]["position"]
        goal = [here[0], here[1], here[2] + 0.02]
        moved = await http.put(f"{ROBOT}/pose", json={"position": goal})
        assert moved.status_code == 200, moved.text
        back = await http.request("DELETE", f"{ROBOT}/intervention")
        assert back.status_code == 200, back.text
        # Without the intervention the master drives, and the pose is refused again.
        late = await http.put(f"{ROBOT}/pose", json={"position": goal})
        assert late.status_code == 409 and late.json()["error"]["code"] == "MASTER_ACTIVE"


async def test_manual_control_refused_by_a_master_says_which_and_what_to_do(
    server: RunningServer,
) -> None:
    """A command over REST while a master drives is refused MASTER_ACTIVE with the master in
    words (a user's own planned move or sequence had only an id like 'master-4') and the ways
    out: wait, intervene, or detach it."""
    joints = {"joints": [{"name": "Rotation", "value": 12}]}
    async with server.client() as http:
        started = await http.post(f"{ROBOT}/master", json=SEQUENCE)
        assert started.status_code == 201, started.text
        master = started.json()["id"]
        for method, path, body in (
            ("PUT", "joints", joints),
            ("PUT", "pose", {"position": [0.0, -0.25, 0.2]}),
            ("POST", "move", {"joints": {"Rotation": 12}}),
            ("POST", "move", {"joints": {"Rotation": 12}, "plan": True}),
        ):
            refused = await http.request(method, f"{ROBOT}/{path}", json=body)
            assert refused.status_code == 409, (path, body, refused.text)
            error = refused.json()["error"]
            assert error["code"] == "MASTER_ACTIVE", (path, error)
            message = error["message"]
            assert f"{master!r} (sequence 'gentle-wave' in a loop)" in message, (path, message)
            assert "POST /api/robots/demo-arm/intervention" in message, (path, message)
            assert "DELETE /api/robots/demo-arm/master" in message, (path, message)


async def test_rest_hand_back_and_detach_answer_once_the_masters_hardware_let_go(
    server: RunningServer,
) -> None:
    """`DELETE .../intervention` and `DELETE .../master` answer once the driver of the master
    that goes has let its hardware go (a leader arm limp, its port free), not before."""
    robot = server.app.manager.get("demo-arm")
    async with server.client() as http:
        sequence = {"type": "mock-sequence", "sequences": ["gentle-wave"], "loop": True}
        assert (await http.post("/api/robots/demo-arm/master", json=sequence)).is_success
        leader = SlowToLetGo(0.5)
        await robot.attach_master(leader, intervene=True)
        back = await http.request("DELETE", "/api/robots/demo-arm/intervention")
        assert back.status_code == 200, back.text
        assert leader.closed  # (an answer before it let go would find it still holding)
        await http.request("DELETE", "/api/robots/demo-arm/master")
        leader = SlowToLetGo(0.5)
        await robot.attach_master(leader)
        gone = await http.request("DELETE", "/api/robots/demo-arm/master")
        assert gone.status_code == 200 and gone.json()["detached"], gone.text
        assert leader.closed
