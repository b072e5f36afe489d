"""`arena mcp --url URL [--api-key KEY]`: the robots of an Arena server as MCP tools over stdio,
with the official MCP Python SDK (the `mcp` extra). The SDK runs on anyio; here under trio (anyio's
trio backend), so the tools use Arena's own trio client in the same loop (specs/scripts.md).
"""

from __future__ import annotations

import functools
from collections.abc import Awaitable, Callable
from typing import Any, ParamSpec, TypeVar

import trio

try:
    from mcp.server.mcpserver import MCPServer
    from mcp.server.mcpserver.exceptions import ToolError
except ImportError:  # mcp before 2: FastMCP, the same decorator and stdio run (tests run 2.3)
    from mcp.server.fastmcp import FastMCP as MCPServer  # type: ignore[attr-defined,no-redef]
    from mcp.server.fastmcp.exceptions import ToolError  # type: ignore[import-not-found,no-redef]

from arena.client import AsyncArena
from arena.mcp.agent import Agent, AgentError

P = ParamSpec("P")
T = TypeVar("T")

INSTRUCTIONS = (
    "Arena's robots (robot arms). Joint values are degrees (the gripper 0-100 percent); "
    "positions are metres in the robot's base frame (x, y, z; z up), orientations quaternions "
    "(x, y, z, w). A move takes the robot as this agent's master: every rule of the server "
    "applies (joint limits, speed, the collision guard, e-stops) and a move another master "
    "holds is refused. Read the pose before moving the hand; move in small steps."
)


def _told(tool: Callable[P, Awaitable[T]]) -> Callable[P, Awaitable[T]]:
    """The agent's refusals as the tool's error, which the model reads."""

    @functools.wraps(tool)
    async def told(*args: P.args, **kwargs: P.kwargs) -> T:
        try:
            return await tool(*args, **kwargs)
        except AgentError as error:
            raise ToolError(str(error)) from None

    return told


def build(agent: Agent) -> MCPServer[Any]:
    """The MCP server with one tool per thing an agent does with a robot."""
    server: MCPServer[Any] = MCPServer("arena", instructions=INSTRUCTIONS)

    @server.tool()
    @_told
    async def list_robots() -> dict[str, Any]:
        """Every robot: id, name, type, safety state (idle, mastered, estopped...), master."""
        return {"robots": await agent.list_robots()}

    @server.tool()
    @_told
    async def read_joints(robot_id: str) -> dict[str, Any]:
        """Each joint's commanded and measured value (degrees; gripper percent) and limits."""
        return await agent.read_joints(robot_id)

    @server.tool()
    @_told
    async def read_pose(robot_id: str) -> dict[str, Any]:
        """The hand's pose, measured and commanded: position (m), orientation, gripper."""
        return await agent.read_pose(robot_id)

    @server.tool()
    @_told
    async def move_joints(
        robot_id: str, joints: dict[str, float], duration: float | None = None
    ) -> dict[str, Any]:
        """Move the named joints to these values (degrees; the gripper 0-100) over `duration`
        seconds (default: as fast as the limits allow). Answers when the move is over."""
        return await agent.move_joints(robot_id, joints, duration)

    @server.tool()
    @_told
    async def move_to_pose(
        robot_id: str,
        position: list[float],
        orientation: list[float] | None = None,
        gripper: float | None = None,
        duration: float | None = None,
    ) -> dict[str, Any]:
        """Move the hand's tool point to `position` [x, y, z] metres in the base frame,
        turned to `orientation` [qx, qy, qz, qw] if given (5-joint arms: leave it out).
        UNREACHABLE says how near the arm can get. Answers when the move is over."""
        return await agent.move_to_pose(robot_id, position, orientation, gripper, duration)

    @server.tool()
    @_told
    async def plan_move(
        robot_id: str,
        joints: dict[str, float] | None = None,
        position: list[float] | None = None,
        orientation: list[float] | None = None,
    ) -> dict[str, Any]:
        """Move to a joint goal or a hand position along a path planned around obstacles,
        where the server plans moves (else it says so)."""
        return await agent.plan_move(robot_id, joints, position, orientation)

    @server.tool()
    @_told
    async def gripper(robot_id: str, action: str | float) -> dict[str, Any]:
        """Open or close the gripper: `open`, `close`, or a value 0-100."""
        return await agent.gripper(robot_id, action)

    @server.tool()
    @_told
    async def release(robot_id: str) -> dict[str, Any]:
        """Hand the robot back (it holds where it is) so that others may drive it."""
        return await agent.release(robot_id)

    @server.tool()
    @_told
    async def estop(robot_id: str, reason: str = "") -> dict[str, Any]:
        """Emergency stop: the robot stops at once and refuses moves until a person resets
        it."""
        return await agent.estop(robot_id, reason)

    return server


async def serve(url: str, api_key: str | None = None, name: str = "mcp-agent") -> None:
    """Serve the robots at `url` over stdio until the client closes it."""
    async with AsyncArena(url, api_key) as arena, trio.open_nursery() as nursery:
        agent = Agent(arena, url, api_key, nursery, name)
        await build(agent).run_stdio_async()
        for robot_id in list(agent.held):
            with trio.move_on_after(5):
                await agent.release(robot_id)
        nursery.cancel_scope.cancel()


def run(url: str, api_key: str | None = None, name: str = "mcp-agent") -> None:
    """`serve` under trio (the SDK's anyio finds trio running and uses its backend)."""
    trio.run(serve, url, api_key, name)
