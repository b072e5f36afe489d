"""Tenants (issue 49): each tenant's robots recorded into files of its own and read back by
the mcap library; a token's tenant and scope held on every node of a fleet (a node serves a
call from another node as the caller it was sent, and a robot out of scope on a node that left
is as absent as any)."""

from __future__ import annotations

import io
import json
import os
import signal
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
import trio
from mcap.reader import make_reader
from trio_websocket import open_websocket_url

from arena.fleet import forward
from arena.fleet import tunnel as tunnels
from arena.fleet.node import NodeView
from arena.protocol.errors import ArenaError, ErrorCode
from arena.recording.mcap_file import FileSeries, read_recording
from arena.recording.recorder import Recorder
from arena.recording.writer_process import McapWriterProcess, TenantFiles, pack_events
from arena.robot.events import Audited, StateChanged
from arena.robot.manager import open_manager
from arena.robot.model import load_robot_model
from arena.robot.safety import Mode
from arena.server.identity import Principal, Role
from arena.servo.calibration import Calibration
from arena.servo.sim_pty import PtySimBus
from tests.conftest import RunningServer, eventually, need
from tests.hardware import running_sim
from tests.test_server_ws import closed_with, receive
from tests.test_users import ADMIN_KEY, SECRET, StartServer, bearer, token


@pytest.fixture
def secret_file(tmp_path: Path) -> Path:
    path = tmp_path / "jwt-secret"
    path.write_bytes(SECRET + b"\n")
    return path


# -- recordings ------------------------------------------------------------------------------------


async def test_each_tenant_is_recorded_into_files_of_its_own(
    start_server: StartServer, secret_file: Path
) -> None:
    server = await start_server(api_keys=(ADMIN_KEY,), jwt_secret_file=str(secret_file))
    key = bearer(ADMIN_KEY)
    acme_admin = bearer(token("admin", tenant="acme"))
    acme = bearer(token("operator", tenant="acme"))
    confined = bearer(token("viewer", tenant="acme", robots=["x-*"]))
    async with server.client() as http:
        assert (await http.post("/api/robots", json={"id": "lab-1"}, headers=key)).is_success
        made = await http.post("/api/robots", json={"id": "acme-1"}, headers=acme_admin)
        assert made.status_code == 201
        for robot_id, headers in (("lab-1", key), ("acme-1", acme)):  # something to record
            await http.post(f"/api/robots/{robot_id}/estop", headers=headers)

        async def listed(headers: dict[str, str]) -> list[str]:
            answer = (await http.get("/api/recordings", headers=headers)).json()
            assert answer["recorder"]["file"] in [None, *(e["name"] for e in answer["recordings"])]
            return [entry["name"] for entry in answer["recordings"]]

        async def both_listed() -> bool:
            return len(await listed(key)) == 1 and len(await listed(acme)) == 1

        await eventually(both_listed, what="each tenant's file being written, listed to it")
        [ours], [theirs] = await listed(key), await listed(acme)
        assert theirs.endswith(".acme.mcap") and ours != theirs
        assert await listed(confined) == []
        # Recording is switched for the whole server: not by a tenant's admin.
        refused = await http.post("/api/recordings/current/stop", headers=acme_admin)
        assert refused.status_code == 403
        stopped = await http.post("/api/recordings/current/stop", headers=key)
        assert stopped.json()["stopped"] == ours  # (the caller's file; acme's is not named)
        # Finished, each file says its tenant: still listed to it alone.
        assert (await listed(acme), await listed(key)) == ([theirs], [ours])
        summary = (await http.get(f"/api/recordings/{theirs}", headers=acme)).json()
        assert list(summary["robots"]) == ["acme-1"]
        joints = (await http.get(f"/api/recordings/{theirs}/joints", headers=acme)).json()
        assert joints["robots"] == ["acme-1"]
        downloads = {}
        for name, headers in ((theirs, acme), (ours, key)):
            reply = await http.get(f"/api/recordings/{name}/file", headers=headers)
            assert reply.status_code == 200
            downloads[name] = reply.content
        # Another tenant's file, or one beyond the caller's scope: as if it did not exist,
        # to every reader (listing, summary, plot, download, replay).
        for name, headers in ((theirs, key), (ours, acme), (theirs, confined)):
            for suffix in ("", "/joints", "/file"):
                hidden = await http.get(f"/api/recordings/{name}{suffix}", headers=headers)
                assert (hidden.status_code, hidden.json()["error"]["message"]) == (
                    404,
                    f"No recording called {name!r}.",
                )
        replay = await http.post(
            "/api/robots/acme-1/replay", json={"recording": ours}, headers=acme
        )
        assert (replay.status_code, replay.json()["error"]["code"]) == (404, "UNKNOWN_RECORDING")
    # Read back by the mcap library: each download holds its tenant's robot and nothing else.
    for name, robot_id, tenant in ((theirs, "acme-1", "acme"), (ours, "lab-1", "default")):
        reader = make_reader(io.BytesIO(downloads[name]))
        topics = {channel.topic for _, channel, _ in reader.iter_messages()}
        assert topics and all(t.startswith(f"/robots/{robot_id}/") for t in topics), topics
        metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
        assert {n for n in metadata if n.startswith("robot/")} == {f"robot/{robot_id}"}
        assert metadata["arena"]["tenant"] == tenant
        assert metadata[f"robot/{robot_id}"]["tenant"] == tenant


async def test_the_recorder_s_status_tells_each_tenant_its_own_counts_and_file_alone(
    start_server: StartServer, secret_file: Path
) -> None:
    server = await start_server(api_keys=(ADMIN_KEY,), jwt_secret_file=str(secret_file))
    key = bearer(ADMIN_KEY)
    acme = bearer(token("admin", tenant="acme"))
    async with server.client() as http:
        assert (await http.post("/api/robots", json={"id": "lab-1"}, headers=key)).is_success
        assert (await http.post("/api/robots", json={"id": "acme-1"}, headers=acme)).is_success
        for _ in range(3):  # the lab's robot says more than acme's: counts that differ
            await http.post("/api/robots/lab-1/estop", headers=key)
            await http.post("/api/robots/lab-1/reset", headers=key)
        await http.post("/api/robots/acme-1/estop", headers=acme)

        async def both_writing() -> bool:
            return len(server.app.recorder.current_files) == 2

        await eventually(both_writing, what="each tenant's file being written")
        stopped = await http.post("/api/recordings/current/stop", headers=key)
        assert stopped.status_code == 200
        ours = stopped.json()["stopped"]
        statuses = {}
        for who, headers in (("default", key), ("acme", acme)):
            listing = (await http.get("/api/recordings", headers=headers)).json()
            [name] = [entry["name"] for entry in listing["recordings"]]
            status = (await http.get("/", headers=headers)).json()["recording"]
            assert status == listing["recorder"]
            statuses[who] = (name, status)
            # Each count is of the caller's own files: read back, they hold that many.
            written = read_recording(server.app.recorder.folder / name).message_count
            assert (status["messages"], status["dropped"], status["error"]) == (written, 0, None)
    assert statuses["default"][0] == ours and statuses["acme"][0].endswith(".acme.mcap")
    assert statuses["default"][1]["messages"] != statuses["acme"][1]["messages"]


async def test_a_file_named_for_a_tenant_is_that_tenant_s_before_its_metadata_is_written(
    start_server: StartServer, secret_file: Path, tmp_path: Path
) -> None:
    """A new file's metadata is not flushed yet: its name says whose it is (the default
    tenant's when it names none), and no other tenant's admin sees it listed."""
    from mcap.writer import Writer

    folder = tmp_path / "recs"
    folder.mkdir()
    gamma_file = "arena-20260101-000000-000.gamma.mcap"
    default_file = "arena-20260101-000000-001.mcap"
    for name in (gamma_file, default_file):
        with (folder / name).open("wb") as stream:
            Writer(stream).start(profile="arena")  # a header, nothing flushed after it
    server = await start_server(
        api_keys=(ADMIN_KEY,), jwt_secret_file=str(secret_file), recordings_dir=str(folder)
    )
    async with server.client() as http:

        async def listed(headers: dict[str, str]) -> list[str]:
            answer = (await http.get("/api/recordings", headers=headers)).json()
            return [entry["name"] for entry in answer["recordings"]]

        assert await listed(bearer(ADMIN_KEY)) == [default_file]
        assert await listed(bearer(token("admin"))) == [default_file]
        assert await listed(bearer(token("admin", tenant="gamma"))) == [gamma_file]
        assert await listed(bearer(token("admin", tenant="acme"))) == []
        refused = await http.get(f"/api/recordings/{gamma_file}", headers=bearer(ADMIN_KEY))
    assert refused.status_code == 404


async def test_a_recorder_that_cannot_write_says_why_without_naming_a_file(
    start_server: StartServer, secret_file: Path, tmp_path: Path
) -> None:
    folder = tmp_path / "not-a-folder"
    folder.write_text("a file where the recordings should go")
    server = await start_server(jwt_secret_file=str(secret_file), recordings_dir=str(folder))
    acme = bearer(token("admin", tenant="acme"))
    async with server.client() as http:
        assert (await http.post("/api/robots", json={"id": "acme-1"}, headers=acme)).is_success

        async def failing() -> dict[str, Any] | None:
            await http.post("/api/robots/acme-1/estop", headers=acme)  # something to write
            status = (await http.get("/", headers=acme)).json()["recording"]
            return status if status["error"] is not None else None

        await eventually(failing, what="acme's recording failing")
        status = await failing()
        lab = (await http.get("/", headers=bearer(token("admin")))).json()
        ready = await http.get("/readyz")
    assert status is not None and status["errors"] >= 1 and status["dropped"] >= 1
    for said in (status["error"], *ready.json()["reasons"]):
        assert "not-a-folder" not in said and str(tmp_path) not in said and ".mcap" not in said
    assert status["error"].startswith("File exists"), status["error"]
    # The default tenant had nothing to write: nothing failed of its own.
    assert (lab["recording"]["error"], lab["recording"]["dropped"]) == (None, 0)


async def test_a_tenant_reads_its_file_being_written_in_a_folder_given_relative(
    start_server: StartServer,
    secret_file: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.chdir(tmp_path)
    server = await start_server(jwt_secret_file=str(secret_file), recordings_dir="recs")
    acme = bearer(token("admin", tenant="acme"))
    async with server.client() as http:
        assert (await http.post("/api/robots", json={"id": "acme-1"}, headers=acme)).is_success
        await http.post("/api/robots/acme-1/estop", headers=acme)

        async def listed() -> list[dict[str, Any]]:
            answer = (await http.get("/api/recordings", headers=acme)).json()
            # (listed from its creation, by its name; active once the recorder says so)
            return [entry for entry in answer["recordings"] if entry["active"]]

        await eventually(listed, what="acme's file being written, listed")
        [entry] = await listed()
        assert entry["active"]
        summary = await http.get(f"/api/recordings/{entry['name']}", headers=acme)
        assert summary.status_code == 200 and list(summary.json()["robots"]) == ["acme-1"]


async def test_a_robot_id_made_anew_in_another_tenant_goes_to_that_tenant_s_files(
    autojump_clock: trio.testing.MockClock, tmp_path: Path
) -> None:
    recorder = Recorder(tmp_path, flush_interval=1.0, batch_interval=1.0, foxglove=False)
    async with trio.open_nursery() as nursery:
        await nursery.start(recorder.run)
        async with open_manager() as manager:
            manager.on_create.append(recorder.follow)
            first = await manager.create_robot("so-arm100", robot_id="x", tenant="acme")
            await first.estop("acme's stop")
            # A batch written: the writer knows the robot. The writer is a real process and
            # trio's clock jumps while it works: bounded in real time, to fail, never hang.
            deadline = time.monotonic() + 60
            while not recorder.writer.messages:
                assert time.monotonic() < deadline, "the writer wrote nothing in a minute"
                await trio.to_thread.run_sync(time.sleep, 0.01)  # (no busy loop meanwhile)
            await first.reset()
            await first.estop("acme's last word")
            # Deleted and made anew at once: the old robot's last events may travel in one
            # batch with the new one's, each to its own tenant.
            await manager.delete("x")
            second = await manager.create_robot("so-arm100", robot_id="x")
            await second.estop("the lab's stop")
            await trio.sleep(1.5)
        nursery.cancel_scope.cancel()
    recordings = [read_recording(path) for path in recorder.writer.files]
    files = {recording.metadata["arena"]["tenant"]: recording for recording in recordings}
    assert sorted(files) == ["acme", "default"] and len(recordings) == 2
    said = {"acme": {"acme's stop", "acme's last word"}, "default": {"the lab's stop"}}
    for tenant, recording in files.items():
        assert recording.metadata["robot/x"]["tenant"] == tenant
        reasons = {m.data["estop_reason"] for m in recording.messages if m.kind == "state"}
        assert reasons - {None} == said[tenant], tenant
    assert files["acme"].path.name.endswith(".acme.mcap")


def test_a_writer_process_started_anew_knows_every_robot_s_tenant_from_its_first_batch(
    tmp_path: Path,
) -> None:
    writer = McapWriterProcess(FileSeries(tmp_path, {}, foxglove=False))
    writer.robots["arm"] = {"robot_type": "so-arm100", "name": "arm", "tenant": "acme"}
    state = json.dumps({"mode": "idle", "owner": None, "estop_reason": None, "cause": "x"})
    items = [("arm", "state", state.encode(), n) for n in range(1, 4)]
    try:
        writer.write(items[:1])
        child = writer._process
        assert child is not None
        os.kill(child.pid, signal.SIGKILL)  # the next batch starts a new child
        child.wait()
        writer.write(items[1:])
    finally:
        writer.shutdown()
    first, second = (read_recording(path) for path in writer.files)
    assert second.path.name.endswith(".acme.mcap"), writer.files  # not the default tenant's
    assert second.metadata["robot/arm"]["tenant"] == "acme"
    assert [m.log_time for m in first.messages + second.messages] == [1, 2, 3]


def test_one_tenant_s_disk_error_leaves_the_other_tenants_events_written(tmp_path: Path) -> None:
    files = TenantFiles(FileSeries(tmp_path / "recordings", {}, foxglove=False))
    tenants = {"acme-1": "acme", "lab-1": "default", "zeta-1": "zeta"}  # acme's lane first
    for robot_id, tenant in tenants.items():
        metadata = {"robot_type": "so-arm100", "name": robot_id, "tenant": tenant}
        files.know(robot_id, metadata, None)
    blocked = tmp_path / "acme-disk"
    blocked.write_text("a file where acme's folder should be")
    files.lane("acme").writer.folder = blocked  # acme's disk refuses (a real OS error)
    slices = {
        tenant: [
            pack_events(
                robot_id, 0.0, [StateChanged(robot_id, Mode.IDLE, None, None, "x", 1.0, 1.0)]
            )
        ]
        for robot_id, tenant in tenants.items()
    }
    files.write_events(slices)
    files.flush()
    errors, _, messages, written, _ = files.reply()
    assert list(errors) == ["acme"] and "acme-disk" not in errors["acme"], errors
    assert errors["acme"].startswith("File exists")
    assert messages == {"acme": 0, "default": 1, "zeta": 1}
    files.close()
    read = {read_recording(path).metadata["arena"]["tenant"]: path for path in written}
    assert sorted(read) == ["default", "zeta"]
    for tenant, path in read.items():
        [message] = read_recording(path).messages
        assert message.robot_id == f"{'lab' if tenant == 'default' else tenant}-1"
    assert files.reply()[0] == {}, "an error is told once"


# -- across a fleet --------------------------------------------------------------------------------


async def _secured_fleet(
    start_server: StartServer, secret_file: Path
) -> tuple[RunningServer, RunningServer]:
    """Nodes a and b; b owns b-acme (tenant acme) and b-lab (default)."""
    need("zenoh", "fleet")
    secured = {"jwt_secret_file": str(secret_file), "fleet_listen": ("tcp/127.0.0.1:0",)}
    a = await start_server(node="a", **secured)
    b = await start_server(node="b", fleet_connect=tuple(await a.app.fleet.locators()), **secured)
    async with b.client() as http:
        for robot_id, tenant in (("b-acme", "acme"), ("b-lab", "default")):
            made = await http.post(
                "/api/robots", json={"id": robot_id}, headers=bearer(token("admin", tenant=tenant))
            )
            assert made.status_code == 201

    async def a_knows_both() -> bool:
        async with a.client() as http:
            answer = await http.get("/api/fleet/robots", headers=bearer(token("admin")))
        known = {robot["id"] for robot in answer.json()["robots"]}
        return "b-lab" in known and a.app.access.tenant_of("b-acme") == "acme"

    await eventually(a_knows_both, what="node a knowing b's robots and their tenants")
    return a, b


async def test_tenants_hold_across_a_fleet(start_server: StartServer, secret_file: Path) -> None:
    need("zenoh", "fleet")
    secured = {"jwt_secret_file": str(secret_file), "fleet_listen": ("tcp/127.0.0.1:0",)}
    a = await start_server(node="a", **secured)
    b = await start_server(node="b", fleet_connect=tuple(await a.app.fleet.locators()), **secured)
    lab, acme = bearer(token("admin")), bearer(token("admin", tenant="acme"))
    async with a.client() as http:
        assert (await http.post("/api/robots", json={"id": "a-0"}, headers=lab)).status_code == 201
    async with b.client() as http:
        made = await http.post("/api/robots", json={"id": "b-acme"}, headers=acme)
        assert made.status_code == 201

    async def listed(headers: dict[str, str]) -> list[str]:
        async with a.client() as http:
            answer = (await http.get("/api/fleet/robots", headers=headers)).json()
        return sorted(robot["id"] for robot in answer["robots"])

    async def both_known() -> bool:
        return await listed(lab) == ["a-0"] and await listed(acme) == ["b-acme"]

    await eventually(both_known, what="each tenant listing its own robot only")
    async with a.client() as http:
        # Another node's robot of another tenant: as absent here as a local one.
        hidden = await http.get("/api/robots/b-acme/status", headers=lab)
        assert (hidden.status_code, hidden.json()["error"]["code"]) == (404, "UNKNOWN_ROBOT")
        seen = await http.get("/api/robots/b-acme/status", headers=acme)
        assert seen.status_code == 200
        watcher = token("viewer", tenant="acme")
        answer = await http.post("/api/fleet/estop", headers=bearer(watcher))
    # A WebSocket carried to the robot's node: checked here, served there.
    async with open_websocket_url(f"{a.ws_url}/ws/robots/b-acme/state?token={watcher}") as ws:
        assert (await receive(ws, "state"))["data"]["mode"] == "estopped"
    async with open_websocket_url(f"{a.ws_url}/ws/robots/b-acme/state?token={token()}") as ws:
        assert (await receive(ws, "error"))["data"]["code"] == "UNKNOWN_ROBOT"
        assert await closed_with(ws) == 4404
    assert {ack["node"]: ack["robots"] for ack in answer.json()["acks"]} == {
        "a": [],
        "b": ["b-acme"],
    }
    assert str(a.app.manager.get("a-0").snapshot().mode) == "idle"
    assert str(b.app.manager.get("b-acme").snapshot().mode) == "estopped"


async def test_a_node_serves_a_call_from_another_node_as_the_caller_it_was_sent(
    start_server: StartServer, secret_file: Path
) -> None:
    a, b = await _secured_fleet(start_server, secret_file)
    fleet = a.app.fleet
    lab_admin = Principal("mallory", Role.ADMIN).to_wire()
    acme_viewer = Principal("vic", Role.VIEWER, "acme").to_wire()

    async def at_b(method: str, path: str, caller: dict[str, Any], body: Any = None) -> Any:
        data = b"" if body is None else json.dumps(body).encode()
        call = forward.Call(method, path, "", {"content-type": "application/json"}, data, caller)
        answer = await forward.forward(fleet, "b", call)
        return answer.status, json.loads(answer.body)

    # Node b decides with what it knows of its robots, whatever node a decided.
    status, body = await at_b("GET", "/api/robots/b-acme/status", lab_admin)
    assert (status, body["error"]["code"]) == (404, "UNKNOWN_ROBOT")
    assert (await at_b("GET", "/api/robots/b-acme/status", acme_viewer))[0] == 200
    moved = {"joints": [{"name": "Rotation", "value": 5}]}
    status, body = await at_b("PUT", "/api/robots/b-acme/joints", acme_viewer, moved)
    assert (status, body["error"]["code"]) == (403, "FORBIDDEN")
    # A WebSocket carried to b, as a caller of the other tenant: refused there as absent.
    for caller, first in ((lab_admin, "error"), (acme_viewer, "state")):
        tunnel = await tunnels.open_to(fleet, "b", "b-acme", "viewer", {}, caller)
        with trio.fail_after(10):
            message = json.loads((await tunnel.inbox.receive())[1:])
        tunnel.close()
        assert message["type"] == first, (caller, message)
        if first == "error":
            assert message["data"]["code"] == "UNKNOWN_ROBOT"
    # Through node a's REST: the robot's node records the caller by name.
    carol = bearer(token("operator", sub="carol", tenant="acme"))
    with b.app.manager.get("b-acme").subscribe(kinds=[Audited]) as audits:
        async with a.client() as http:
            reset = await http.post("/api/robots/b-acme/reset", headers=carol)
            assert (reset.status_code, reset.headers["X-Arena-Node"]) == (200, "b")
            nodes = (await http.get("/api/fleet/nodes", headers=bearer(token("viewer")))).json()
        trail = [(event.user, event.action) for event in audits.drain()]
    assert trail == [("carol", "POST /api/robots/{robot_id}/reset")]
    assert {node["name"]: node["robots"] for node in nodes["nodes"]} == {"a": [], "b": ["b-lab"]}
    # An id deleted on a (of acme) and made anew on b (of default) is b's robot's, of default.
    acme_admin, lab = bearer(token("admin", tenant="acme")), bearer(token("admin"))
    async with a.client() as http:
        assert (await http.post("/api/robots", json={"id": "dup"}, headers=acme_admin)).is_success
        assert (await http.delete("/api/robots/dup", headers=acme_admin)).is_success
    async with b.client() as http:
        assert (await http.post("/api/robots", json={"id": "dup"}, headers=lab)).is_success

    async def a_knows_dup_on_b() -> bool:
        async with a.client() as http:
            answer = await http.get("/api/fleet/robots", headers=lab)
        return any(robot["id"] == "dup" for robot in answer.json()["robots"])

    await eventually(a_knows_dup_on_b, what="node a seeing b's new robot")
    async with a.client() as http:
        seen = await http.get("/api/robots/dup/status", headers=lab)
        assert (seen.status_code, seen.headers.get("X-Arena-Node")) == (200, "b")
        hidden = await http.get("/api/robots/dup/status", headers=acme_admin)
        assert hidden.status_code == 404


async def test_a_node_with_credentials_refuses_a_call_that_names_no_caller(
    start_server: StartServer, secret_file: Path
) -> None:
    a, b = await _secured_fleet(start_server, secret_file)
    fleet = a.app.fleet
    # As a node of an older version sends them: no caller. Run as anyone, it would be the
    # unlimited admin: it is refused, and the robot stays.
    call = forward.Call("DELETE", "/api/robots/b-lab", "", {}, b"", None)
    answer = await forward.forward(fleet, "b", call)
    error = json.loads(answer.body)["error"]
    assert (answer.status, error["code"]) == (401, "UNAUTHORIZED")
    assert "no caller" in error["message"]
    with pytest.raises(ArenaError) as refused:
        await tunnels.open_to(fleet, "b", "b-lab", "master", {}, None)
    assert refused.value.code is ErrorCode.UNAUTHORIZED
    assert b.app.manager.find("b-lab") is not None
    assert b.app.manager.get("b-lab").snapshot().master is None


async def test_an_open_fleet_serves_a_call_without_a_caller_as_every_call_there(
    start_server: StartServer,
) -> None:
    need("zenoh", "fleet")
    a = await start_server(node="a", fleet_listen=("tcp/127.0.0.1:0",))
    b = await start_server(node="b", fleet_connect=tuple(await a.app.fleet.locators()))
    async with b.client() as http:
        assert (await http.post("/api/robots", json={"id": "b-0"})).status_code == 201
    call = forward.Call("DELETE", "/api/robots/b-0", "", {}, b"", None)
    answer = await forward.forward(a.app.fleet, "b", call)
    assert answer.status == 200, answer.body
    assert b.app.manager.find("b-0") is None


async def test_a_reused_robot_id_has_the_tenant_its_live_owner_says(
    start_server: StartServer, secret_file: Path
) -> None:
    a, _b = await _secured_fleet(start_server, secret_file)
    fleet = a.app.fleet
    # A node that left had a robot of acme called b-lab (listed first, as a node seen
    # earlier would be); b, alive, owns b-lab now, of the default tenant.
    ghost = NodeView("ghost", False, robots=[{"id": "b-lab", "tenant": "acme"}])
    fleet.nodes = {"ghost": ghost, **fleet.nodes}
    assert fleet.robot_nodes["b-lab"] == "b"
    assert a.app.access.tenant_of("b-lab") == "default"
    async with a.client() as http:
        seen = await http.get("/api/robots/b-lab/status", headers=bearer(token("admin")))
        assert (seen.status_code, seen.headers.get("X-Arena-Node")) == (200, "b")
        acme = bearer(token("admin", tenant="acme"))
        hidden = await http.get("/api/robots/b-lab/status", headers=acme)
        assert hidden.status_code == 404
    # No live node has it: the dead node's word is all there is.
    ghost.robots.append({"id": "gone-1", "tenant": "acme"})
    assert a.app.access.tenant_of("gone-1") == "acme"


async def test_a_robot_out_of_scope_on_a_node_that_left_is_as_absent_as_any(
    start_server: StartServer, secret_file: Path
) -> None:
    a, b = await _secured_fleet(start_server, secret_file)
    b.stop.set()
    await b.done.wait()

    async def b_is_gone() -> bool:
        view = a.app.fleet.nodes.get("b")
        return view is not None and not view.alive

    await eventually(b_is_gone, what="node b seen gone")
    lab, acme = token("admin"), token("admin", tenant="acme")
    confined = token("admin", tenant="acme", robots=["x-*"])
    async with a.client() as http:
        for path in ("/api/robots/b-acme/status", "/api/robots/b-acme/no-such-route"):
            for caller in (lab, confined):
                hidden = await http.get(path, headers=bearer(caller))
                assert (hidden.status_code, hidden.json()["error"]["code"]) == (
                    404,
                    "UNKNOWN_ROBOT",
                ), path
            told = await http.get(path, headers=bearer(acme))
            assert (told.status_code, told.json()["error"]["code"]) == (503, "NODE_LOST")
    for caller, expected in ((lab, ("UNKNOWN_ROBOT", 4404)), (acme, ("NODE_LOST", 4503))):
        async with open_websocket_url(f"{a.ws_url}/ws/master/b-acme?token={caller}") as ws:
            error = await receive(ws, "error")
            assert (error["data"]["code"], await closed_with(ws)) == expected


# -- calibration -----------------------------------------------------------------------------------


@pytest.fixture
def sim(tmp_path: Path) -> Iterator[PtySimBus]:
    yield from running_sim(tmp_path)


async def test_each_tenant_has_its_own_calibration_folder_and_no_other_file(
    start_server: StartServer, secret_file: Path, sim: PtySimBus, tmp_path: Path
) -> None:
    root = tmp_path / "calibration"
    server = await start_server(jwt_secret_file=str(secret_file), calibration_dir=str(root))
    lab_file = root / "lab-arm.json"  # the default tenant's, where it always was
    model = load_robot_model("so-arm100")
    Calibration.identity({j.name: j.servo_id for j in model.joints}).save(lab_file)
    before = lab_file.read_bytes()
    acme = bearer(token("admin", tenant="acme"))
    async with server.client() as http:
        assert (await http.post("/api/robots", json={"id": "acme-1"}, headers=acme)).is_success
        slaves = "/api/robots/acme-1/slaves"
        # A file outside acme's folder: refused by path, by LeRobot id, by a link out of its
        # folder (made by someone with a shell: the server never follows it), and nothing
        # is attached.
        (root / "acme").mkdir()
        (root / "acme" / "linked.json").symlink_to(lab_file)
        for value in (str(lab_file), "lerobot:arm", "lab-arm.json", "linked"):
            body = {"type": "usb-slave", "port": str(sim.link), "calibration": value}
            refused = await http.post(slaves, json=body, headers=acme)
            assert (refused.status_code, refused.json()["error"]["code"]) == (403, "FORBIDDEN")
        assert server.app.manager.get("acme-1").snapshot().slaves == ()
        # The default tenant's name, asked by acme: acme's own file of that name (none yet).
        body = {"type": "usb-slave", "port": str(sim.link), "calibration": "lab-arm"}
        attached = await http.post(slaves, json=body, headers=acme)
        assert attached.status_code == 201, attached.text
        status = (await http.get("/api/robots/acme-1/calibration", headers=acme)).json()
    assert status["file"] == str(root / "acme" / "lab-arm.json")
    assert status["calibrated"] is False
    assert lab_file.read_bytes() == before


# -- policies ----------------------------------------------------------------------------------


async def test_a_policy_is_a_folder_of_the_tenant_s_own_and_a_path_is_the_admin_s_alone(
    start_server: StartServer, secret_file: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    need("lerobot", "lerobot")  # (else every attach is 501 NOT_INSTALLED)
    monkeypatch.chdir(tmp_path)  # the default policy folder, `policies/`, is the server's
    root = tmp_path / "policies"
    lab = root / "lab-policy"  # the default tenant's (a policy's config.json is enough here)
    lab.mkdir(parents=True)
    (lab / "config.json").write_text("{}")
    acme_folder = root / "acme"
    acme_folder.mkdir()
    (acme_folder / "sneaky").symlink_to(lab)  # a link out of acme's folder, to lab's policy
    leaky = acme_folder / "leaky"  # acme's own folder, with one file linked from lab's
    leaky.mkdir()
    (leaky / "config.json").symlink_to(lab / "config.json")
    server = await start_server(jwt_secret_file=str(secret_file))
    acme_admin = bearer(token("admin", tenant="acme"))
    acme = bearer(token("operator", tenant="acme"))
    scoped_lab = bearer(token("operator", robots=["lab-*"]))  # the default tenant, not its admin
    async with httpx.AsyncClient(base_url=server.url, timeout=120) as http:  # (a worker's start)
        for robot_id, headers in (("acme-1", acme_admin), ("lab-1", bearer(token("admin")))):
            made = await http.post("/api/robots", json={"id": robot_id}, headers=headers)
            assert made.status_code == 201, made.text

        async def answer(value: str, headers: dict[str, str] = acme) -> tuple[int, str, str]:
            robot = "lab-1" if headers is scoped_lab else "acme-1"
            body = {"type": "policy", "path": value}
            got = await http.post(f"/api/robots/{robot}/master", json=body, headers=headers)
            error = got.json()["error"]
            return got.status_code, error["code"], error["message"].replace(value, "X")

        # A path, to another tenant's policy or to nothing at all: the same refusal, which
        # tells nothing of what is there.
        refusals = {
            await answer(value)
            for value in (
                str(lab),
                str(tmp_path / "no-such-folder"),
                "policies/lab-policy",
                "../lab-policy",
                "~",
                "acme/../lab-policy",
            )
        }
        assert len(refusals) == 1, refusals
        [(status, code, message)] = refusals
        assert (status, code) == (403, "FORBIDDEN") and "only an admin" in message
        # A name is a folder of acme's own: lab's name is not lab's policy.
        assert await answer("lab-policy") == await answer("no-such-policy")
        status, code, message = await answer("lab-policy")
        assert (status, code) == (422, "POLICY_INVALID")
        assert "policies/acme" in message and str(lab) not in message
        # Symbolic links out of acme's folder are never followed, the folder's or a file's.
        for value in ("sneaky", "leaky"):
            status, code, message = await answer(value)
            assert (status, code) == (403, "FORBIDDEN") and "symbolic link" in message
        # The default tenant's folder holds the others': a name there reaches none of them.
        assert await answer("acme", scoped_lab) == await answer("nothing", scoped_lab)
    assert server.app.manager.get("acme-1").snapshot().master is None
    assert server.app.manager.get("lab-1").snapshot().master is None


async def test_a_tenant_lists_its_own_policies_only_and_the_listing_is_bounded(
    start_server: StartServer, secret_file: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    root = tmp_path / "policies"
    for folder, kind in ((root / "lab-policy", "act"), (root / "acme" / "reach", "diffusion")):
        folder.mkdir(parents=True)
        (folder / "config.json").write_text(json.dumps({"type": kind}))
    (root / "acme" / "notes").mkdir()  # a folder that is not a policy
    (root / "acme" / "sneaky").symlink_to(root / "lab-policy")  # a link out of acme's folder
    leaky = root / "acme" / "leaky"  # acme's own folder, its config.json linked from lab's
    leaky.mkdir()
    (leaky / "config.json").symlink_to(root / "lab-policy" / "config.json")
    (root / "acme" / "broken").mkdir()
    (root / "acme" / "broken" / "config.json").write_text("{not json")
    server = await start_server(jwt_secret_file=str(secret_file), policy_dir=str(root))
    acme = bearer(token("admin", tenant="acme"))
    lab = bearer(token("admin"))
    async with server.client() as http:
        for robot_id, headers in (("acme-1", acme), ("lab-1", lab)):
            made = await http.post("/api/robots", json={"id": robot_id}, headers=headers)
            assert made.status_code == 201, made.text
        listed = await http.get("/api/robots/acme-1/policies", headers=acme)
        assert listed.status_code == 200, listed.text
        assert listed.json() == {
            "policies": [{"name": "broken", "type": None}, {"name": "reach", "type": "diffusion"}],
            "truncated": False,
        }
        # The default tenant's folder holds acme's: acme's folder is no policy of its.
        listed = await http.get("/api/robots/lab-1/policies", headers=lab)
        assert listed.json()["policies"] == [{"name": "lab-policy", "type": "act"}]
        # Another tenant's robot is as absent as any.
        hidden = await http.get("/api/robots/lab-1/policies", headers=acme)
        assert hidden.status_code == 404
        # However many there are, a bounded answer that says it was cut.
        monkeypatch.setattr("arena.server.policies_api.MAX_LISTED", 1)
        listed = await http.get("/api/robots/acme-1/policies", headers=acme)
        assert listed.json() == {"policies": [{"name": "broken", "type": None}], "truncated": True}
