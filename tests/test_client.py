"""arena.client from a plain script (blocking REST in a thread) and its error reporting."""

from __future__ import annotations

import pytest
import trio

from arena.client import Arena, ArenaClientError, ViewerSession, messages
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
