"""Fleets: several Arena nodes joined over Zenoh on 127.0.0.1, explicit endpoints, no multicast.

Nodes are real servers (port 0 for HTTP and for Zenoh); one test runs a node as its own
process and kills it. Waits are for events (a listing that shows what it must), bounded only
so that a broken test ends.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
from collections.abc import Awaitable, Callable
from functools import partial
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
import trio
from trio_websocket import ConnectionClosed, open_websocket_url

from arena.fleet.node import FleetNode, FleetSettings, Tunnel
from arena.fleet.tunnel import TunnelSocket
from arena.protocol.errors import ArenaError, ErrorCode
from arena.protocol.ws_frames import UpgradeRequest, WebSocketClosed
from arena.recording.mcap_file import read_recording
from arena.server import fleet_api
from tests.conftest import RunningServer, eventually, need

need("zenoh", "fleet")

Start = Callable[..., Awaitable[RunningServer]]


async def start_fleet(start_server: Start, names: list[str], **first: Any) -> list[RunningServer]:
    """Nodes `names`, each listening on a port of its own choosing; the others connect to the
    first and find each other through it (Zenoh's gossip). Returns once every node sees every
    other."""
    hub = await start_server(node=names[0], fleet_listen=("tcp/127.0.0.1:0",), **first)
    locators = tuple(await hub.app.fleet.locators())
    assert locators and locators[0].startswith("tcp/127.0.0.1:")
    nodes = [hub]
    for name in names[1:]:
        nodes.append(
            await start_server(node=name, fleet_listen=("tcp/127.0.0.1:0",), fleet_connect=locators)
        )

    async def all_see_all() -> bool:
        return all(
            {n for n, v in node.app.fleet.nodes.items() if v.alive} >= set(names) for node in nodes
        )

    await eventually(all_see_all)

    async def all_answer_all() -> bool:
        """Every node's questions reach every other: Zenoh routes a query a little after a
        node is seen (on a loaded machine, long enough for one asked at once to find no one)."""
        for node in nodes:
            for name in names:
                if name != node.app.fleet.name:
                    with contextlib.suppress(ArenaError):
                        await node.app.fleet.ask(name, "info", timeout=30)
                        continue
                    return False
        return True

    await eventually(all_answer_all, what="every node answering every other")
    return nodes


async def robot_states(server: RunningServer) -> dict[str, tuple[str, str]]:
    async with server.client() as http:
        listing = (await http.get("/api/fleet/robots")).json()
    return {r["id"]: (r["node"], r["state"]) for r in listing["robots"]}


def test_fleet_settings_are_checked() -> None:
    FleetSettings("a", "lab", ("tcp/127.0.0.1:7447",)).check()
    for bad in (
        FleetSettings("a b"),
        FleetSettings("a", "lab/1"),
        FleetSettings("a", connect=("127.0.0.1:7447",)),
        FleetSettings("a", lease_ms=10),
    ):
        with pytest.raises(ArenaError):
            bad.check()


async def test_three_nodes_list_each_other_and_refuse_a_taken_id(start_server: Start) -> None:
    a, b, c = await start_fleet(start_server, ["a", "b", "c"], demo=True)
    async with b.client() as http:
        assert (await http.post("/api/robots", json={"id": "arm-b"})).status_code == 201
    async with c.client() as http:
        assert (await http.post("/api/robots", json={"id": "arm-c"})).status_code == 201
        nodes = (await http.get("/api/fleet/nodes")).json()
        assert nodes["node"] == "c"
        listed = {n["name"]: n for n in nodes["nodes"]}
        assert set(listed) == {"a", "b", "c"}
        assert all(n["alive"] and n["version"] for n in listed.values())
        assert listed["a"]["robots"] == ["demo-arm"] and listed["b"]["robots"] == ["arm-b"]
        assert listed["a"]["locators"] and listed["a"]["http"] == a.url
        # an id another node holds is refused, with a code of its own
        taken = await http.post("/api/robots", json={"id": "arm-b"})
        assert taken.status_code == 409
        assert taken.json()["error"]["code"] == "ROBOT_ELSEWHERE"
        assert "'b'" in taken.json()["error"]["message"]
        status = (await http.get("/")).json()
        assert status["fleet"]["node"] == "c" and status["fleet"]["fleet"] == "default"
    assert await robot_states(a) == {
        "demo-arm": ("a", "idle"),
        "arm-b": ("b", "idle"),
        "arm-c": ("c", "idle"),
    }
    # REST for another node's robot, through any node: its rules, its answer
    async with c.client() as http:
        remote = await http.get("/api/robots/demo-arm")
        assert remote.status_code == 200 and remote.headers["x-arena-node"] == "a"
        assert remote.json()["slaves"][0]["id"] == "demo-mock-slave"
        moved = await http.put(
            "/api/robots/demo-arm/joints", json={"joints": [{"name": "Rotation", "value": 12}]}
        )
        assert moved.json()["status"] == "accepted"
        assert (await http.get("/api/robots/nowhere")).status_code == 404
    assert a.app.manager.get("demo-arm").snapshot().joint("Rotation").goal == 12
    # each node's recording names its node and fleet
    async with a.client() as http:
        name = (await http.post("/api/recordings/current/stop")).json()["stopped"]
    recording = read_recording(Path(a.app.recorder.folder) / name)
    assert (recording.metadata["arena"]["node"], recording.metadata["arena"]["fleet"]) == (
        "a",
        "default",
    )
    # the command that came through node c is in the recording of the robot's node
    (moved_record,) = [m for m in recording.messages if m.kind == "command"]
    assert moved_record.data["joints"][0]["value"] == 12


def command(value: float) -> str:
    return json.dumps(
        {"type": "command", "data": {"joints": [{"name": "Rotation", "value": value}]}}
    )


async def next_of(ws: Any, kind: str) -> dict[str, Any]:
    """The next message of `kind`."""
    while True:
        message = json.loads(await ws.get_message())
        if message["type"] == kind:
            return message


async def test_a_master_on_one_node_drives_a_slave_on_another_and_takeover_crosses(
    start_server: Start,
) -> None:
    a, b, c = await start_fleet(start_server, ["a", "b", "c"])
    async with a.client() as http:
        assert (await http.post("/api/robots", json={"id": "arm"})).status_code == 201
    await eventually(_known([b, c], "arm"))
    async with (
        open_websocket_url(a.ws_url + "/ws/slave/arm?id=real-arm") as slave,
        open_websocket_url(b.ws_url + "/ws/master/arm?id=operator") as master,
    ):
        await master.send_message(command(10))
        ack = await next_of(master, "ack")
        assert ack["data"]["status"] == "accepted"
        rotation = None
        with trio.fail_after(30):
            while rotation != 10:  # the trajectory's targets, to the goal (within limits)
                execute = await next_of(slave, "execute_command")
                rotation = {j["name"]: j["value"] for j in execute["data"]["joints"]}["Rotation"]
        await slave.send_message(
            json.dumps({"type": "joint_states", "data": [{"name": "Rotation", "value": 10}]})
        )
        # the robot's own node holds the master; every node says so, and a viewer through a
        # third node sees the state and the joints the slave reported
        assert a.app.manager.get("arm").snapshot().owner == "operator"
        async with open_websocket_url(c.ws_url + "/ws/robots/arm/state") as viewer:
            state = await next_of(viewer, "state")
            assert (state["data"]["mode"], state["data"]["owner"]) == ("mastered", "operator")
            joints = await next_of(viewer, "joint_states")
            real = {j["name"]: j["real_value"] for j in joints["data"]}
            assert real["Rotation"] == 10
        async with c.client() as http:
            assert (await http.get("/api/robots/arm/status")).json()["state"] == "mastered"
        # a second master through a third node is refused by the robot's rules...
        async with open_websocket_url(c.ws_url + "/ws/master/arm?id=other") as second:
            refusal = await next_of(second, "error")
            assert refusal["data"]["code"] == "MASTER_ACTIVE"
            with pytest.raises(ConnectionClosed) as closed:
                await second.get_message()
            assert closed.value.reason.code == 4409
        # ...unless it takes over, and the first master is told
        async with open_websocket_url(c.ws_url + "/ws/master/arm?id=boss&takeover=true") as boss:
            await boss.send_message(command(-5))
            assert (await next_of(boss, "ack"))["data"]["status"] == "accepted"
            told = await next_of(master, "detached")
            assert told["data"]["code"] == "TAKEN_OVER"
            with pytest.raises(ConnectionClosed) as ended:
                await master.get_message()
            assert ended.value.reason.code == 4409
            assert a.app.manager.get("arm").snapshot().owner == "boss"


def _known(servers: list[RunningServer], robot_id: str) -> Callable[[], Awaitable[bool]]:
    """A check: every one of `servers` knows which node owns `robot_id`."""

    async def check() -> bool:
        return all(s.app.fleet.robot_nodes.get(robot_id) is not None for s in servers)

    return check


async def test_a_fleet_estop_reaches_every_node_and_every_dashboard_sees_it(
    start_server: Start,
) -> None:
    nodes = await start_fleet(start_server, ["a", "b", "c"])
    for node in nodes:
        async with node.client() as http:
            for i in range(3):
                robot = {"id": f"{node.app.fleet.name}-{i}"}
                assert (await http.post("/api/robots", json=robot)).status_code == 201
    heard: list[tuple[str, str, str]] = []
    nodes[0].app.fleet.on_remote_state.append(
        lambda node, robot, state: heard.append((node, robot, state["mode"]))
    )
    async with nodes[1].client() as http:
        answer = (await http.post("/api/fleet/estop", json={"reason": "drill"})).json()
    assert answer["complete"] and answer["missing"] == []
    assert {ack["node"]: sorted(ack["robots"]) for ack in answer["acks"]} == {
        name: [f"{name}-0", f"{name}-1", f"{name}-2"] for name in ("a", "b", "c")
    }
    assert all(0 < ack["ms"] < 1000 for ack in answer["acks"])
    for node in nodes:
        assert all(str(r.snapshot().mode) == "estopped" for r in node.app.manager.robots())
    # node a heard the others' e-stops as they were published
    await eventually(_heard_all(heard))
    states = await robot_states(nodes[2])
    assert {state for _, state in states.values()} == {"estopped"}


def _heard_all(heard: list[tuple[str, str, str]]) -> Callable[[], Awaitable[bool]]:
    """A check: the e-stops of the six robots of nodes b and c were heard."""

    async def check() -> bool:
        stopped = {(node, robot) for node, robot, mode in heard if mode == "estopped"}
        return len(stopped) == 6

    return check


async def robots_on(fleet: list[RunningServer], count: int) -> None:
    """`count` robots on each node, named `<node>-<k>`, known to every node."""
    for node in fleet:
        async with node.client() as http:
            for k in range(count):
                robot = {"id": f"{node.app.fleet.name}-{k}"}
                assert (await http.post("/api/robots", json=robot)).status_code == 201
    for node in fleet:
        await eventually(_known(fleet, f"{node.app.fleet.name}-0"))


def stopped_on(node: RunningServer) -> set[str]:
    """The robots of `node` that are e-stopped."""
    return {r.robot_id for r in node.app.manager.robots() if str(r.snapshot().mode) == "estopped"}


async def test_a_fleet_estop_with_a_node_whose_estop_failed_is_incomplete_and_names_it(
    start_server: Start, monkeypatch: pytest.MonkeyPatch
) -> None:
    a, b, c = fleet = await start_fleet(start_server, ["a", "b", "c"])
    await robots_on(fleet, 2)

    async def bus_gone(reason: str) -> None:
        raise RuntimeError("bus gone")

    monkeypatch.setattr(b.app.manager, "estop_all", bus_gone)
    monkeypatch.setattr(fleet_api, "ESTOP_TIMEOUT", 10.0)  # a and c answer, however slow
    async with a.client() as http:
        answer = await http.post("/api/fleet/estop", json={"reason": "drill"})
    body = answer.json()
    assert answer.status_code == 503 and body["complete"] is False
    assert body["failed"] == [{"node": "b", "code": "INTERNAL_ERROR", "message": "bus gone"}]
    assert [ack["node"] for ack in body["acks"]] == ["a", "c"] and body["missing"] == []
    assert body["error"]["code"] == "ESTOP_INCOMPLETE"
    assert "'b'" in body["error"]["message"] and "bus gone" in body["error"]["message"]
    assert stopped_on(a) == {"a-0", "a-1"} and stopped_on(c) == {"c-0", "c-1"}
    assert stopped_on(b) == set()  # what the answer says: b's robots are not known stopped


async def test_a_fleet_estop_names_the_node_that_did_not_answer_in_time(
    start_server: Start, monkeypatch: pytest.MonkeyPatch
) -> None:
    _, b, c = fleet = await start_fleet(start_server, ["a", "b", "c"])
    await robots_on(fleet, 1)
    # node b's e-stop is held until the asker has its answer: b cannot be in time, however
    # long the wait (2 s here, so that a and c are in time on any machine; 100 ms in service)
    monkeypatch.setattr(fleet_api, "ESTOP_TIMEOUT", 2.0)
    release = trio.Event()
    estop = b.app.fleet.services["estop"]

    async def held(payload: bytes) -> Any:
        await release.wait()
        return await estop(payload)

    b.app.fleet.services["estop"] = held
    async with c.client() as http:
        answer = await http.post("/api/fleet/estop", json={"reason": "drill"})
    release.set()
    body = answer.json()
    assert answer.status_code == 503 and body["complete"] is False
    assert body["missing"] == ["b"] and body["failed"] == []
    assert [ack["node"] for ack in body["acks"]] == ["a", "c"]
    assert "'b' did not answer within 2000 ms" in body["error"]["message"]
    # b's stop was only late: once let go, it happens
    await eventually(_estopped(b, {"b-0"}))


async def test_asking_one_node_passes_on_its_refusal_and_names_it_when_it_is_silent(
    start_server: Start, monkeypatch: pytest.MonkeyPatch
) -> None:
    a, b = await start_fleet(start_server, ["a", "b"])
    # (Those two given all the time a loaded machine may take; only the last has a deadline.)
    assert "version" in await a.app.fleet.ask("b", "info", timeout=30)
    # A refusal comes back as the answering node said it: its code and its sentence.
    monkeypatch.delitem(b.app.fleet.services, "http")
    with pytest.raises(ArenaError) as refused:
        await a.app.fleet.ask("b", "http", timeout=30)
    assert refused.value.code is ErrorCode.NOT_FOUND
    assert refused.value.message == "Node b offers no http."
    # A node that answers after the asker's own timeout did not answer: the asker gives up
    # at its timeout (0.3 s), not at the default (1 s), before b answers (0.8 s after it was
    # asked, from b's side, so always after the asker's deadline: a slow machine only makes
    # b later; the real-time wait separates the two timeouts, it decides nothing else).
    answered = trio.Event()

    async def slow(payload: bytes) -> Any:
        await trio.sleep(0.8)
        answered.set()
        return "late"

    monkeypatch.setitem(b.app.fleet.services, "info", slow)
    with pytest.raises(ArenaError) as silent:
        await a.app.fleet.ask("b", "info", timeout=0.3)
    assert silent.value.code is ErrorCode.NODE_LOST
    assert silent.value.message == "Node 'b' did not answer."
    await answered.wait()  # b did answer, too late


async def test_a_garbled_answer_from_a_stranger_on_the_fleet_is_passed_over(
    start_server: Start, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Anyone who reaches the fleet's Zenoh network can answer its queries: an answer that is
    # not JSON, or an error (which Arena's nodes never send: a refusal is an answer carrying
    # `error`), is left out, and the nodes' answers still come back.
    import zenoh

    from arena.fleet import keys

    a, b = await start_fleet(start_server, ["a", "b"])
    info = b.app.fleet.services["info"]

    async def unhurried(payload: bytes) -> Any:  # b answers after the strangers have
        await trio.sleep(0.2)
        return await info(payload)

    monkeypatch.setitem(b.app.fleet.services, "info", unhurried)
    config = zenoh.Config()
    config.insert_json5("mode", '"peer"')
    config.insert_json5("connect/endpoints", json.dumps(await a.app.fleet.locators()))
    config.insert_json5("scouting/multicast/enabled", "false")
    session = await trio.to_thread.run_sync(zenoh.open, config)
    asked = trio.Event()
    token = trio.lowlevel.current_trio_token()
    rogue = keys.service(a.app.fleet.fleet, "rogue", "info")
    failing = keys.service(a.app.fleet.fleet, "failing", "info")

    def answer(query: Any) -> None:
        query.reply(rogue, b"\xff not json")
        token.run_sync_soon(asked.set)

    queryables = [
        session.declare_queryable(rogue, answer),
        session.declare_queryable(failing, lambda query: query.reply_err(b"no")),
    ]
    try:

        async def heard() -> bool:  # the stranger's queryable is known to the asker
            answers = await a.app.fleet.ask_all("info")
            return asked.is_set() and set(answers) == {"a", "b"}

        await eventually(heard)
    finally:
        for queryable in queryables:
            queryable.undeclare()
        await trio.to_thread.run_sync(session.close)


def _estopped(node: RunningServer, robots: set[str]) -> Callable[[], Awaitable[bool]]:
    """A check: these robots of `node` are e-stopped."""

    async def check() -> bool:
        return stopped_on(node) == robots

    return check


async def test_a_robot_of_a_node_that_left_answers_node_lost_naming_it(
    start_server: Start,
) -> None:
    hub, far = await start_fleet(start_server, ["hub", "far"])
    async with far.client() as http:
        assert (await http.post("/api/robots", json={"id": "arm"})).status_code == 201
    await eventually(_known([hub], "arm"))
    assert (await robot_states(hub))["arm"] == ("far", "idle")
    far.stop.set()  # the node leaves (its session closes: its tokens go at once)
    await far.done.wait()

    async def far_is_gone() -> bool:
        view = hub.app.fleet.nodes.get("far")
        return view is not None and not view.alive

    await eventually(far_is_gone)
    assert (await robot_states(hub))["arm"] == ("far", "offline")
    async with hub.client() as http:
        for path in ("/api/robots/arm", "/api/robots/arm/status"):
            gone = await http.get(path)
            assert gone.status_code == 503, path
            error = gone.json()["error"]
            assert error["code"] == "NODE_LOST" and "'far'" in error["message"]
        moved = await http.put(
            "/api/robots/arm/joints", json={"joints": [{"name": "Rotation", "value": 5}]}
        )
        assert moved.status_code == 503 and moved.json()["error"]["code"] == "NODE_LOST"
        # a robot no node ever had is still not found
        assert (await http.get("/api/robots/nowhere")).status_code == 404
    async with open_websocket_url(hub.ws_url + "/ws/master/arm") as master:
        told = await next_of(master, "error")
        assert told["data"]["code"] == "NODE_LOST" and "'far'" in told["data"]["message"]
        with pytest.raises(ConnectionClosed) as closed:
            await master.get_message()
        assert closed.value.reason.code == 4503


def spawn_node(name: str, connect: str, folder: Path) -> subprocess.Popen[bytes]:
    """`arena serve --node NAME --demo` as a process of its own, connected to `connect`."""
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "arena.cli",
            "serve",
            "--port",
            "0",
            "--demo",
            "--node",
            name,
            "--fleet-connect",
            connect,
            "--fleet-listen",
            "tcp/127.0.0.1:0",
            "--recordings-dir",
            str(folder),
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        env={**os.environ, "LOG_LEVEL": "WARNING"},
    )


async def test_a_killed_node_goes_offline_its_masters_are_told_and_it_comes_back(
    start_server: Start, tmp_path: Path
) -> None:
    (hub,) = await start_fleet(start_server, ["hub"])
    (locator,) = await hub.app.fleet.locators()

    async def demo_is(state: str) -> bool:
        return (await robot_states(hub)).get("demo-arm") == ("far", state)

    process = spawn_node("far", locator, tmp_path / "far")
    try:
        await eventually(partial(demo_is, "idle"), timeout=60)
        async with open_websocket_url(hub.ws_url + "/ws/master/demo-arm") as master:
            await master.send_message(command(3))
            assert (await next_of(master, "ack"))["data"]["status"] == "accepted"
            process.send_signal(signal.SIGKILL)  # no goodbye: the lease must tell
            process.wait()
            with trio.fail_after(30):  # the lease is 1 s; 30 s only if it is broken
                told = await next_of(master, "error")
            assert told["data"]["code"] == "NODE_LOST"
            with pytest.raises(ConnectionClosed) as closed:
                await master.get_message()
            assert closed.value.reason.code == 4503
        assert await demo_is("offline")
        async with hub.client() as http:
            nodes = {
                n["name"]: n["alive"] for n in (await http.get("/api/fleet/nodes")).json()["nodes"]
            }
            assert nodes == {"hub": True, "far": False}
            gone = await http.get("/api/robots/demo-arm")
            assert gone.status_code == 503  # not routed to a node that is gone: it says so
            assert gone.json()["error"]["code"] == "NODE_LOST"
        process = spawn_node("far", locator, tmp_path / "far-again")
        await eventually(partial(demo_is, "idle"), timeout=60)
        async with hub.client() as http:
            back = await http.get("/api/robots/demo-arm")
            assert back.status_code == 200 and back.headers["x-arena-node"] == "far"
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()


async def test_a_node_that_has_left_the_fleet_asks_no_one_and_says_so() -> None:
    node = FleetNode(FleetSettings(node="solo", listen=("tcp/127.0.0.1:0",)))
    async with trio.open_nursery() as nursery:
        await nursery.start(node.run)
        nursery.cancel_scope.cancel()  # it leaves
    for ask in (partial(node.ask_all, "info"), partial(node.ask, "solo", "info")):
        with pytest.raises(ArenaError) as info:
            await ask()
        assert info.value.code is ErrorCode.NODE_LOST
        assert info.value.message == "This node has left the fleet."


async def test_without_node_no_zenoh_is_loaded(tmp_path: Path) -> None:
    code = (
        "import sys, trio\n"
        "from arena.server.config import ServerConfig\n"
        "from arena.server.run import run_server\n"
        "async def main():\n"
        "    stop = trio.Event()\n"
        "    async with trio.open_nursery() as n:\n"
        f"        await n.start(lambda task_status: run_server(ServerConfig(port=0, "
        f"recordings_dir={str(tmp_path)!r}), stop=stop, task_status=task_status))\n"
        "        stop.set()\n"
        "trio.run(main)\n"
        "print('zenoh' in sys.modules)\n"
    )
    result = await trio.run_process(
        [sys.executable, "-c", code], capture_stdout=True, capture_stderr=True
    )
    assert result.stdout.decode().strip().endswith("False")


async def test_the_fleet_api_says_when_there_is_no_fleet(server: RunningServer) -> None:
    async with server.client() as http:
        answer = await http.get("/api/fleet/nodes")
        assert answer.status_code == 404 and "--node" in answer.json()["error"]["message"]
        assert (await http.get("/")).json()["fleet"] is None


def make_certificates(folder: Path) -> Path:
    """A CA and a certificate for localhost signed by it (openssl); a Zenoh config using them."""

    def openssl(*args: str) -> None:
        subprocess.run(["openssl", *args], cwd=folder, check=True, capture_output=True)

    openssl(
        "req",
        "-x509",
        "-newkey",
        "rsa:2048",
        "-nodes",
        "-keyout",
        "ca.key",
        "-out",
        "ca.pem",
        "-days",
        "2",
        "-subj",
        "/CN=arena-test-ca",
    )
    openssl(
        "req",
        "-newkey",
        "rsa:2048",
        "-nodes",
        "-keyout",
        "node.key",
        "-out",
        "node.csr",
        "-subj",
        "/CN=localhost",
    )
    (folder / "ext.cnf").write_text("subjectAltName=DNS:localhost\nbasicConstraints=CA:FALSE\n")
    openssl(
        "x509",
        "-req",
        "-in",
        "node.csr",
        "-CA",
        "ca.pem",
        "-CAkey",
        "ca.key",
        "-CAcreateserial",
        "-out",
        "node.pem",
        "-days",
        "2",
        "-extfile",
        "ext.cnf",
    )
    config = folder / "zenoh.json5"
    tls = {
        "root_ca_certificate": str(folder / "ca.pem"),
        "listen_private_key": str(folder / "node.key"),
        "listen_certificate": str(folder / "node.pem"),
    }
    config.write_text(json.dumps({"transport": {"link": {"tls": tls}}}))
    return config


@pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl command")
async def test_nodes_join_over_tls_and_a_node_without_the_ca_cannot(
    start_server: Start, tmp_path: Path
) -> None:
    config = make_certificates(tmp_path)
    secure = {"fleet_zenoh_config": str(config)}
    hub = await start_server(node="hub", fleet_listen=("tls/localhost:0",), demo=True, **secure)
    (locator,) = await hub.app.fleet.locators()
    assert locator.startswith("tls/localhost:")
    # a node that does not trust the fleet's CA never gets in; one started just after it that
    # does is in at once (the stranger had as long, and more)
    other = tmp_path / "other"
    other.mkdir()
    stranger = await start_server(
        node="stranger",
        fleet_connect=(locator,),
        fleet_zenoh_config=str(make_certificates(other)),
        recordings_dir=str(tmp_path / "stranger"),
    )
    member = await start_server(node="member", fleet_connect=(locator,), **secure)
    await eventually(_known([member], "demo-arm"))
    assert (await robot_states(member))["demo-arm"] == ("hub", "idle")
    assert await robot_states(stranger) == {}
    assert set(stranger.app.fleet.nodes) == {"stranger"}
    assert "stranger" not in hub.app.fleet.nodes


async def test_a_tunnel_socket_hands_over_the_messages_in_hand_and_its_close() -> None:
    # A master carried from another node reads a burst whole as a local one does: the
    # messages already in the tunnel's inbox, without waiting; the end of the tunnel ends it.
    tunnel = Tunnel(SimpleNamespace(tunnels={}), "tunnel-1", "key", "node-b")  # type: ignore[arg-type]
    socket = TunnelSocket(tunnel, UpgradeRequest("/ws/master/arm"))
    for data in (b"tfirst", b"?what the tunnel does not know", b"tsecond"):
        tunnel.deliver(data)
    assert await socket.receive() == "first"
    assert socket.holds_more()
    assert socket.next_in_hand() == "second"
    assert socket.next_in_hand() is None and not socket.holds_more()
    tunnel.deliver(b'c{"code": 4000, "reason": "bye"}')
    with pytest.raises(WebSocketClosed) as closed:
        socket.next_in_hand()
    assert closed.value.code == 4000 and socket.close_sent
