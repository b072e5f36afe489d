"""WebSockets for robots of other nodes of the fleet, over `fleet.tunnel`: the client's node
checks the key or token and carries the connection (`proxy`); the robot's node serves it with
its own endpoints (`serve_tunnel`), as the caller the client's node sent, whose tenant and
scope it checks again."""

from __future__ import annotations

from typing import Any

import trio

from arena.fleet import tunnel as tunnels
from arena.fleet.node import FleetNode
from arena.protocol.errors import ArenaError, ErrorCode
from arena.server.base import ArenaApp
from arena.server.identity import Principal
from arena.server.ws.backpressure import Encoded
from arena.server.ws.connection import Connection
from arena.server.ws.endpoints import serve_role


def kind_of(text: str) -> str:
    """The `type` of a message (encoded with `type` first), for latest-wins toward a slow
    client; anything else counts as rare."""
    if text.startswith('{"type":"'):
        end = text.find('"', 9)
        if end > 0:
            return text[9:end]
    return ""


def serve_tunnel(app: ArenaApp, fleet: FleetNode, call: dict[str, Any]) -> dict[str, Any]:
    """Serve a client of another node: the robot must be here; the connection runs as if
    the client had connected to this node, as the caller that node sent."""
    app.manager.get(str(call["robot"]))  # UNKNOWN_ROBOT if it is not here (any more)
    try:
        open_server = not app.arena_config.auth_enabled
        caller = Principal.of_wire(call.get("caller"), open_server=open_server)
    except ValueError as exc:
        raise ArenaError(
            ErrorCode.UNAUTHORIZED, f"The carried caller is not valid: {exc}."
        ) from None

    async def serve(socket: tunnels.TunnelSocket, role: str, robot_id: str) -> None:
        connection = Connection(app, socket, role)
        connection.principal = caller
        await serve_role(connection, robot_id)

    return tunnels.serve_tunnel(fleet, call, serve)


async def proxy(connection: Connection, robot_id: str, node: str) -> None:
    """A client of this node for a robot of `node`: carry its connection there."""
    fleet = connection.app.fleet
    assert fleet is not None
    if not await connection.authorized():
        return
    if not connection.sees(robot_id):
        await connection.refuse(
            ArenaError(ErrorCode.UNKNOWN_ROBOT, f"No robot with id {robot_id!r}.")
        )
        return
    try:
        tunnel = await tunnels.open_to(
            fleet, node, robot_id, connection.role, connection.args, connection.principal.to_wire()
        )
    except ArenaError as error:
        await connection.refuse(error)
        return

    async def deliver(text: str) -> None:
        await connection.send(Encoded(kind_of(text), text))

    async def body(nursery: trio.Nursery) -> None:
        await tunnels.carry(connection, tunnel, robot_id, deliver, nursery)

    try:
        await connection.run(body)
    finally:
        tunnel.close()
