"""The API's words: every refusal names what is wrong and what is allowed, no field a client
sends is silently ignored, and the contract (OpenAPI, specs/api.md, the README) says what the
code does. Real servers on 127.0.0.1, port 0."""

from __future__ import annotations

import ast
import inspect
import json
import re
import textwrap
import typing
from pathlib import Path
from typing import Any

import msgspec
import pytest
import trio
from trio_websocket import open_websocket_url

from arena.protocol import messages as wire
from arena.protocol.errors import ErrorCode
from arena.protocol.messages import MAX_MESSAGE_BYTES, decode_master, decode_slave
from arena.protocol.rest import MasterBody, SlaveBody
from arena.protocol.validation import nearest
from arena.server import openapi
from arena.server.base import STATUS_FOR
from arena.server.ws.connection import CLOSE_FOR
from tests.conftest import RunningServer, eventually
from tests.test_server_ws import command, receive

ROOT = Path(__file__).resolve().parent.parent
JSON = {"Content-Type": "application/json"}
#: What a refusal of the body's content (not of the world's state) answers.
VALIDATION_CODES = {
    "INVALID_BODY",
    "INVALID_JSON",
    "INVALID_VALUE",
    "INVALID_CONFIG",
    "UNKNOWN_FIELD",
    "UNSUPPORTED_MEDIA_TYPE",
    "MESSAGE_TOO_LARGE",
}


def tags(union: Any) -> list[str]:
    """The `type`s of a union of driver configs, as the code declares them."""
    return [str(member.__struct_config__.tag) for member in typing.get_args(union)]


# --- 1. the 413 names the limit ---------------------------------------------------------------


async def test_a_body_over_the_limit_is_refused_naming_the_limit(server: RunningServer) -> None:
    async def chunked() -> Any:
        for _ in range(70):
            yield b"x" * 1000

    async with server.client() as http:
        sized = await http.put("/api/robots/demo-arm/joints", content=b"x" * 70_000, headers=JSON)
        streamed = await http.put("/api/robots/demo-arm/joints", content=chunked(), headers=JSON)
    for response in (sized, streamed):
        assert response.status_code == 413
        error = response.json()["error"]
        assert error["code"] == "MESSAGE_TOO_LARGE"
        assert f"{MAX_MESSAGE_BYTES}-byte limit" in error["message"]
    assert "70000 bytes" in sized.json()["error"]["message"]
    # The WebSocket says it in the same words.
    async with open_websocket_url(f"{server.ws_url}/ws/master/demo-arm") as ws:
        await ws.send_message("x" * 70_000)
        error = (await receive(ws, "error"))["data"]
    assert error["code"] == "MESSAGE_TOO_LARGE"
    assert f"{MAX_MESSAGE_BYTES}-byte limit" in error["message"]


# --- 2. an unknown driver type lists the valid ones -------------------------------------------


@pytest.mark.parametrize(
    ("path", "union", "meant"),
    [("slaves", SlaveBody, "mock-slave"), ("master", MasterBody, "mock-sequence")],
)
async def test_an_unknown_driver_type_lists_the_valid_ones(
    server: RunningServer, path: str, union: Any, meant: str
) -> None:
    async with server.client() as http:
        for body in ({"type": "mock"}, {}):
            response = await http.post(f"/api/robots/demo-arm/{path}", json=body)
            assert response.status_code == 422
            error = response.json()["error"]
            assert error["code"] == "INVALID_BODY"
            said = "Unknown type 'mock'" if body else "Missing 'type'"
            assert said in error["message"], error["message"]
            for tag in tags(union):
                assert tag in error["message"], (tag, error["message"])
        wrong = await http.post(f"/api/robots/demo-arm/{path}", json={"type": "mock"})
        assert f"did you mean {meant!r}" in wrong.json()["error"]["message"]


def test_the_readme_names_the_driver_types_as_they_are() -> None:
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    (row,) = [line for line in readme.splitlines() if line.startswith("| drivers |")]
    for tag in [*tags(SlaveBody), *tags(MasterBody)]:
        assert f"`{tag}`" in row, tag


# --- 3. no field is silently ignored ----------------------------------------------------------


def body_routes() -> list[tuple[str, str, Any]]:
    return [(m, p, body) for m, p, _, body in openapi.ROUTES if body is not None]


def struct_infos(kind: Any) -> list[msgspec.inspect.StructType]:
    """Every struct type `kind` holds, itself and nested."""
    found: dict[type, msgspec.inspect.StructType] = {}

    def walk(info: msgspec.inspect.Type) -> None:
        if isinstance(info, msgspec.inspect.Metadata):
            walk(info.type)
        elif isinstance(info, msgspec.inspect.StructType):
            if info.cls not in found:
                found[info.cls] = info
                for field in info.fields:
                    walk(field.type)
        elif isinstance(info, msgspec.inspect.UnionType):
            for option in info.types:
                walk(option)
        elif isinstance(info, msgspec.inspect.ListType | msgspec.inspect.VarTupleType):
            walk(info.item_type)
        elif isinstance(info, msgspec.inspect.DictType):
            walk(info.value_type)

    walk(msgspec.inspect.type_info(kind))
    return list(found.values())


def test_every_body_and_message_type_refuses_unknown_fields() -> None:
    kinds = [body for *_, body in body_routes()] + [wire.MasterMessage, wire.SlaveMessage]
    structs = {info.cls: info for kind in kinds for info in struct_infos(kind)}
    assert len(structs) > 25  # the walk found the nested ones too
    lenient = sorted(
        cls.__name__ for cls, info in structs.items() if not info.forbid_unknown_fields
    )
    assert lenient == []


def objects_in(value: Any, path: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    """The path of every JSON object in `value` (the whole first)."""
    found = []
    if isinstance(value, dict):
        found.append(path)
        for key, item in value.items():
            found += objects_in(item, (*path, key))
    elif isinstance(value, list):
        for index, item in enumerate(value):
            found += objects_in(item, (*path, index))
    return found


def with_field(value: Any, path: tuple[Any, ...], name: str) -> Any:
    copy = json.loads(json.dumps(value))
    target = copy
    for step in path:
        target = target[step]
    target[name] = 1
    return copy


async def test_every_body_refuses_an_unknown_field_at_every_level(server: RunningServer) -> None:
    """Each route's examples, with a field added to each object in turn (a free-form object,
    such as a command's `metadata`, must not be in an example)."""
    checked = 0
    async with server.client() as http:
        assert (
            await http.post("/api/groups", json={"id": "g", "members": ["demo-arm"]})
        ).is_success
        for method, path, body in body_routes():
            url = path.replace("{robot_id}", "demo-arm").replace("{group_id}", "g")
            for example in openapi.examples(body).values():
                for where in objects_in(example["value"]):
                    sent = with_field(example["value"], where, "bogus_field")
                    before = (await http.get("/api/robots")).json()
                    response = await http.request(method, url, json=sent)
                    assert response.status_code == 400, (path, sent, response.text)
                    error = response.json()["error"]
                    assert error["code"] == "UNKNOWN_FIELD"
                    assert "'bogus_field'" in error["message"]
                    named = example["value"]
                    for step in where:
                        named = named[step]
                    for field in named:  # the allowed fields are listed
                        assert field in error["message"], (field, error["message"])
                    assert (await http.get("/api/robots")).json() == before
                    checked += 1
    assert checked >= 25


async def test_the_misspelled_id_is_refused_and_no_robot_is_made(server: RunningServer) -> None:
    async with server.client() as http:
        response = await http.post("/api/robots", json={"robot_id": "my-robot"})
        robots = [r["id"] for r in (await http.get("/api/robots")).json()]
    assert response.status_code == 400
    error = response.json()["error"]
    assert error["code"] == "UNKNOWN_FIELD"
    assert "'robot_id'" in error["message"] and "did you mean 'id'?" in error["message"]
    assert "robot_type, name, id" in error["message"]
    assert robots == ["demo-arm"]


async def test_a_route_that_takes_no_body_refuses_one_with_fields(server: RunningServer) -> None:
    async with server.client() as http:
        await http.post("/api/robots/demo-arm/estop")
        ignored = await http.post("/api/robots/demo-arm/reset", json={"force": True})
        assert ignored.status_code == 400
        assert ignored.json()["error"]["code"] == "UNKNOWN_FIELD"
        assert "'force'" in ignored.json()["error"]["message"]
        state = (await http.get("/api/robots/demo-arm/status")).json()["state"]
        assert state == "estopped"  # refused: nothing changed
        assert (await http.post("/api/robots/demo-arm/reset", json={})).status_code == 200
        assert (await http.post("/api/robots/demo-arm/estop")).status_code == 200
        assert (await http.post("/api/robots/demo-arm/reset")).status_code == 200


async def first_of(ws: Any, kinds: set[str]) -> dict[str, Any]:
    """The next message whose type is one of `kinds`."""
    with trio.fail_after(30):
        while True:
            message: dict[str, Any] = json.loads(await ws.get_message())
            if message["type"] in kinds:
                return message


async def test_a_websocket_message_with_an_unknown_field_is_refused(
    server: RunningServer,
) -> None:
    async with open_websocket_url(f"{server.ws_url}/ws/master/demo-arm") as ws:
        for message, name, allowed, hint in [
            (
                {"type": "command", "robot_id": "demo-arm", "data": {"joints": []}},
                "robot_id",
                "type, data, timestamp",
                None,
            ),
            (
                {"type": "command", "data": {"joints": [], "durration": 500}},
                "durration",
                "joints, timestamp, duration, metadata",
                "duration",
            ),
            (
                {"type": "command", "data": {"joints": [{"name": "Rotation", "vaule": 5}]}},
                "vaule",
                "name, value, speed",
                "value",
            ),
        ]:
            message["data"]["joints"] = message["data"]["joints"] or [
                {"name": "Rotation", "value": 30}
            ]
            await ws.send_message(json.dumps(message))
            answer = await first_of(ws, {"ack", "error"})
            assert answer["type"] == "error", answer  # not acted on
            error = answer["data"]
            assert error["code"] == "UNKNOWN_FIELD"
            assert f"{name!r}" in error["message"] and allowed in error["message"]
            if hint:
                assert f"did you mean {hint!r}?" in error["message"]
        # Nothing moved, and the connection still works.
        ack = await command(ws, {"Pitch": 1})
        assert ack["data"]["status"] == "accepted"
    async with server.client() as http:
        joints = {j["name"]: j for j in (await http.get("/api/robots/demo-arm/joints")).json()}
    assert joints["Rotation"]["virtual_value"] == 0


def test_every_websocket_message_type_refuses_an_unknown_field() -> None:
    messages: list[tuple[Any, dict[str, Any]]] = [
        (decode_master, {"type": "command", "data": {"joints": [{"name": "Jaw", "value": 1}]}}),
        (decode_master, {"type": "sequence", "data": {"commands": []}}),
        (decode_master, {"type": "heartbeat"}),
        (decode_master, {"type": "estop", "data": {"reason": "r"}}),
        (decode_master, {"type": "reset"}),
        (decode_slave, {"type": "status_update", "data": {"isConnected": True}}),
        (decode_slave, {"type": "joint_states", "data": [{"name": "Jaw", "value": 1}]}),
        (decode_slave, {"type": "error", "data": {"code": "X"}}),
        (decode_slave, {"type": "heartbeat"}),
    ]
    for decode, message in messages:
        decode(json.dumps(message))  # as it is, accepted
        for where in objects_in(message):
            with pytest.raises(Exception) as caught:
                decode(json.dumps(with_field(message, where, "bogus_field")))
            assert getattr(caught.value, "code", None) is ErrorCode.UNKNOWN_FIELD, message
            assert "'bogus_field'" in caught.value.message  # type: ignore[attr-defined]
    with pytest.raises(Exception) as caught:
        decode_master('{"type": "comand"}')
    assert caught.value.code is ErrorCode.UNKNOWN_MESSAGE_TYPE  # type: ignore[attr-defined]
    assert "did you mean 'command'" in caught.value.message  # type: ignore[attr-defined]


def test_an_answer_repeats_at_most_a_short_piece_of_what_was_sent() -> None:
    for message in (
        {"type": "command", "data": {"joints": []}, "x" * 50_000: 1},
        {"type": "y" * 50_000},
        {"type": "estop", "data": {"reason": "r", "z" * 50_000: 1}},
    ):
        with pytest.raises(Exception) as caught:
            decode_master(json.dumps(message))
        assert len(caught.value.message) < 300  # type: ignore[attr-defined]


def test_the_nearest_name() -> None:
    assert nearest("robot_id", ["robot_type", "name", "id"]) == "id"
    assert nearest("baud_rate", ["port", "baudRate"]) == "baudRate"
    assert nearest("mock", ["mock-slave", "usb-slave"]) == "mock-slave"
    assert nearest("durration", ["joints", "duration"]) == "duration"
    assert nearest("colour", ["name", "source", "fps"]) is None


# --- 4. replay refusals name the field --------------------------------------------------------


async def test_replay_refusals_name_the_field(server: RunningServer) -> None:
    async with server.client() as http:
        assert (await http.post("/api/robots", json={"id": "second"})).status_code == 201
        for robot in ("demo-arm", "second"):
            moved = await http.put(
                f"/api/robots/{robot}/joints", json={"joints": [{"name": "Rotation", "value": 9}]}
            )
            assert moved.status_code == 200

        async def file_open() -> bool:  # the recorder's next batch opens the file
            return bool((await http.get("/api/recordings")).json()["recorder"]["file"])

        await eventually(file_open, what="the recording's file")
        name = (await http.post("/api/recordings/current/stop")).json()["stopped"]
        assert name
        cases: list[tuple[dict[str, Any], str, list[str]]] = [
            ({"recording": name}, "INVALID_VALUE", ["`source_robot`", "demo-arm", "second"]),
            ({"recording": name, "source_robot": "ghost"}, "UNKNOWN_ROBOT", ["`source_robot`"]),
            ({"recording": "nope.mcap"}, "UNKNOWN_RECORDING", ["`recording`"]),
            ({"recording": "../x"}, "UNKNOWN_RECORDING", ["`recording`"]),
            ({"recording": name, "source_robot": "second", "speed": 0}, "INVALID_BODY", ["speed"]),
            (
                {"recording": name, "source_robot": "second", "start": 5, "end": 2},
                "INVALID_VALUE",
                ["`end`", "`start`"],
            ),
            (
                {"recording": name, "source_robot": "second", "start": 3600},
                "INVALID_VALUE",
                ["`start`"],
            ),
        ]
        for body, code, words in cases:
            for url, sent in (
                ("/api/robots/demo-arm/replay", body),
                ("/api/robots/demo-arm/master", {"type": "replay", **body}),
            ):
                response = await http.post(url, json=sent)
                error = response.json()["error"]
                assert error["code"] == code, (sent, error)
                for word in words:
                    assert word in error["message"], (sent, error)
        status = (await http.get("/api/robots/demo-arm/status")).json()
        assert status["has_master"] is False


# --- 5. OpenAPI says what the routes do -------------------------------------------------------


def returned_statuses(view: Any) -> set[int]:
    """The success statuses a view's code returns: `return body, 201`, `redirect(...)` (302),
    a `Response(..., status=N)`, else 200. Nested functions are not the view's answers."""
    tree = ast.parse(textwrap.dedent(inspect.getsource(view)))
    function = tree.body[0]
    assert isinstance(function, ast.AsyncFunctionDef | ast.FunctionDef)
    statuses: dict[str, int] = {}  # variables assigned a Response with a status

    def status_of(node: ast.expr) -> int | None:
        if isinstance(node, ast.Call):
            name = getattr(node.func, "id", getattr(node.func, "attr", ""))
            if name == "redirect":
                return 302
            for keyword in node.keywords:
                if keyword.arg == "status" and isinstance(keyword.value, ast.Constant):
                    return int(keyword.value.value)
        return None

    found: set[int] = set()

    def visit(node: ast.AST) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda):
                continue
            if isinstance(child, ast.Assign) and len(child.targets) == 1:
                target = child.targets[0]
                status = status_of(child.value)
                if isinstance(target, ast.Name) and status is not None:
                    statuses[target.id] = status
            if isinstance(child, ast.Return) and child.value is not None:
                value = child.value
                if isinstance(value, ast.Await):
                    value = value.value
                last = value.elts[-1] if isinstance(value, ast.Tuple) else None
                if isinstance(last, ast.Constant) and isinstance(last.value, int):
                    found.add(last.value)
                elif isinstance(value, ast.Name) and value.id in statuses:
                    found.add(statuses[value.id])
                else:
                    found.add(status_of(value) or 200)
            visit(child)

    visit(function)
    return found


async def test_openapi_gives_each_route_the_status_its_code_answers(server: RunningServer) -> None:
    async with server.client() as http:
        document = (await http.get("/openapi.json")).json()
        created = await http.post("/api/robots", json={})
    assert created.status_code == 201
    checked = 0
    for rule in server.app.url_map.iter_rules():
        if rule.websocket or rule.endpoint == "static":
            continue
        path = re.sub(r"<(?:\w+:)?(\w+)>", r"{\1}", rule.rule)
        (status,) = returned_statuses(server.app.view_functions[rule.endpoint])
        for method in rule.methods - {"HEAD", "OPTIONS"}:
            responses = document["paths"][path][method.lower()]["responses"]
            success = {int(code) for code in responses if code != "default"}
            assert success == {status}, (method, path, success, status)
            checked += 1
    assert checked > 50
    assert "201" in document["paths"]["/api/robots"]["post"]["responses"]


async def test_every_request_body_has_examples_its_route_accepts(server: RunningServer) -> None:
    async with server.client() as http:
        document = (await http.get("/openapi.json")).json()
        page = (await http.get("/docs")).text
        assert "examples" in page  # /docs fills them in
        sent = 0
        for method, path, body in body_routes():
            content = document["paths"][path][method.lower()]["requestBody"]["content"]
            shown = content["application/json"]["examples"]
            members = typing.get_args(body) or (body,)
            assert len(shown) == len(members), path  # one for each type of a union
            for example in shown.values():
                value = example["value"]
                msgspec.json.decode(json.dumps(value), type=body)  # the route's own decoding
                # A fresh robot each time, so that one example's effect does not refuse the next.
                robot = (await http.post("/api/robots", json={})).json()["id"]
                url = path.replace("{robot_id}", robot).replace("{group_id}", "g")
                response = await http.request(method, url, json=value)
                if response.status_code >= 300:
                    code = response.json()["error"]["code"]
                    # Refused for the world (no hardware here, no such file), not the body.
                    assert code not in VALIDATION_CODES, (path, value, response.text)
                sent += 1
    assert sent >= 20


# --- 6. the error table is the code's ---------------------------------------------------------


def error_table() -> dict[str, tuple[int | None, int | None]]:
    """specs/api.md's error table: code -> (HTTP status, WebSocket close code)."""
    text = (ROOT / "specs" / "api.md").read_text(encoding="utf-8")
    section = text.split("## Errors", 1)[1].split("\n## ", 1)[0]
    rows = [line for line in section.splitlines() if line.startswith("| ")][1:]  # no header
    table: dict[str, tuple[int | None, int | None]] = {}

    def numbers(cell: str, count: int) -> list[int | None]:
        if "(" in cell:  # "(HTTP 403 to the handshake)": no close code
            cell = ""
        found = [int(n) for n in re.findall(r"\d{3,4}", cell)]
        if not found:
            return [None] * count
        return found if len(found) == count else found * count

    for row in rows:
        cells = [cell.strip() for cell in row.strip("|").split("|")]
        codes = re.findall(r"[A-Z][A-Z0-9_]+", cells[0])
        pairs = zip(
            codes, numbers(cells[1], len(codes)), numbers(cells[2], len(codes)), strict=True
        )
        for code, status, close in pairs:
            assert code not in table, f"{code} is in the table twice"
            table[code] = (status, close)
    return table


def test_the_error_table_holds_every_code_both_ways() -> None:
    table = error_table()
    codes = {str(code) for code in ErrorCode}
    assert sorted(codes - set(table)) == [], "codes the server sends that the table lacks"
    assert sorted(set(table) - codes) == [], "codes in the table that the server never sends"
    for code in ErrorCode:
        status, close = table[str(code)]
        if code in STATUS_FOR:
            assert status == STATUS_FOR[code], code
        elif status is not None:
            assert status == 400, code  # the status of any code without its own
        assert close == CLOSE_FOR.get(code), code


#: Calls whose first argument is an error code that leaves the server.
_CODE_TAKERS = {
    "ArenaError",
    "report_fault",
    "report_sensor_fault",
    "send_error",
    "error_message",
    "error_response",
}


def test_every_code_the_server_sends_is_an_error_code() -> None:
    """No code is sent as a bare string (which the table could not be held to), and every
    `ErrorCode` is sent somewhere."""
    bare: list[str] = []
    used: set[str] = set()
    for path in sorted((ROOT / "arena").rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        # A code as a key of a table (its HTTP status, its close code) is not a code sent.
        keys = {
            id(key) for node in ast.walk(tree) if isinstance(node, ast.Dict) for key in node.keys
        }
        for node in ast.walk(tree):
            if (
                isinstance(node, ast.Attribute)
                and isinstance(node.value, ast.Name)
                and node.value.id == "ErrorCode"
                and id(node) not in keys
            ):
                used.add(node.attr)
            if not isinstance(node, ast.Call):
                continue
            name = getattr(node.func, "id", getattr(node.func, "attr", ""))
            if name not in _CODE_TAKERS:
                continue
            arguments = [a for a in node.args if not isinstance(a, ast.Starred)]
            first = arguments[0] if arguments else None
            if name == "report_sensor_fault" and len(arguments) > 1:
                first = arguments[1]
            if isinstance(first, ast.Constant) and isinstance(first.value, str):
                bare.append(f"{path.relative_to(ROOT)}:{node.lineno} {first.value}")
    assert bare == []
    assert sorted({code.name for code in ErrorCode} - used) == []
