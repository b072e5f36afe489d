"""Arena's own WebSocket transport: the frame codec alone, then the real server on loopback."""

from __future__ import annotations

import json
import os
import struct
from collections.abc import Awaitable, Callable

import httpx
import pytest
import trio
import trio.testing

from arena.protocol import ws_frames
from arena.protocol.ws_frames import (
    OP_BINARY,
    OP_CLOSE,
    OP_CONTINUATION,
    OP_PING,
    OP_PONG,
    OP_TEXT,
    FrameParser,
    ProtocolViolation,
    UpgradeRequest,
    WebSocketClosed,
)
from arena.server import ws_transport
from arena.server.read_poller import ReadPoller
from arena.server.ws_transport import WebSocket
from tests.conftest import RunningServer, eventually
from tests.raw_websocket import RawWebSocket


def client_frame(
    opcode: int, payload: bytes, *, fin: bool = True, masked: bool = True, rsv: int = 0
) -> bytes:
    """A frame as a client would send it, or as a broken client might."""
    frame = ws_frames.encode_frame(opcode, payload, mask=os.urandom(4) if masked else None, fin=fin)
    return bytes([frame[0] | rsv]) + frame[1:]


def text_payloads(data: bytes) -> list[bytes]:
    """The payloads of the server's (unmasked) text frames in `data`."""
    payloads = []
    while data:
        opcode, payload, used = ws_frames.split_unmasked(data)  # type: ignore[misc]
        assert opcode == OP_TEXT
        payloads.append(payload)
        data = data[used:]
    return payloads


def parse_all(parser: FrameParser, data: bytes) -> list[ws_frames.Message]:
    parser.feed(data)
    messages = []
    while (message := parser.next()) is not None:
        messages.append(message)
    return messages


# --- the codec -------------------------------------------------------------------------------


def test_accept_key_matches_the_rfc_example() -> None:
    assert ws_frames.accept_key("dGhlIHNhbXBsZSBub25jZQ==") == "s3pPLMBiTxaQ9kYGzzhZRbK+xOo="
    assert ws_frames.valid_client_key("dGhlIHNhbXBsZSBub25jZQ==")
    assert not ws_frames.valid_client_key("c2hvcnQ=")  # 5 bytes
    assert not ws_frames.valid_client_key("not base64!")


@pytest.mark.parametrize("size", [0, 1, 125, 126, 65535, 65536, 70_000])
def test_every_length_form_parses_fed_whole_or_a_byte_at_a_time(size: int) -> None:
    payload = bytes(i % 251 for i in range(size))
    data = client_frame(OP_BINARY, payload) + client_frame(OP_TEXT, b"next")
    whole = parse_all(FrameParser(1 << 20), data)
    assert [(m.opcode, m.payload) for m in whole] == [(OP_BINARY, payload), (OP_TEXT, b"next")]
    if size <= 126:  # byte by byte: the parser waits for each header form and payload
        parser = FrameParser(1 << 20)
        trickled = [m for byte in data for m in parse_all(parser, bytes([byte]))]
        assert [(m.opcode, m.payload) for m in trickled] == [
            (OP_BINARY, payload),
            (OP_TEXT, b"next"),
        ]


def test_the_size_cap_is_per_message_not_per_connection() -> None:
    # Many messages that add up to far more than the cap all pass.
    parser = FrameParser(1000)
    frame = client_frame(OP_TEXT, b"x" * 900)
    for _ in range(50):
        assert [m.payload for m in parse_all(parser, frame)] == [b"x" * 900]


def test_fragments_are_joined_and_control_frames_come_between() -> None:
    data = (
        client_frame(OP_TEXT, b"hel", fin=False)
        + client_frame(OP_PING, b"p")
        + client_frame(OP_CONTINUATION, b"lo ", fin=False)
        + client_frame(OP_CONTINUATION, b"arm")
    )
    messages = parse_all(FrameParser(100), data)
    assert [(m.opcode, m.payload) for m in messages] == [(OP_PING, b"p"), (OP_TEXT, b"hello arm")]


@pytest.mark.parametrize(
    ("data", "code"),
    [
        (client_frame(OP_TEXT, b"hi", masked=False), 1002),
        (client_frame(OP_TEXT, b"hi", rsv=0x40), 1002),  # no extension was agreed
        (client_frame(0x3, b"hi"), 1002),  # a reserved opcode
        (client_frame(OP_PING, b"x" * 126), 1002),
        (client_frame(OP_PING, b"x", fin=False), 1002),
        (client_frame(OP_CONTINUATION, b"x"), 1002),
        (client_frame(OP_TEXT, b"a", fin=False) + client_frame(OP_TEXT, b"b"), 1002),
        (client_frame(OP_TEXT, b"x" * 101), 1009),
        (
            client_frame(OP_TEXT, b"x" * 60, fin=False) + client_frame(OP_CONTINUATION, b"y" * 41),
            1009,
        ),
    ],
)
def test_protocol_violations_fail_with_the_rfc_code(data: bytes, code: int) -> None:
    with pytest.raises(ProtocolViolation) as violation:
        parse_all(FrameParser(100), data)
    assert violation.value.code == code
    assert violation.value.reason.endswith(".")


def test_close_frames_are_read_and_checked() -> None:
    assert ws_frames.parse_close(b"") == (1005, "")
    assert ws_frames.parse_close(struct.pack("!H", 4000) + b"bye") == (4000, "bye")
    for bad in (b"\x03", struct.pack("!H", 1005), struct.pack("!H", 999), struct.pack("!H", 2000)):
        with pytest.raises(ProtocolViolation):
            ws_frames.parse_close(bad)
    # Our own close frames fit a control frame even with a long reason.
    frame = ws_frames.encode_close(1000, "é" * 200)
    assert frame[1] <= 125 and frame[4:].decode("utf-8")


# --- on the real server ----------------------------------------------------------------------


async def _first_text(raw: RawWebSocket) -> dict[str, object]:
    frame = await raw.receive_frame()
    assert frame is not None and frame.opcode == OP_TEXT
    return json.loads(frame.payload)  # type: ignore[no-any-return]


async def test_pings_are_answered_with_their_payload(server: RunningServer) -> None:
    raw = await RawWebSocket.connect(server.url, "/ws/robots/demo-arm/state")
    await _first_text(raw)
    await raw.send_frame(OP_PING, b"are you there")
    with trio.fail_after(30):
        while (frame := await raw.receive_frame()) is not None and frame.opcode != OP_PONG:
            pass
    assert frame is not None and frame.payload == b"are you there"
    await raw.aclose()


async def test_a_ping_flood_from_a_peer_that_never_reads_is_bounded_and_slows_no_one(
    server: RunningServer,
) -> None:
    # A viewer with a 4 KiB receive buffer sends pings as fast as it can and reads nothing:
    # the server keeps only the newest pong it owes, other clients are answered meanwhile,
    # and when the flooder reads again it gets the pong of its newest ping.
    flooder = await RawWebSocket.connect(server.url, "/ws/robots/demo-arm/state", 4096)
    highest = 0
    sent = 0
    async with server.client() as http:
        for _ in range(40):
            burst = b"".join(
                client_frame(OP_PING, struct.pack("!I", sent + i)) for i in range(1000)
            )
            sent += 1000
            await flooder.stream.send_all(burst)
            # Another client is answered while the flood goes on.
            assert (await http.post("/api/robots/demo-arm/estop")).status_code == 200
            assert (await http.post("/api/robots/demo-arm/reset")).status_code == 200
            highest = max([highest, *(c.ws.queued_bytes for c in server.app.connections)])
    flooding = next(c for c in server.app.connections if c.role == "viewer")
    assert flooding.ws.pongs_dropped > 0
    assert highest < 64 * 1024, highest
    pongs = 0
    with trio.fail_after(10):
        while True:
            frame = await flooder.receive_frame()
            assert frame is not None
            if frame.opcode == OP_PONG:
                pongs += 1
                if frame.payload == struct.pack("!I", sent - 1):
                    break
    assert pongs < sent
    await flooder.aclose()


async def test_control_frames_count_toward_the_readers_fair_share() -> None:
    # A thousand pings in hand before a text frame: reading through them lets other tasks run.
    left, _right = trio.testing.memory_stream_pair()
    ws = WebSocket(left, UpgradeRequest("/"), max_message=1024)
    ws.feed(b"".join(client_frame(OP_PING, b"") for _ in range(1000)))
    ws.feed(client_frame(OP_TEXT, b"after the pings"))
    turns = 0

    async def other() -> None:
        nonlocal turns
        while True:
            turns += 1
            await trio.lowlevel.checkpoint()

    async with trio.open_nursery() as nursery:
        nursery.start_soon(other)
        await trio.lowlevel.checkpoint()  # it has started
        turns = 0
        assert await ws.receive() == "after the pings"
        nursery.cancel_scope.cancel()
    assert turns >= 1000 // 32 - 1, turns


def test_text_frames_are_made_right_even_when_the_same_text_repeats_or_is_empty() -> None:
    # Sent texts are framed with a one-entry cache (the acks of a burst share one text).
    texts = ("", "ack", "ack", "")
    assert text_payloads(ws_transport._frames(texts)) == [text.encode() for text in texts]


async def test_frames_in_hand_are_taken_without_waiting_up_to_the_fair_share() -> None:
    # A reader takes the rest of a burst at once (and answers it in one write), but no more
    # frames in a row than it may before letting other tasks run.
    left, _right = trio.testing.memory_stream_pair()
    ws = WebSocket(left, UpgradeRequest("/"), max_message=1024)
    ws.feed(b"".join(client_frame(OP_TEXT, str(n).encode()) for n in range(40)))
    taken = [await ws.receive()]
    while (message := ws.next_in_hand()) is not None:
        taken.append(message)
    assert taken == [str(n) for n in range(32)]
    assert await ws.receive() == "32"  # after a checkpoint
    assert ws.next_in_hand() == "33"


async def test_the_answers_to_frames_taken_together_go_out_at_once_even_with_more_in_hand() -> None:
    # A reader answering what it took together writes it itself (no hop to the writer task);
    # a single answer while more frames wait in hand is kept to go out with theirs.
    mine, theirs = trio.socket.socketpair()
    ws = WebSocket(trio.SocketStream(mine), UpgradeRequest("/"), max_message=1024)
    ws.feed(b"".join(client_frame(OP_TEXT, str(n).encode()) for n in range(3)))
    assert await ws.receive() == "0" and ws.holds_more()
    assert ws.offer("one answer")
    assert ws.queued_bytes > 0  # kept, with frames still in hand
    ws2 = WebSocket(trio.SocketStream(mine), UpgradeRequest("/"), max_message=1024)
    ws2.feed(b"".join(client_frame(OP_TEXT, str(n).encode()) for n in range(3)))
    assert await ws2.receive() == "0" and ws2.holds_more()
    assert ws2.offer("all", "answers", whole=True)
    assert ws2.queued_bytes == 0
    assert text_payloads(await theirs.recv(1024)) == [b"all", b"answers"]
    mine.close()
    theirs.close()


async def test_a_close_in_hand_is_answered_after_what_came_before_it() -> None:
    # The close frame that answers the peer's close (or a violation) goes out only with the
    # reader's next receive, after the answers to the frames taken before it.
    left, _right = trio.testing.memory_stream_pair()
    ws = WebSocket(left, UpgradeRequest("/"), max_message=1024)
    ws.feed(client_frame(OP_TEXT, b"before"))
    ws.feed(client_frame(OP_CLOSE, struct.pack("!H", 1000)))
    ws.feed(client_frame(OP_TEXT, b"after the close"))
    assert await ws.receive() == "before"
    assert ws.next_in_hand() is None
    assert not ws.close_sent  # the reader still answers "before"
    with pytest.raises(WebSocketClosed) as closed:
        await ws.receive()
    assert closed.value.code == 1000 and ws.close_sent

    ws = WebSocket(left, UpgradeRequest("/"), max_message=1024)
    ws.feed(client_frame(OP_TEXT, b"before"))
    ws.feed(client_frame(OP_TEXT, b"x" * 2000))  # over the cap: a violation
    assert await ws.receive() == "before"
    assert ws.next_in_hand() is None and not ws.close_sent
    with pytest.raises(WebSocketClosed) as closed:
        await ws.receive()
    assert closed.value.code == ws_frames.CLOSE_TOO_BIG and ws.close_sent


async def test_a_fragmented_command_is_one_command(server: RunningServer) -> None:
    raw = await RawWebSocket.connect(server.url, "/ws/master/demo-arm")
    await _first_text(raw)
    text = json.dumps({"type": "command", "data": {"joints": [{"name": "Rotation", "value": 4}]}})
    half = len(text) // 2
    await raw.stream.send_all(
        client_frame(OP_TEXT, text[:half].encode(), fin=False)
        + client_frame(OP_CONTINUATION, text[half:].encode())
    )
    with trio.fail_after(30):
        while (message := await _first_text(raw))["type"] != "ack":
            pass
    assert message["data"]["status"] in ("accepted", "clamped")  # type: ignore[index]
    await raw.aclose()


async def test_a_frame_that_arrives_in_pieces_is_read_whole(server: RunningServer) -> None:
    # After each piece the server has read all there was (a short read) and waits for the
    # next edge: no piece may be left unread.
    raw = await RawWebSocket.connect(server.url, "/ws/master/demo-arm")
    await _first_text(raw)
    text = json.dumps({"type": "command", "data": {"joints": [{"name": "Rotation", "value": 3}]}})
    frame = client_frame(OP_TEXT, text.encode())
    for start in range(0, len(frame), 7):
        await raw.stream.send_all(frame[start : start + 7])
        await trio.testing.wait_all_tasks_blocked()
    with trio.fail_after(30):
        while (message := await _first_text(raw))["type"] != "ack":
            pass
    assert message["data"]["status"] in ("accepted", "clamped")  # type: ignore[index]
    await raw.aclose()


@pytest.mark.skipif(not ReadPoller.available(), reason="epoll is Linux only")
async def test_the_servers_websocket_reads_wait_on_its_poller_which_forgets_them_at_the_end(
    start_server: Callable[..., Awaitable[RunningServer]], monkeypatch: pytest.MonkeyPatch
) -> None:
    # Every other test would pass as well with reads waiting on trio: this one says the
    # listener hands its poller to the transport and lets go of each socket before closing it.
    waited: list[int] = []
    forgotten: list[int] = []
    wait_readable, forget = ReadPoller.wait_readable, ReadPoller.forget

    async def noting_wait(poller: ReadPoller, sock: trio.socket.SocketType) -> None:
        waited.append(sock.fileno())
        await wait_readable(poller, sock)

    def noting_forget(poller: ReadPoller, sock: trio.socket.SocketType) -> None:
        forgotten.append(sock.fileno())
        forget(poller, sock)

    monkeypatch.setattr(ReadPoller, "wait_readable", noting_wait)
    monkeypatch.setattr(ReadPoller, "forget", noting_forget)
    server = await start_server(demo=True)
    raw = await RawWebSocket.connect(server.url, "/ws/master/demo-arm")
    await _first_text(raw)
    command = {"type": "command", "data": {"joints": [{"name": "Rotation", "value": 2}]}}
    await raw.stream.send_all(client_frame(OP_TEXT, json.dumps(command).encode()))
    with trio.fail_after(30):
        while (await _first_text(raw))["type"] != "ack":
            pass
    assert waited, "the master's reads never waited on the poller"
    await raw.aclose()
    await eventually(lambda: bool(forgotten), what="the poller forgetting the socket")
    assert set(waited) == set(forgotten)


async def test_a_client_close_is_echoed_and_a_master_leaves(server: RunningServer) -> None:
    raw = await RawWebSocket.connect(server.url, "/ws/master/demo-arm?id=polite")
    await _first_text(raw)
    await raw.send_frame(OP_CLOSE, struct.pack("!H", 1000) + b"done")
    with trio.fail_after(30):
        while (frame := await raw.receive_frame()) is not None and frame.opcode != OP_CLOSE:
            pass
        assert frame is not None and frame.close_code == 1000
        assert await raw.receive_frame() is None  # then the server closes the TCP connection
    robot = server.app.manager.get("demo-arm")
    await eventually(lambda: robot.snapshot().master is None, what="the master's leaving")
    await raw.aclose()


async def test_an_unmasked_frame_fails_the_connection_with_1002(server: RunningServer) -> None:
    raw = await RawWebSocket.connect(server.url, "/ws/robots/demo-arm/state")
    await _first_text(raw)
    await raw.stream.send_all(client_frame(OP_TEXT, b'{"type":"heartbeat"}', masked=False))
    with trio.fail_after(30):
        while (frame := await raw.receive_frame()) is not None and frame.opcode == OP_TEXT:
            pass
    assert frame is not None and frame.close_code == 1002
    assert b"masked" in frame.payload
    await raw.aclose()


async def _handshake(server: RunningServer, request: str) -> bytes:
    host, port = server.url.split("//")[1].rsplit(":", 1)
    stream = await trio.open_tcp_stream(host, int(port))
    await stream.send_all(request.encode())
    answer = b""
    with trio.fail_after(30):
        while chunk := await stream.receive_some(65536):
            answer += chunk
            if b"\r\n\r\n" in answer and b"Content-Length" not in answer.split(b"\r\n\r\n")[0]:
                break
            head, _, body = answer.partition(b"\r\n\r\n")
            length = [ln for ln in head.split(b"\r\n") if ln.lower().startswith(b"content-length")]
            if length and len(body) >= int(length[0].split(b":")[1]):
                break
    await stream.aclose()
    return answer


async def test_a_bad_handshake_gets_a_json_400(server: RunningServer) -> None:
    answer = await _handshake(
        server,
        "GET /ws/master/demo-arm HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: websocket\r\n"
        "Connection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n"
        "Sec-WebSocket-Version: 8\r\n\r\n",
    )
    head, _, body = answer.partition(b"\r\n\r\n")
    assert head.startswith(b"HTTP/1.1 400")
    error = json.loads(body)["error"]
    assert error["code"] == "INVALID_MESSAGE" and "version 13" in error["message"]
    robot = server.app.manager.get("demo-arm")
    assert robot.snapshot().master is None  # nothing was claimed


async def test_other_paths_and_plain_gets_still_reach_the_http_app(server: RunningServer) -> None:
    async with httpx.AsyncClient(base_url=server.url) as http:
        # /ws/ without an upgrade is ordinary HTTP: the app's JSON 404.
        plain = await http.get("/ws/master/demo-arm")
        assert plain.status_code == 404 and plain.json()["error"]["code"] == "NOT_FOUND"
        assert (await http.get("/api/robots")).status_code == 200
    with pytest.raises(ConnectionError):  # an upgrade to a path with no endpoint is refused
        await RawWebSocket.connect(server.url, "/ws/nothing-here")
