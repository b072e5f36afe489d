"""Fuzzing the edges: generated messages and bodies, from nearly valid to hostile.

Every one gets an error code (or, if it happens to be valid, an ordinary answer), nothing
crashes, and the robot is left as it was.
"""

from __future__ import annotations

import json
import math
from collections.abc import Awaitable, Callable
from typing import Any

import pytest
import trio
from hypothesis import given, settings
from hypothesis import strategies as st
from trio_websocket import ConnectionClosed, open_websocket_url

from arena.protocol.errors import ArenaError, ErrorCode
from arena.protocol.messages import decode_master, decode_slave
from tests.conftest import RunningServer, eventually
from tests.raw_websocket import OP_TEXT, RawWebSocket
from tests.test_server_ws import command, receive

EDGE_CODES = {
    ErrorCode.INVALID_JSON,
    ErrorCode.INVALID_MESSAGE,
    ErrorCode.UNKNOWN_MESSAGE_TYPE,
    ErrorCode.UNKNOWN_FIELD,
    ErrorCode.MESSAGE_TOO_LARGE,
}

json_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(10**30), 10**30)
    | st.floats(allow_nan=False, allow_infinity=False)
    | st.text(max_size=20),
    lambda children: (
        st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=8), children, max_size=4)
    ),
    max_leaves=20,
)
hostile_numbers = st.sampled_from(
    ["NaN", "Infinity", "-Infinity", "1e400", "-1e309", "1" * 400, "0x10", "00", "1.", ".5"]
)
joint_names = st.sampled_from(["Rotation", "Pitch", "Jaw", "shoulder_pan", "Nope", "", "ROTATION"])
message_types = st.sampled_from(
    ["command", "sequence", "heartbeat", "estop", "reset", "joint_states", "error", "teleport"]
)


@st.composite
def nearly_valid(draw: st.DrawFn) -> str:
    """A command or sequence with one part wrong (or a hostile number spliced in)."""
    joints = [
        {"name": draw(joint_names), "value": draw(json_values)}
        for _ in range(draw(st.integers(0, 3)))
    ]
    data: dict[str, Any] = {"joints": joints}
    if draw(st.booleans()):
        data["duration"] = draw(json_values)
    message = {"type": draw(message_types), "data": draw(st.sampled_from([data, json_values]))}
    text = json.dumps(message, default=str)
    if draw(st.booleans()) and '"value": ' in text:
        text = text.replace('"value": ', f'"value": {draw(hostile_numbers)}, "x": ', 1)
    return text


@st.composite
def deep(draw: st.DrawFn) -> str:
    depth = draw(st.integers(50, 5000))
    return '{"type": "command", "data": ' + "[" * depth + "]" * depth + "}"


frames = (
    nearly_valid()
    | deep()
    | json_values.map(json.dumps)
    | st.text(max_size=100)
    | st.binary(max_size=64)
)


def intent(server: RunningServer) -> tuple[object, ...]:
    """What a refused input must not change: the robot's mode, owner and joint goals.

    (Virtual values keep moving while an earlier, valid move plays out: goals do not.)
    """
    snapshot = server.app.manager.get("demo-arm").snapshot()
    return (snapshot.mode, snapshot.owner, tuple(j.goal for j in snapshot.joints))


def predicted(frame: str | bytes, decode: Any) -> ErrorCode | None:
    """What the edge should answer, from the codec alone (None: the frame is valid)."""
    if isinstance(frame, bytes):
        return ErrorCode.BINARY_NOT_SUPPORTED
    try:
        decode(frame)
    except ArenaError as error:
        return error.code
    return None


@given(frames)
def test_the_codecs_only_ever_raise_arena_errors(frame: str | bytes) -> None:
    for decode in (decode_master, decode_slave):
        try:
            message = decode(frame)
        except ArenaError as error:
            assert error.code in EDGE_CODES
            assert error.message
            continue
        # Whatever got through is well typed: finite numbers only.
        data = getattr(message, "data", None)
        for joint in getattr(data, "joints", None) or []:
            assert math.isfinite(joint.value)


def generate(strategy: st.SearchStrategy[Any], count: int) -> list[Any]:
    """`count` examples of `strategy`, hypothesis-generated (edge cases included), in order.

    The server is started once per test: hypothesis drives the inputs, the test sends them.
    """
    found: list[Any] = []

    @settings(max_examples=count, deadline=None, database=None)
    @given(strategy)
    def collect(example: Any) -> None:
        found.append(example)

    collect()
    return found


async def test_fuzzed_master_frames(server: RunningServer) -> None:
    async with open_websocket_url(server.ws_url + "/ws/master/demo-arm?takeover=1") as master:
        await receive(master, "joint_states")
        before = intent(server)
        refused = 0
        for frame in generate(frames, 300):
            expected = predicted(frame, decode_master)
            if expected is None:
                continue  # valid by chance: not this test's business (and it would move things)
            await master.send_message(frame)
            error = await receive(master, "error")
            assert error["data"]["code"] == expected, frame
            assert intent(server) == before, frame
            refused += 1
        assert refused > 200
        # The connection and the robot still work. (Unstamped: a fuzzed frame that was a
        # command in all but its joints may have stamped this link's clock with any time, and
        # a stamp judged against it would be this client's own doing: STALE_COMMAND.)
        joints = [{"name": "Rotation", "value": 1}]
        await master.send_message(json.dumps({"type": "command", "data": {"joints": joints}}))
        reply = await receive(master, "ack")
        assert reply["data"]["status"] == "accepted", reply


async def test_fuzzed_slave_frames(server: RunningServer) -> None:
    before = intent(server)
    async with open_websocket_url(server.ws_url + "/ws/slave/demo-arm") as slave:
        for frame in generate(frames, 300):
            expected = predicted(frame, decode_slave)
            if expected is None:
                continue  # valid by chance (it may even carry a fault): not this test's business
            await slave.send_message(frame)
            error = await receive(slave, "error")
            assert error["data"]["code"] == expected, frame
            assert intent(server) == before, frame
    async with server.client() as http:
        assert (await http.get("/api/robots/demo-arm")).status_code == 200


REST_TARGETS = [
    ("POST", "/api/robots"),
    ("PUT", "/api/robots/demo-arm/joints"),
    ("POST", "/api/robots/demo-arm/slaves"),
    ("POST", "/api/robots/demo-arm/master"),
    ("POST", "/api/robots/demo-arm/estop"),
    ("POST", "/api/robots/demo-arm/calibration/start"),
    ("POST", "/api/robots/demo-arm/replay"),
]
rest_bodies = nearly_valid() | json_values.map(json.dumps) | st.text(max_size=50) | deep()


async def test_fuzzed_rest_bodies(server: RunningServer) -> None:
    async with server.client() as http:
        for (method, path), body in generate(
            st.tuples(st.sampled_from(REST_TARGETS), rest_bodies), 300
        ):
            before = intent(server)
            reply = await http.request(
                method, path, content=body, headers={"Content-Type": "application/json"}
            )
            assert reply.status_code < 500, (path, body, reply.text)
            answer = reply.json()
            if reply.status_code >= 400:
                assert answer["error"]["code"] and answer["error"]["message"]
                assert intent(server) == before, (path, body)
            elif path.endswith("/estop"):
                await http.post("/api/robots/demo-arm/reset")


def padded(size: int) -> str:
    return '{"type": "command", "data": {"joints": [], "pad": "' + "x" * size + '"}}'


async def test_multi_megabyte_frames_get_an_error(server: RunningServer) -> None:
    async with server.client() as http:
        before = (await http.get("/api/robots/demo-arm/joints")).json()
        async with open_websocket_url(
            server.ws_url + "/ws/master/demo-arm", max_message_size=64 << 20
        ) as master:
            await receive(master, "joint_states")
            await master.send_message(padded(3 << 20))
            assert (await receive(master, "error"))["data"]["code"] == "MESSAGE_TOO_LARGE"
            assert (await command(master, {"Rotation": 2}))["data"]["status"] == "accepted"
            with trio.fail_after(30):  # the move takes its trajectory's time
                while (after := (await http.get("/api/robots/demo-arm/joints")).json())[0][
                    "virtual_value"
                ] != pytest.approx(2.0):
                    await trio.sleep(0.01)  # only the valid command moved it
        assert [j["virtual_value"] for j in after[1:]] == [j["virtual_value"] for j in before[1:]]


async def test_a_frame_over_the_socket_cap_closes_it_and_the_master_is_lost(
    start_server: Callable[..., Awaitable[RunningServer]],
) -> None:
    server = await start_server(demo=True, heartbeat_interval=0.2, heartbeat_timeout=1.0)
    async with open_websocket_url(
        server.ws_url + "/ws/master/demo-arm", max_message_size=64 << 20
    ) as master:
        await receive(master, "joint_states")
        with pytest.raises(ConnectionClosed) as closed:
            # Over the server's 16 MiB cap: refused from the frame's header, so the close may
            # come while the client is still sending.
            await master.send_message(padded(17 << 20))
            await receive(master, "error")
        assert closed.value.reason.code == 1009  # MESSAGE_TOO_BIG
    robot = server.app.manager.get("demo-arm")
    # The connection is gone, so the master is lost (the loss policy applies).
    await eventually(lambda: robot.snapshot().master is None, what="the master's loss")
    async with server.client() as http:
        status = (await http.get("/api/robots/demo-arm")).json()
    assert status["state"] == "estopped" and "lost" in status["estop_reason"]


@pytest.mark.parametrize("depth", [10, 1000, 100_000])
def test_deep_nesting_is_refused_without_recursion_errors(depth: int) -> None:
    frame = '{"type": "command", "data": {"joints": ' + "[" * depth + "]" * depth + "}}"
    with pytest.raises(ArenaError) as caught:
        decode_master(frame)
    assert caught.value.code in EDGE_CODES


@pytest.mark.parametrize("role", ["viewer", "master"])
async def test_text_that_is_not_utf8_fails_the_connection(server: RunningServer, role: str) -> None:
    # RFC 6455 8.1: an endpoint that finds invalid UTF-8 in a text frame fails the connection;
    # the server says so with a 1007 close frame. The peer is let go at once: a viewer changes
    # nothing, a master is lost (loss policy).
    path = "/ws/robots/demo-arm/state" if role == "viewer" else "/ws/master/demo-arm"
    before = intent(server)
    raw = await RawWebSocket.connect(server.url, path)
    first = await raw.receive_frame()  # the state: the peer is in place
    assert first is not None and json.loads(first.payload)["type"] == "state"
    await raw.send_frame(OP_TEXT, b'{"type": "heartbeat", "x": "\xff\xfe\xc3\x28"}')
    with trio.fail_after(30):
        while (frame := await raw.receive_frame()) is not None and frame.opcode == OP_TEXT:
            pass  # what was sent before the bad frame
    assert frame is not None and frame.close_code == 1007, frame
    assert frame.payload[2:] == b"Text frames must be UTF-8."
    await raw.aclose()
    robot = server.app.manager.get("demo-arm")
    await eventually(lambda: robot.snapshot().owner is None, what="the peer's leaving")
    if role == "viewer":
        assert intent(server) == before
    else:
        assert str(robot.snapshot().mode) == "estopped"
        assert "lost" in (robot.snapshot().estop_reason or "")
    async with server.client() as http:
        await http.post("/api/robots/demo-arm/reset")
    async with open_websocket_url(server.ws_url + "/ws/master/demo-arm") as master:
        await receive(master, "joint_states")
        assert (await command(master, {"Rotation": 3}))["data"]["status"] == "accepted"
