"""`arena mcp` (specs/scripts.md): the robots of a real server as MCP tools, listed and called
by the official SDK's own client (`mcp.client.stdio`) over the stdio of `arena mcp` in a
process of its own, with an API key; the agent is a master under every rule."""

from __future__ import annotations

import json
import math
import os
import sys
from collections.abc import AsyncIterator, Awaitable, Callable
from contextlib import asynccontextmanager
from typing import Any

import pytest
import trio

from tests.conftest import REPOSITORY, RunningServer, need

Start = Callable[..., Awaitable[RunningServer]]
KEY = "agent-key"
#: Bounds on waits only a broken feature reaches (the process imports the SDK: a few seconds).
WAIT = 60.0

TOOLS = {
    "list_robots",
    "read_joints",
    "read_pose",
    "move_joints",
    "move_to_pose",
    "plan_move",
    "gripper",
    "release",
    "estop",
}


@asynccontextmanager
async def agent(server: RunningServer, *args: str) -> AsyncIterator[Any]:
    """The SDK's client session with `arena mcp --url ... --api-key ...` as its server."""
    need("mcp", "mcp")
    from mcp.client.session import ClientSession
    from mcp.client.stdio import StdioServerParameters, stdio_client

    environment = {"PYTHONPATH": str(REPOSITORY), "PATH": os.environ.get("PATH", "")}
    command = ["-m", "arena", "mcp", "--url", server.url, "--api-key", KEY, *args]
    params = StdioServerParameters(command=sys.executable, args=command, env=environment)
    async with stdio_client(params) as (read, write), ClientSession(read, write) as session:
        with trio.fail_after(WAIT):
            await session.initialize()
        yield session


async def call(session: Any, tool: str, **arguments: Any) -> Any:
    """The tool's answer as JSON; AssertionError with its text if it is an error."""
    with trio.fail_after(WAIT):
        result = await session.call_tool(tool, arguments)
    text = "".join(part.text for part in result.content)
    assert not result.is_error, text
    return json.loads(text)


async def refused(session: Any, tool: str, **arguments: Any) -> str:
    """The error text of a tool call that must fail."""
    with trio.fail_after(WAIT):
        result = await session.call_tool(tool, arguments)
    assert result.is_error
    text = "".join(part.text for part in result.content)
    prefix = f"Error executing tool {tool}: "  # (the SDK's words before the tool's own)
    return text.removeprefix(prefix)


async def test_the_sdks_client_lists_and_calls_the_tools_and_the_agent_is_a_master(
    start_server: Start,
) -> None:
    server = await start_server(demo=True, api_keys=(KEY,))
    robot = server.app.manager.get("demo-arm")
    async with agent(server) as session:
        listed = await session.list_tools()
        assert {tool.name for tool in listed.tools} == TOOLS
        assert all(tool.description for tool in listed.tools)

        (arm,) = (await call(session, "list_robots"))["robots"]
        assert arm["id"] == "demo-arm" and arm["robot_type"] == "so-arm100"
        assert arm["held_by_this_agent"] is False
        joints = await call(session, "read_joints", robot_id="demo-arm")
        assert set(joints["joints"]) == {j.name for j in robot.model.joints}
        pose = await call(session, "read_pose", robot_id="demo-arm")
        start = pose["commanded"]["position"]

        # The hand 3 cm up: solved and checked by the server, the agent its master meanwhile.
        wanted = [start[0], start[1], start[2] + 0.03]
        moved = await call(session, "move_to_pose", robot_id="demo-arm", position=wanted)
        assert moved["status"] == "accepted" and moved["finished"] is True
        master = robot.snapshot().master
        assert master is not None and master.peer_id == "mcp-agent"
        after = await call(session, "read_pose", robot_id="demo-arm")
        assert math.dist(after["commanded"]["position"], wanted) < 0.001

        moved = await call(session, "move_joints", robot_id="demo-arm", joints={"Rotation": 12})
        assert moved["finished"] is True and moved["joints"]["Rotation"] == pytest.approx(12)
        closed = await call(session, "gripper", robot_id="demo-arm", action="close")
        jaw = robot.model.joint("Jaw")
        assert jaw is not None and closed["joints"]["Jaw"] == pytest.approx(jaw.lower, abs=0.01)
        half = await call(session, "gripper", robot_id="demo-arm", action=10)
        assert half["joints"]["Jaw"] == pytest.approx(10, abs=0.01)

        # Every rule applies: a joint past its limit is clamped, a far pose is unreachable;
        # a planned move where the server plans (else it says it does not).
        clamped = await call(session, "move_joints", robot_id="demo-arm", joints={"Rotation": 999})
        assert clamped["status"] == "clamped"
        far = await refused(session, "move_to_pose", robot_id="demo-arm", position=[3, 0, 0])
        assert far.startswith("UNREACHABLE: ")
        from arena.protocol import messages

        if hasattr(messages, "MoveMessage"):  # a server with planned moves (issue 58's)
            planned = await call(session, "plan_move", robot_id="demo-arm", joints={"Rotation": 0})
            assert planned["finished"] is True
            assert planned["joints"]["Rotation"] == pytest.approx(0, abs=0.1)
        else:
            plan = await refused(session, "plan_move", robot_id="demo-arm", joints={"Rotation": 0})
            assert plan.startswith("NOT_INSTALLED: this server plans no moves")

        stopped = await call(session, "estop", robot_id="demo-arm", reason="agent test")
        assert stopped["state"] == "estopped"
        assert robot.snapshot().estop_reason == "agent test"
        moving = await refused(session, "move_joints", robot_id="demo-arm", joints={"Pitch": 5})
        assert moving.startswith("ESTOPPED: ")


async def test_the_agent_takes_no_robot_another_master_holds_and_releases_what_it_holds(
    start_server: Start,
) -> None:
    server = await start_server(demo=True, api_keys=(KEY,))
    robot = server.app.manager.get("demo-arm")
    async with server.client(headers={"Authorization": f"Bearer {KEY}"}) as http:
        body = {"type": "mock-sequence", "sequences": ["gentle-wave"], "loop": True}
        assert (await http.post("/api/robots/demo-arm/master", json=body)).status_code == 201
    async with agent(server) as session:
        taken = await refused(session, "move_joints", robot_id="demo-arm", joints={"Pitch": 5})
        assert taken.startswith("MASTER_ACTIVE: ")
        async with server.client(headers={"Authorization": f"Bearer {KEY}"}) as http:
            assert (await http.delete("/api/robots/demo-arm/master")).status_code == 200
        moved = await call(session, "move_joints", robot_id="demo-arm", joints={"Pitch": 5})
        assert moved["finished"] is True
        assert (await call(session, "release", robot_id="demo-arm"))["released"] is True
        assert robot.snapshot().master is None
        unknown = await refused(session, "read_pose", robot_id="nobody")
        assert unknown.startswith("UNKNOWN_ROBOT: ")


async def test_without_the_key_the_agent_reads_and_moves_nothing(start_server: Start) -> None:
    server = await start_server(demo=True, api_keys=("another-key",))
    async with agent(server) as session:
        answer = await refused(session, "list_robots")
        assert answer == "FORBIDDEN: That API key is not valid here."
        moved = await refused(session, "move_joints", robot_id="demo-arm", joints={"Pitch": 5})
        assert moved.startswith("FORBIDDEN: ")
    assert server.app.manager.get("demo-arm").snapshot().master is None


def test_without_the_sdk_arena_mcp_says_what_to_install(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from arena import cli

    monkeypatch.setitem(sys.modules, "mcp", None)  # (an import of it raises ImportError)
    assert cli.main(["mcp", "--url", "http://127.0.0.1:9"]) == 2
    said = capsys.readouterr().err
    assert said.startswith("arena mcp: NOT_INSTALLED: arena mcp needs the MCP Python SDK (mcp)")
    assert "-m pip install 'arena[mcp]'" in said
