"""The REST API against a real server on 127.0.0.1 (port 0): the seed's table and beyond."""

from __future__ import annotations

import logging
import re
import shutil
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import pytest
import trio

from arena.protocol.errors import ArenaError, ErrorCode
from arena.robot.model import BUILTIN_TYPES_DIR, TYPES_PATH_ENV
from arena.server.config import ServerConfig, load_config
from tests.conftest import RunningServer, eventually

StartServer = Callable[..., Awaitable[RunningServer]]
JSON = {"Content-Type": "application/json"}


async def test_the_seed_curl_table(server: RunningServer) -> None:
    async with server.client() as http:
        status = (await http.get("/")).json()
        assert status["status"] == "running" and status["robots"] == 1
        robots = (await http.get("/api/robots")).json()
        assert [r["id"] for r in robots] == ["demo-arm"]
        created = await http.post(
            "/api/robots", headers=JSON, json={"robot_type": "so-arm100", "name": "My Robot"}
        )
        assert created.status_code == 201
        robot = created.json()
        robot_id = robot["id"]
        assert robot["name"] == "My Robot" and robot["state"] == "idle"
        assert [j["name"] for j in robot["joints"]] == [
            "Rotation",
            "Pitch",
            "Elbow",
            "Wrist_Pitch",
            "Wrist_Roll",
            "Jaw",
        ]
        details = (await http.get(f"/api/robots/{robot_id}")).json()
        assert details["robot_type"] == "so-arm100"
        assert (await http.get(f"/api/robots/{robot_id}/status")).json()["has_master"] is False
        sequences = (await http.get("/api/sequences")).json()
        assert {s["id"]: s["duration"] for s in sequences} == {
            "gentle-wave": 6000,
            "small-scan": 8000,
            "tiny-flex": 8000,
        }
        played = await http.post("/api/robots/demo-arm/play-sequence/gentle-wave")
        assert played.status_code == 200 and played.json()["sequence"] == "gentle-wave"
        status = (await http.get("/api/robots/demo-arm/status")).json()
        assert status["has_master"] and status["master"]["type"] == "mock-sequence"

        async def moved() -> bool:
            joints = (await http.get("/api/robots/demo-arm/joints")).json()
            return any(j["real_value"] not in (None, 0.0) for j in joints)

        await eventually(moved)
        stopped = (await http.post("/api/robots/demo-arm/stop-sequence")).json()
        assert stopped["stopped"] is True
        assert (await http.get("/api/robots/demo-arm/status")).json()["state"] == "idle"
        assert (await http.delete(f"/api/robots/{robot_id}")).json() == {"deleted": robot_id}
        gone = await http.get(f"/api/robots/{robot_id}")
        assert gone.status_code == 404
        assert gone.json()["error"]["code"] == "UNKNOWN_ROBOT"


async def test_estop_reset_and_manual_control(server: RunningServer) -> None:
    async with server.client() as http:
        moved = await http.put(
            "/api/robots/demo-arm/joints",
            json={
                "joints": [
                    {"name": "Rotation", "value": 45},
                    {"name": "shoulder_lift", "value": -30},
                ]
            },
        )
        assert moved.status_code == 200 and moved.json()["status"] == "accepted"
        clamped = await http.put(
            "/api/robots/demo-arm/joints", json={"joints": [{"name": "Jaw", "value": 500}]}
        )
        assert clamped.json()["status"] == "clamped"
        assert clamped.json()["clamped"][0]["joint"] == "Jaw"

        async def followed() -> bool:
            joints = {j["name"]: j for j in (await http.get("/api/robots/demo-arm/joints")).json()}
            return joints["Rotation"]["real_value"] == 45 and joints["Pitch"]["real_value"] == -30

        await eventually(followed)
        stopped = await http.post("/api/robots/demo-arm/estop", json={"reason": "test button"})
        assert stopped.json()["state"] == "estopped"
        assert stopped.json()["estop_reason"] == "test button"
        refused = await http.put(
            "/api/robots/demo-arm/joints", json={"joints": [{"name": "Rotation", "value": 0}]}
        )
        assert refused.status_code == 423 and refused.json()["error"]["code"] == "ESTOPPED"
        assert (await http.post("/api/robots/demo-arm/reset")).json()["state"] == "idle"
        sequence = await http.post(
            "/api/robots/demo-arm/master",
            json={"type": "mock-sequence", "sequences": ["tiny-flex"]},
        )
        assert sequence.status_code == 201
        busy = await http.put(
            "/api/robots/demo-arm/joints", json={"joints": [{"name": "Rotation", "value": 0}]}
        )
        assert busy.status_code == 409 and busy.json()["error"]["code"] == "MASTER_ACTIVE"
        everything = await http.post("/api/estop")
        assert everything.json() == {"estopped": ["demo-arm"]}
        status = (await http.get("/api/robots/demo-arm/status")).json()
        assert status["state"] == "estopped" and status["has_master"] is False
        assert (await http.delete("/api/robots/demo-arm/master")).json() == {"detached": None}


async def test_slaves_and_masters_over_rest(server: RunningServer) -> None:
    async with server.client() as http:
        attached = await http.post(
            "/api/robots/demo-arm/slaves", json={"type": "mock-slave", "simulateLatency": 50}
        )
        assert attached.status_code == 201 and attached.json()["type"] == "mock-slave"
        slave_id = attached.json()["id"]
        slaves = (await http.get("/api/robots/demo-arm/status")).json()["slaves"]
        assert slave_id in [s["id"] for s in slaves] and len(slaves) == 2
        assert (await http.delete(f"/api/robots/demo-arm/slaves/{slave_id}")).status_code == 200
        again = await http.delete(f"/api/robots/demo-arm/slaves/{slave_id}")
        assert again.status_code == 404 and again.json()["error"]["code"] == "UNKNOWN_SLAVE"
        master = await http.post(
            "/api/robots/demo-arm/master", json={"type": "mock-sequence", "loop": True}
        )
        assert master.status_code == 201
        detached = await http.delete("/api/robots/demo-arm/master")
        assert detached.json() == {"detached": master.json()["id"]}


async def test_manual_control_is_rate_limited(
    start_server: StartServer, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # A robot type allowing one command and then one a thousand seconds: however slow the
    # machine, the second request comes too soon (the limiter's timing is tested on MockClock).
    folder = tmp_path / "types" / "so-arm100-slow"
    shutil.copytree(BUILTIN_TYPES_DIR / "so-arm100", folder)
    config = folder / "robot.toml"
    text = re.sub(r"command_rate = [\d.]+", "command_rate = 0.001", config.read_text())
    config.write_text(re.sub(r"command_burst = \d+", "command_burst = 1", text))
    monkeypatch.setenv(TYPES_PATH_ENV, str(folder.parent))
    server = await start_server()
    async with server.client() as http:
        created = await http.post("/api/robots", json={"robot_type": "so-arm100-slow", "id": "s"})
        assert created.status_code == 201, created.text
        codes = []
        for i in range(3):
            response = await http.put(
                "/api/robots/s/joints", json={"joints": [{"name": "Rotation", "value": i}]}
            )
            codes.append(response.status_code)
        assert codes == [200, 429, 429]
        assert response.json()["error"]["code"] == "RATE_LIMITED"


JOINTS = "/api/robots/demo-arm/joints"
BAD_REQUESTS: list[tuple[str, str, Any, int, str]] = [
    ("POST", "/api/robots", b"{not json", 422, "INVALID_JSON"),
    ("POST", "/api/robots", {"robot_type": 5}, 422, "INVALID_BODY"),
    ("POST", "/api/robots", {"robot_type": "toaster"}, 422, "UNKNOWN_ROBOT_TYPE"),
    ("POST", "/api/robots", {"id": "demo-arm"}, 409, "ROBOT_EXISTS"),
    ("POST", "/api/robots", {"id": "../../etc/passwd"}, 422, "INVALID_BODY"),
    ("POST", "/api/robots", b"[1, 2]", 422, "INVALID_BODY"),
    ("PUT", "/api/robots/demo-arm/joints", {}, 422, "INVALID_BODY"),
    ("PUT", "/api/robots/demo-arm/joints", {"joints": "Rotation"}, 422, "INVALID_BODY"),
    (
        "PUT",
        "/api/robots/demo-arm/joints",
        {"joints": [{"name": "Nope", "value": 1}]},
        422,
        "UNKNOWN_JOINT",
    ),
    (
        "PUT",
        "/api/robots/demo-arm/joints",
        {"joints": [{"name": "Rotation", "value": "1"}]},
        422,
        "INVALID_BODY",
    ),
    (
        "PUT",
        "/api/robots/demo-arm/joints",
        b'{"joints": [{"name": "Rotation", "value": 1e400}]}',
        422,
        "INVALID_BODY",
    ),
    (
        "PUT",
        "/api/robots/demo-arm/joints",
        b'{"joints": [{"name": "Rotation", "value": NaN}]}',
        422,
        "INVALID_JSON",
    ),
    ("PUT", "/api/robots/demo-arm/joints", {"joints": []}, 422, "EMPTY_COMMAND"),
    (
        "PUT",
        "/api/robots/demo-arm/joints",
        {"joints": [{"name": "Rotation", "value": 1}], "duration": -5},
        422,
        "INVALID_VALUE",
    ),
    ("PUT", "/api/robots/demo-arm/joints", b"x" * 70_000, 413, "MESSAGE_TOO_LARGE"),
    ("POST", "/api/robots/demo-arm/slaves", {"type": "warp-drive"}, 422, "INVALID_BODY"),
    # A joining speed is slow and positive (no port is opened for a refused body).
    *(
        ("POST", "/api/robots/demo-arm/slaves", {"type": "usb-slave", "joinSpeed": v}, 422, code)
        for v, code in ((0, "INVALID_BODY"), (500, "INVALID_BODY"), ("fast", "INVALID_BODY"))
    ),
    (
        "POST",
        "/api/robots/demo-arm/slaves",
        {"type": "mock-slave", "simulateLatency": -1},
        422,
        "INVALID_CONFIG",
    ),
    (
        "POST",
        "/api/robots/demo-arm/slaves",
        {"type": "mock-slave", "errorRate": 2},
        422,
        "INVALID_CONFIG",
    ),
    # (checked before any connection: the URL is never dialled)
    (
        "POST",
        "/api/robots/demo-arm/slaves",
        {"type": "websocket-slave", "url": "ws://127.0.0.1:9"},
        422,
        "INVALID_CONFIG",
    ),
    (
        "POST",
        "/api/robots/demo-arm/master",
        {"type": "mock-sequence", "sequences": ["moon"]},
        404,
        "UNKNOWN_SEQUENCE",
    ),
    ("POST", "/api/robots/demo-arm/play-sequence/moonwalk", None, 404, "UNKNOWN_SEQUENCE"),
    ("POST", "/api/robots/ghost/play-sequence/gentle-wave", None, 404, "UNKNOWN_ROBOT"),
    ("GET", "/api/robots/ghost/status", None, 404, "UNKNOWN_ROBOT"),
    ("DELETE", "/api/robots/ghost", None, 404, "UNKNOWN_ROBOT"),
    ("PATCH", "/api/robots/demo-arm", {}, 405, "METHOD_NOT_ALLOWED"),
    ("GET", "/api/nothing-here", None, 404, "NOT_FOUND"),
    ("POST", "/api/robots/demo-arm/estop", {"reason": 7}, 422, "INVALID_BODY"),
]


@pytest.mark.parametrize(("method", "path", "body", "status", "code"), BAD_REQUESTS)
async def test_bad_requests_get_a_json_error_and_change_nothing(
    server: RunningServer, method: str, path: str, body: Any, status: int, code: str
) -> None:
    async with server.client() as http:
        before = (await http.get("/api/robots")).json()
        kwargs: dict[str, Any] = (
            {"content": body}
            if isinstance(body, bytes)
            else ({"json": body} if body is not None else {})
        )
        response = await http.request(method, path, **kwargs)
        assert response.status_code == status
        assert response.headers["content-type"].startswith("application/json")
        error = response.json()["error"]
        assert error["code"] == code
        assert error["message"] and "Traceback" not in error["message"]
        assert (await http.get("/api/robots")).json() == before


@pytest.mark.parametrize(("method", "path"), [("POST", "/api/robots"), ("PUT", JOINTS)])
async def test_an_empty_body_is_called_empty_not_truncated_json(
    server: RunningServer, method: str, path: str
) -> None:
    """`curl -X POST .../robots` with no `-d`: the answer said "not valid JSON: Input data was
    truncated", which reads like a cut connection; it says the body is empty and what to send."""
    async with server.client() as http:
        for headers in ({}, {"Content-Type": "application/json"}):
            response = await http.request(method, path, content=b"", headers=headers)
            assert response.status_code == 422, response.text
            error = response.json()["error"]
            assert error["code"] == "INVALID_JSON", error
            assert error["message"].startswith("The body is empty: "), error
            assert "JSON object" in error["message"], error


async def test_api_keys(start_server: StartServer, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.DEBUG)
    server = await start_server(demo=True, api_keys=("s3cret-key",))
    async with server.client() as http:
        missing = await http.post("/api/robots", json={})
        assert missing.status_code == 401 and missing.json()["error"]["code"] == "UNAUTHORIZED"
        wrong = await http.post("/api/robots", json={}, headers={"Authorization": "Bearer nope"})
        assert wrong.status_code == 403 and wrong.json()["error"]["code"] == "FORBIDDEN"
        assert (await http.get("/api/robots")).status_code == 401
        assert (await http.get("/docs")).status_code == 200
        good = {"Authorization": "Bearer s3cret-key"}
        assert (await http.post("/api/robots", json={}, headers=good)).status_code == 201
        assert (await http.get("/api/robots", headers=good)).status_code == 200
    assert "s3cret-key" not in caplog.text


async def test_open_reads(start_server: StartServer) -> None:
    server = await start_server(demo=True, api_keys=("k",), open_reads=True)
    async with server.client() as http:
        assert (await http.get("/api/robots")).status_code == 200
        assert (await http.post("/api/robots/demo-arm/estop")).status_code == 401


def test_refuses_to_bind_beyond_loopback_without_keys(monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(ArenaError) as info:
        ServerConfig(host="0.0.0.0").check()
    assert info.value.code is ErrorCode.INVALID_CONFIG and "--api-key" in info.value.message
    ServerConfig(host="0.0.0.0", insecure=True).check()
    ServerConfig(host="0.0.0.0", api_keys=("k",)).check()
    ServerConfig(host="::1").check()
    ServerConfig(host="localhost").check()
    monkeypatch.setenv("ARENA_API_KEYS", "a,b")
    config = load_config(None, host="0.0.0.0", api_keys=("c",))
    assert config.api_keys == ("a", "b", "c")
    config.check()


def test_config_file(tmp_path: Any) -> None:
    path = tmp_path / "arena.toml"
    path.write_text('port = 9000\napi_keys = ["x"]\nheartbeat_timeout = 5.0\n')
    config = load_config(str(path))
    assert (config.port, config.api_keys, config.heartbeat_timeout) == (9000, ("x",), 5.0)
    path.write_text("prot = 9000\n")
    with pytest.raises(ArenaError) as info:
        load_config(str(path))
    assert "prot" in info.value.message


async def test_openapi_covers_every_route_and_docs_load_nothing_external(
    server: RunningServer,
) -> None:
    async with server.client() as http:
        document = (await http.get("/openapi.json")).json()
        page = (await http.get("/docs")).text
    documented = {(m.upper(), p) for p, ops in document["paths"].items() for m in ops}
    routes = set()
    for rule in server.app.url_map.iter_rules():
        if rule.websocket or rule.endpoint == "static":
            continue
        path = re.sub(r"<(?:\w+:)?(\w+)>", r"{\1}", rule.rule)
        for method in rule.methods - {"HEAD", "OPTIONS"}:
            routes.add((method, path))
    assert routes == documented
    put_joints = document["paths"]["/api/robots/{robot_id}/joints"]["put"]
    assert "requestBody" in put_joints
    assert "JointValue" in document["components"]["schemas"]
    assert "CommandMessage" in document["components"]["schemas"]
    assert not re.search(r"(src|href)=[\"']https?://", page)


async def test_metrics(server: RunningServer) -> None:
    async with server.client() as http:
        await http.put(
            "/api/robots/demo-arm/joints", json={"joints": [{"name": "Rotation", "value": 1}]}
        )
        await http.put(
            "/api/robots/demo-arm/joints", json={"joints": [{"name": "Nope", "value": 1}]}
        )
        await http.post("/api/robots/demo-arm/estop")
        text = (await http.get("/metrics")).text
    assert "arena_robots 1" in text
    assert 'arena_commands_total{result="accepted"} 1' in text
    assert 'arena_commands_total{result="UNKNOWN_JOINT"} 1' in text
    assert "arena_estops_total 1" in text
    assert 'arena_connections{role="master"} 0' in text


async def test_tls(start_server: StartServer, tmp_path: Any) -> None:
    import shutil
    import subprocess

    if shutil.which("openssl") is None:
        pytest.skip("openssl is not installed")
    cert, key = tmp_path / "cert.pem", tmp_path / "key.pem"
    subprocess.run(
        [
            "openssl",
            "req",
            "-x509",
            "-newkey",
            "rsa:2048",
            "-nodes",
            "-days",
            "1",
            "-subj",
            "/CN=127.0.0.1",
            "-keyout",
            str(key),
            "-out",
            str(cert),
        ],
        check=True,
        capture_output=True,
    )
    server = await start_server(demo=True, certfile=str(cert), keyfile=str(key))
    assert server.url.startswith("https://")
    async with server.client(verify=False) as http:
        assert (await http.get("/")).json()["status"] == "running"
    # WebSockets over TLS take the transport's stream path (no raw socket to write to).
    import ssl

    from trio_websocket import open_websocket_url

    from tests.test_server_ws import command

    context = ssl.create_default_context(cafile=str(cert))
    context.check_hostname = False
    wss = "wss" + server.url[len("https") :] + "/ws/master/demo-arm"
    async with open_websocket_url(wss, ssl_context=context) as master:
        reply = await command(master, {"Rotation": 4})
        assert reply["data"]["status"] == "accepted"


async def test_recordings_over_rest(server: RunningServer) -> None:
    async with server.client() as http:
        await http.put(
            "/api/robots/demo-arm/joints", json={"joints": [{"name": "Rotation", "value": 20}]}
        )
        with trio.fail_after(30):  # the recorder's next batch opens the file
            while True:
                listing = (await http.get("/api/recordings")).json()
                if any(r["active"] for r in listing["recordings"]):
                    break
                await trio.sleep(0.02)
        assert listing["recorder"]["active"] is True
        (current,) = [r for r in listing["recordings"] if r["active"]]
        name = current["name"]
        stopped = (await http.post(f"/api/recordings/{name}/stop")).json()
        assert stopped["stopped"] == name and stopped["active"] is False
        summary = (await http.get(f"/api/recordings/{name}")).json()
        assert summary["truncated"] is False
        assert summary["topics"]["/robots/demo-arm/command"]["count"] == 1
        download = await http.get(f"/api/recordings/{name}/file")
        assert download.status_code == 200
        assert download.content == (server.app.recorder.folder / name).read_bytes()
        assert (await http.post("/api/recordings")).json()["active"] is True
        await http.put(
            "/api/robots/demo-arm/joints", json={"joints": [{"name": "Rotation", "value": 0}]}
        )
        with trio.fail_after(30):  # a new file, once the next batch comes
            while (
                len(
                    names := [
                        r["name"] for r in (await http.get("/api/recordings")).json()["recordings"]
                    ]
                )
                < 2
            ):
                await trio.sleep(0.02)
        assert len(names) == 2
        replay = await http.post(
            "/api/robots/demo-arm/replay", json={"recording": name, "speed": 4}
        )
        assert replay.status_code == 201
        assert replay.json()["master"]

        async def replayed() -> bool:
            joints = (await http.get("/api/robots/demo-arm/joints")).json()
            return joints[0]["real_value"] == 20

        await eventually(replayed)
        for bad in ("..%2F..%2Fetc%2Fpasswd", "nope.mcap", ".hidden.mcap"):
            response = await http.get(f"/api/recordings/{bad}")
            assert response.status_code == 404, bad
        missing = await http.post("/api/robots/demo-arm/replay", json={"recording": "x.mcap"})
        assert missing.status_code == 404
        assert missing.json()["error"]["code"] == "UNKNOWN_RECORDING"


async def test_no_record_starts_idle(start_server: StartServer) -> None:
    server = await start_server(demo=True, record=False)
    async with server.client() as http:
        await http.put(
            "/api/robots/demo-arm/joints", json={"joints": [{"name": "Rotation", "value": 20}]}
        )
        recorder = server.app.recorder
        # the recorder has taken (and, paused, dropped) the events
        await eventually(lambda: not any(len(queue) for queue in recorder._followed))
        listing = (await http.get("/api/recordings")).json()
        assert listing["recorder"]["active"] is False and listing["recordings"] == []


async def test_a_sequence_for_another_robot_type_is_refused_before_it_plays(
    server: RunningServer,
) -> None:
    # The demo sequences name the so-arm100's joints: on an so-101 every command would be
    # refused while the answer said it played.
    async with server.client() as http:
        created = await http.post("/api/robots", headers=JSON, json={"robot_type": "so-101"})
        robot = created.json()["id"]
        played = await http.post(f"/api/robots/{robot}/play-sequence/gentle-wave")
        assert played.status_code == 422
        error = played.json()["error"]
        assert error["code"] == "UNKNOWN_JOINT"
        assert "gentle-wave" in error["message"] and "so-101" in error["message"]
        master = await http.post(
            f"/api/robots/{robot}/master", headers=JSON, json={"type": "mock-sequence"}
        )
        assert master.status_code == 422 and master.json()["error"]["code"] == "UNKNOWN_JOINT"
        status = (await http.get(f"/api/robots/{robot}/status")).json()
        assert status["has_master"] is False
