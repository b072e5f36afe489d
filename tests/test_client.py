"""arena.client from a plain script (blocking REST in a thread) and its error reporting."""

from __future__ import annotations

import pytest
import trio

from arena.client import Arena, ArenaClientError, ViewerSession, handshake, messages
from arena.protocol.messages import decode_master, decode_slave, encode
from tests.conftest import RunningServer


def script(url: str) -> list[str]:
    """What a plain script does: no trio, no async."""
    seen = []
    with Arena(url) as arena:
        arena.create_robot("scripted")
        arena.attach_slave("scripted", {"type": "mock-slave"})
        arena.set_joints("scripted", {"Rotation": 10})
        seen.append(arena.robot("scripted")["state"])
        arena.estop("scripted", "script says stop")
        seen.append(arena.robot("scripted")["state"])
        try:
            arena.set_joints("scripted", {"Rotation": 11})
        except ArenaClientError as error:
            seen.append(f"{error.status} {error.code}")
        arena.reset("scripted")
        seen.append(arena.robot("scripted")["state"])
    return seen


async def test_a_plain_script_drives_a_robot(server: RunningServer) -> None:
    seen = await trio.to_thread.run_sync(script, server.url)
    assert seen == ["idle", "estopped", "423 ESTOPPED", "idle"]


async def test_a_viewer_session_follows_the_robot(server: RunningServer) -> None:
    async with ViewerSession.open(server.url, "demo-arm") as viewer:
        async with server.client() as http:
            answer = await http.put(
                "/api/robots/demo-arm/joints", json={"joints": [{"name": "Jaw", "value": 5}]}
            )
            assert answer.status_code == 200
        await viewer.wait_for(lambda v: v.joints.get("Jaw", {}).get("real_value") == 5)


def test_an_unreachable_server_is_an_arena_error_too() -> None:
    with Arena("http://127.0.0.1:9") as arena, pytest.raises(ArenaClientError) as raised:
        arena.robots()
    assert raised.value.code == "UNREACHABLE"


def test_the_clients_messages_are_the_protocols_own() -> None:
    """What a client sends is made of the protocol's structs: the server's decoders read each
    back as it was made."""
    command = messages.command({"Rotation": 1, "Elbow": -2.5}, duration=300, metadata={"a": 1})
    assert decode_master(encode(command)) == command
    for message in (messages.heartbeat(), messages.estop("why"), messages.reset()):
        assert decode_master(encode(message)) == message
    release = messages.release()
    assert decode_master(encode(release)) == release
    report = messages.joint_states({"Rotation": 1.5})
    assert decode_slave(encode(report)) == report
    assert messages.command_message({"Rotation": 1})["data"]["joints"] == [
        {"name": "Rotation", "value": 1.0}
    ]
    with pytest.raises(ValueError, match="'Rotation'"):
        messages.joint_states({"Rotation": float("nan")})


def test_the_raw_clients_handshake_is_checked_both_ways() -> None:
    """The handshake the lean and raw clients share: a request a server reads, answers told
    apart (101 or a refusal), the first frames kept."""
    request = handshake.upgrade_request("127.0.0.1", 8080, "/ws/slave/arm?id=a", key="k==")
    lines = request.decode().split("\r\n")
    assert lines[0] == "GET /ws/slave/arm?id=a HTTP/1.1" and "Host: 127.0.0.1:8080" in lines
    assert "Sec-WebSocket-Key: k==" in lines and request.endswith(b"\r\n\r\n")
    assert handshake.split_answer(b"HTTP/1.1 101 Switching Protocols\r\nUpgrade: w") is None
    head, rest = handshake.split_answer(b"HTTP/1.1 101 OK\r\nA: b\r\n\r\n\x81\x00") or ((), b"")
    assert head == b"HTTP/1.1 101 OK\r\nA: b" and rest == b"\x81\x00"
    assert handshake.refusal(head) is None
    assert handshake.refusal(b"HTTP/1.1 403 Forbidden\r\nX: 101") == "HTTP/1.1 403 Forbidden"
    assert handshake.refusal(b"") == "no answer"
