"""Who may do what: viewer keys, keys kept out of logs and recordings, roles, names, CORS."""

from __future__ import annotations

import json
import logging
import shutil
from collections.abc import Awaitable, Callable
from pathlib import Path
from urllib.parse import quote

import pytest
import trio
from trio_websocket import open_websocket_url

from arena.server.config import load_config
from tests.conftest import RunningServer
from tests.test_server_ws import closed_with, command, receive

StartServer = Callable[..., Awaitable[RunningServer]]
ADMIN, VIEWER = "adm1n-k3y-zz", "v1ewer-k3y-zz"
GOLDEN = Path(__file__).resolve().parent.parent / "recordings" / "golden" / "gentle-wave.mcap"


async def test_a_viewer_key_watches_but_cannot_command(start_server: StartServer) -> None:
    server = await start_server(demo=True, api_keys=(ADMIN,), viewer_keys=(VIEWER,))
    viewer = {"Authorization": f"Bearer {VIEWER}"}
    async with server.client() as http:
        assert (await http.get("/api/robots/demo-arm", headers=viewer)).status_code == 200
        for method, path in [
            ("POST", "/api/robots/demo-arm/reset"),
            ("PUT", "/api/robots/demo-arm/joints"),
            ("PUT", "/api/robots/demo-arm/workspace"),
            ("POST", "/api/robots"),
            ("DELETE", "/api/robots/demo-arm"),
            ("POST", "/api/recordings"),
        ]:
            reply = await http.request(method, path, headers=viewer, json={})
            assert (reply.status_code, reply.json()["error"]["code"]) == (403, "FORBIDDEN"), path
        assert (await http.get("/api/robots/demo-arm")).json()["error"]["code"] == "UNAUTHORIZED"
        assert (await http.get("/api/robots/demo-arm", headers=viewer)).json()["state"] == "idle"
        # Stopping needs no more than seeing (issue 49): a viewer may e-stop, not reset.
        stopped = await http.post("/api/robots/demo-arm/estop", headers=viewer)
        assert (stopped.status_code, stopped.json()["state"]) == (200, "estopped")
        admin = {"Authorization": f"Bearer {ADMIN}"}
        assert (await http.post("/api/robots/demo-arm/reset", headers=admin)).status_code == 200
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
            # Naming another robot in the message is refused (no field is ignored), and the
            # socket stays bound to its one robot.
            await master.send_message(
                json.dumps(
                    {
                        "type": "command",
                        "data": {"joints": [{"name": "Rotation", "value": 7}], "robotId": "other"},
                    }
                )
            )
            assert (await receive(master, "error"))["data"]["code"] == "UNKNOWN_FIELD"
            ack = await command(master, {"Rotation": 7})
            assert ack["data"]["status"] == "accepted"
        assert (await http.get("/api/robots/other/joints")).json() == before_other


async def test_recording_names_cannot_escape_the_folder(
    start_server: StartServer, tmp_path: Path
) -> None:
    # A real recording sits just outside the folder and one inside: the inside one is served
    # (so a refusal below means something), and no name reaches the outside one.
    folder = tmp_path / "recordings"
    folder.mkdir()
    shutil.copy(GOLDEN, folder / "inside.mcap")
    shutil.copy(GOLDEN, tmp_path / "secret.mcap")
    server = await start_server(demo=True, recordings_dir=str(folder), record=False)
    async with server.client() as http:
        assert (await http.get("/api/recordings/inside.mcap/file")).status_code == 200
        for name in (
            "..%2Fsecret.mcap",
            "%2E%2E%2Fsecret.mcap",
            "..%5Csecret.mcap",
            quote(str(tmp_path / "secret.mcap"), safe=""),
            "recordings%2F..%2F..%2Fsecret.mcap",
            "..",
            ".hidden.mcap",
            "a%00b",
        ):
            reply = await http.get(f"/api/recordings/{name}/file")
            assert reply.status_code in (404, 422), name
            assert not reply.content.startswith(b"\x89MCAP"), name
            assert reply.json()["error"]["code"] in (
                "UNKNOWN_RECORDING",
                "INVALID_BODY",
                "NOT_FOUND",
            )
            summary = await http.get(f"/api/recordings/{name}")
            assert summary.status_code in (404, 422), name
        for recording in ("../secret.mcap", str(tmp_path / "secret.mcap")):
            replay = await http.post("/api/robots/demo-arm/replay", json={"recording": recording})
            assert replay.status_code in (404, 422), recording
        assert server.app.manager.get("demo-arm").snapshot().master is None


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


async def _upgrade(server: RunningServer, path: str, headers: dict[str, str]) -> tuple[int, bytes]:
    """A WebSocket handshake with the headers given; the HTTP status and body answered."""
    host, port = server.url.split("//")[1].rsplit(":", 1)
    lines = {
        "Host": f"{host}:{port}",
        "Upgrade": "websocket",
        "Connection": "Upgrade",
        "Sec-WebSocket-Key": "dGhlIHNhbXBsZSBub25jZQ==",
        "Sec-WebSocket-Version": "13",
        **headers,
    }
    request = f"GET {path} HTTP/1.1\r\n" + "".join(f"{k}: {v}\r\n" for k, v in lines.items())
    stream = await trio.open_tcp_stream(host, int(port))
    await stream.send_all((request + "\r\n").encode())
    answer = b""
    with trio.fail_after(10):
        while b"\r\n\r\n" not in answer:
            answer += await stream.receive_some(65536)
        head, _, body = answer.partition(b"\r\n\r\n")
        if head.startswith(b"HTTP/1.1 403"):
            length = int(head.lower().split(b"content-length:")[1].split(b"\r\n")[0])
            while len(body) < length:
                body += await stream.receive_some(65536)
    await stream.aclose()
    return int(head.split()[1]), body


EVIL = "https://evil.example"


@pytest.mark.parametrize("keys", [(), (ADMIN,)])
async def test_a_foreign_page_changes_nothing_over_rest(
    start_server: StartServer, keys: tuple[str, ...]
) -> None:
    # A page elsewhere can POST text/plain without a preflight; with or without API keys
    # (its fetch could even carry a key it learned), its Origin gives it away.
    server = await start_server(demo=True, api_keys=keys)
    auth = {"Authorization": f"Bearer {ADMIN}"} if keys else {}
    robot = server.app.manager.get("demo-arm")
    async with server.client() as http:
        for path, body in [
            ("/api/robots/demo-arm/estop", b""),
            ("/api/robots", b'{"robot_type": "so-arm100", "id": "planted"}'),
        ]:
            reply = await http.post(
                path, content=body, headers={**auth, "Origin": EVIL, "Content-Type": "text/plain"}
            )
            assert reply.status_code == 403, reply.text
            assert reply.json()["error"]["code"] == "ORIGIN_NOT_ALLOWED"
        assert str(robot.snapshot().mode) != "estopped"
        assert [r["id"] for r in (await http.get("/api/robots", headers=auth)).json()] == [
            "demo-arm"
        ]
        # Reading is not changing: a foreign page may GET (CORS keeps the answer from it).
        assert (await http.get("/api/robots", headers={**auth, "Origin": EVIL})).status_code == 200
        # The server's own pages (the dashboard) may, and so may a script with no Origin.
        own = server.url
        estop = await http.post("/api/robots/demo-arm/estop", headers={**auth, "Origin": own})
        assert estop.status_code == 200
        assert (await http.post("/api/robots/demo-arm/reset", headers=auth)).status_code == 200


async def test_a_body_must_be_json(server: RunningServer) -> None:
    async with server.client() as http:
        for content_type in (
            "text/plain",
            "application/x-www-form-urlencoded",
            "multipart/form-data",
        ):
            reply = await http.post(
                "/api/robots",
                content=b'{"robot_type": "so-arm100", "id": "planted"}',
                headers={"Content-Type": content_type},
            )
            assert reply.status_code == 415, content_type
            assert reply.json()["error"]["code"] == "UNSUPPORTED_MEDIA_TYPE"
        assert [r["id"] for r in (await http.get("/api/robots")).json()] == ["demo-arm"]
        # A bare POST needs no content type; JSON declared as such (with a charset) passes.
        assert (await http.post("/api/robots/demo-arm/estop")).status_code == 200
        assert (await http.post("/api/robots/demo-arm/reset")).status_code == 200
        created = await http.post(
            "/api/robots",
            content=b'{"robot_type": "so-arm100", "id": "fine"}',
            headers={"Content-Type": "application/json; charset=utf-8"},
        )
        assert created.status_code == 201, created.text


async def test_a_foreign_page_cannot_open_a_websocket(start_server: StartServer) -> None:
    server = await start_server(demo=True, allowed_origins=("http://lab-tools.local:3000",))
    robot = server.app.manager.get("demo-arm")
    for path in ("/ws/master/demo-arm", "/ws/slave/demo-arm", "/ws/robots/demo-arm/state"):
        status, body = await _upgrade(server, path, {"Origin": EVIL})
        assert status == 403, path
        assert json.loads(body)["error"]["code"] == "ORIGIN_NOT_ALLOWED"
    assert robot.snapshot().master is None
    for origin in (server.url, "http://lab-tools.local:3000"):
        status, _ = await _upgrade(server, "/ws/robots/demo-arm/state", {"Origin": origin})
        assert status == 101, origin


async def test_a_loopback_server_answers_only_to_its_own_names(start_server: StartServer) -> None:
    # DNS rebinding: evil.example resolves to 127.0.0.1, so its page is "same-origin"; the
    # Host header still names evil.example.
    server = await start_server(demo=True, allowed_hosts=("arena.lab",))
    port = server.url.rsplit(":", 1)[1]
    async with server.client() as http:
        for host in (f"evil.example:{port}", "evil.example"):
            reply = await http.get("/api/robots", headers={"Host": host})
            assert reply.status_code == 403 and reply.json()["error"]["code"] == "HOST_NOT_ALLOWED"
            rebound = await http.post(
                "/api/robots/demo-arm/estop",
                headers={"Host": host, "Origin": f"http://{host}"},
            )
            assert rebound.status_code == 403
        for host in (f"localhost:{port}", f"127.0.0.1:{port}", f"arena.lab:{port}", "[::1]"):
            assert (await http.get("/api/robots", headers={"Host": host})).status_code == 200, host
    status, body = await _upgrade(server, "/ws/master/demo-arm", {"Host": f"evil.example:{port}"})
    assert status == 403 and json.loads(body)["error"]["code"] == "HOST_NOT_ALLOWED"
    assert str(server.app.manager.get("demo-arm").snapshot().mode) != "estopped"


def test_allowed_origins_come_from_flags_and_the_config_file(tmp_path: Path) -> None:
    config_file = tmp_path / "arena.toml"
    config_file.write_text('allowed_origins = ["http://a.example"]\nallowed_hosts = ["lab"]\n')
    config = load_config(
        str(config_file), allowed_origins=("http://b.example",), allowed_hosts=("rig",)
    )
    assert config.allowed_origins == ("http://a.example", "http://b.example")
    assert config.allowed_hosts == ("lab", "rig")


async def test_what_a_caller_creates_is_bounded_and_said_so(start_server: StartServer) -> None:
    server = await start_server(
        api_keys=(ADMIN,), max_robots=3, max_groups=2, max_websockets_per_caller=2
    )
    admin = {"Authorization": f"Bearer {ADMIN}"}
    async with server.client(headers=admin) as http:
        # Names: a robot's name is a line of at most 128 characters, its id and a group's
        # members robot ids (1-64 letters, digits, '.', '_', '-').
        for body, field in (
            ({"name": "x" * 60_000}, "name"),
            ({"name": "two\nlines"}, "name"),
            ({"name": ""}, "name"),
            ({"id": "x" * 65}, "id"),
            ({"id": "../up"}, "id"),
        ):
            refused = await http.post("/api/robots", json=body)
            error = refused.json()["error"]
            assert (refused.status_code, error["code"]) == (422, "INVALID_BODY"), body
            assert f"Invalid `{field}`" in error["message"] and len(error["message"]) < 300, error
        made = [
            await http.post("/api/robots", json={"id": f"arm-{n}", "name": f"Arm {n} (SO-101)"})
            for n in range(3)
        ]
        assert [reply.status_code for reply in made] == [201, 201, 201]
        assert made[0].json()["name"] == "Arm 0 (SO-101)"
        # Robots: at most `max_robots` a tenant.
        refused = await http.post("/api/robots", json={"id": "arm-3"})
        error = refused.json()["error"]
        assert (refused.status_code, error["code"]) == (429, "LIMIT_REACHED")
        assert "3 robots" in error["message"] and "max_robots" in error["message"]
        # Groups: at most `max_groups` a tenant; their members are robot ids.
        for n in range(2):
            group = {"id": f"pair-{n}", "members": ["arm-0", "arm-1"]}
            assert (await http.post("/api/groups", json=group)).status_code == 201
        refused = await http.post("/api/groups", json={"id": "pair-2", "members": ["arm-2"]})
        error = refused.json()["error"]
        assert (refused.status_code, error["code"]) == (429, "LIMIT_REACHED")
        assert "2 groups" in error["message"] and "max_groups" in error["message"]
        await http.delete("/api/groups/pair-0")
        odd = await http.post("/api/groups", json={"id": "pair-2", "members": ["y" * 60_000]})
        assert odd.json()["error"]["code"] == "INVALID_BODY"
        assert (
            await http.post("/api/groups", json={"id": "pair-2", "members": ["arm-2"]})
        ).is_success
        # WebSockets: at most `max_websockets_per_caller` open at once for one caller.
        url = f"{server.ws_url}/ws/robots/arm-0/state?token={ADMIN}"
        async with open_websocket_url(url) as first, open_websocket_url(url) as second:
            for ws in (first, second):
                await receive(ws, "state")
            async with open_websocket_url(url) as third:
                error = await receive(third, "error")
                assert (error["data"]["code"], await closed_with(third)) == ("LIMIT_REACHED", 4429)
                assert "2 WebSockets" in error["data"]["message"]
        async with open_websocket_url(url) as again:  # the two closed: free again
            await receive(again, "state")
