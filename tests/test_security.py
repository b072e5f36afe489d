"""Who may do what: viewer keys, keys kept out of logs and recordings, roles, names, CORS."""

from __future__ import annotations

import json
import logging
from collections.abc import Awaitable, Callable
from pathlib import Path

import pytest
from trio_websocket import open_websocket_url

from tests.conftest import RunningServer
from tests.test_server_ws import closed_with, command, receive

StartServer = Callable[..., Awaitable[RunningServer]]
ADMIN, VIEWER = "adm1n-k3y-zz", "v1ewer-k3y-zz"


async def test_a_viewer_key_watches_but_cannot_command(start_server: StartServer) -> None:
    server = await start_server(demo=True, api_keys=(ADMIN,), viewer_keys=(VIEWER,))
    viewer = {"Authorization": f"Bearer {VIEWER}"}
    async with server.client() as http:
        assert (await http.get("/api/robots/demo-arm", headers=viewer)).status_code == 200
        for method, path in [
            ("POST", "/api/robots/demo-arm/estop"),
            ("PUT", "/api/robots/demo-arm/joints"),
            ("POST", "/api/robots"),
            ("DELETE", "/api/robots/demo-arm"),
            ("POST", "/api/recordings"),
        ]:
            reply = await http.request(method, path, headers=viewer, json={})
            assert (reply.status_code, reply.json()["error"]["code"]) == (403, "FORBIDDEN"), path
        assert (await http.get("/api/robots/demo-arm")).json()["error"]["code"] == "UNAUTHORIZED"
        assert (await http.get("/api/robots/demo-arm", headers=viewer)).json()["state"] == "idle"
    for role in ("master", "slave"):
        async with open_websocket_url(f"{server.ws_url}/ws/{role}/demo-arm?token={VIEWER}") as ws:
            assert (await receive(ws, "error"))["data"]["code"] == "FORBIDDEN"
            assert await closed_with(ws) == 4403
    async with open_websocket_url(
        f"{server.ws_url}/ws/robots/demo-arm/state?token={VIEWER}"
    ) as watcher:
        assert (await receive(watcher, "joint_states"))["data"]


async def test_keys_never_reach_logs_or_recordings(
    start_server: StartServer, caplog: pytest.LogCaptureFixture, tmp_path: Path
) -> None:
    caplog.set_level(logging.DEBUG)
    recordings = tmp_path / "rec"
    server = await start_server(
        demo=True, api_keys=(ADMIN,), viewer_keys=(VIEWER,), recordings_dir=str(recordings)
    )
    admin = {"Authorization": f"Bearer {ADMIN}"}
    async with server.client() as http:
        await http.get("/api/robots", headers={"Authorization": f"Bearer {VIEWER}"})
        await http.post("/api/robots/demo-arm/estop", headers={"Authorization": "Bearer wrong"})
        await http.post("/api/robots/demo-arm/estop", headers=admin)
        await http.post("/api/robots/demo-arm/reset", headers=admin)
    async with open_websocket_url(f"{server.ws_url}/ws/master/demo-arm?token={ADMIN}") as master:
        await command(master, {"Rotation": 3})
    server.stop.set()
    await server.done.wait()
    files = list(recordings.glob("*.mcap"))
    assert files
    for path in files:
        raw = path.read_bytes()
        assert ADMIN.encode() not in raw and VIEWER.encode() not in raw
    server_logs = "\n".join(  # the test's own clients log their URLs; the server must not
        record.getMessage()
        for record in caplog.records
        if record.name.split(".")[0] in ("arena", "hypercorn", "quart", "quart_trio")
    )
    assert server_logs and ADMIN not in server_logs and VIEWER not in server_logs


async def test_a_slave_cannot_command_and_a_master_reaches_only_its_robot(
    server: RunningServer,
) -> None:
    async with server.client() as http:
        await http.post("/api/robots", json={"id": "other"})
        before_other = (await http.get("/api/robots/other/joints")).json()
        before_arm = (await http.get("/api/robots/demo-arm/joints")).json()
        async with open_websocket_url(server.ws_url + "/ws/slave/demo-arm") as slave:
            await slave.send_message(
                json.dumps(
                    {"type": "command", "data": {"joints": [{"name": "Rotation", "value": 40}]}}
                )
            )
            assert (await receive(slave, "error"))["data"]["code"] == "UNKNOWN_MESSAGE_TYPE"
        assert (await http.get("/api/robots/demo-arm/joints")).json() == before_arm
        await http.post("/api/robots/demo-arm/reset")  # that slave leaving e-stopped the arm
        async with open_websocket_url(server.ws_url + "/ws/master/demo-arm") as master:
            # Naming another robot in the message changes nothing: the socket is bound to one.
            ack = await command(master, {"Rotation": 7}, robot_id="other", robotId="other")
            assert ack["data"]["status"] == "accepted"
        assert (await http.get("/api/robots/other/joints")).json() == before_other


async def test_recording_names_cannot_escape_the_folder(server: RunningServer) -> None:
    async with server.client() as http:
        for name in ("..%2F..%2Fetc%2Fpasswd", "..", ".hidden.mcap", "a%00b"):
            reply = await http.get(f"/api/recordings/{name}/file")
            assert reply.status_code in (404, 422), name
            assert reply.json()["error"]["code"] in (
                "UNKNOWN_RECORDING",
                "INVALID_BODY",
                "NOT_FOUND",
            )
        replay = await http.post(
            "/api/robots/demo-arm/replay", json={"recording": "../../etc/passwd"}
        )
        assert replay.status_code in (404, 422) and "error" in replay.json()


async def test_cors_is_closed_by_default(server: RunningServer) -> None:
    async with server.client() as http:
        origin = {"Origin": "https://evil.example"}
        reply = await http.get("/api/robots", headers=origin)
        assert "access-control-allow-origin" not in reply.headers
        preflight = await http.options(
            "/api/robots/demo-arm/estop",
            headers={**origin, "Access-Control-Request-Method": "POST"},
        )
        assert "access-control-allow-origin" not in preflight.headers
