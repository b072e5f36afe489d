"""Which endpoint serves a WebSocket: by its path, for a robot of this node or, carried
through the fleet, of the node that owns it."""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from functools import partial

from arena.protocol.errors import ArenaError, ErrorCode
from arena.protocol.ws_frames import UpgradeRequest
from arena.server.base import ArenaApp
from arena.server.listener import WebSocketHandler
from arena.server.ws.connection import Connection
from arena.server.ws.endpoints import ENDPOINTS, PEER_ROLES
from arena.server.ws.fleet import proxy
from arena.server.ws_transport import WebSocket


def router(app: ArenaApp) -> Callable[[UpgradeRequest], WebSocketHandler | None]:
    """The WebSocket endpoints by path (None for any other path)."""

    def route(request: UpgradeRequest) -> WebSocketHandler | None:
        """The handler for the path; raises `ArenaError` for a foreign page or host name."""
        parts = request.path.split("/")
        if len(parts) == 4 and parts[1] == "ws" and parts[2] in PEER_ROLES and parts[3]:
            role = parts[2]
        elif len(parts) == 5 and parts[1:3] == ["ws", "robots"] and parts[4] == "state":
            role = "viewer"
        else:
            return None
        handler, robot_id = ENDPOINTS[role], parts[3]
        host = request.headers.get("host")
        app.origin_policy.check_host(host)
        app.origin_policy.check_origin(request.headers.get("origin"), host, request.scheme)
        try:
            node = _remote_node(app, robot_id)
        except ArenaError as error:  # its node is gone (NODE_LOST): the client is told so
            return partial(_held, app, role, partial(_refused, robot_id=robot_id, error=error))
        if node is not None:  # another node of the fleet owns it: carried there
            return partial(_held, app, role, partial(proxy, robot_id=robot_id, node=node))
        return partial(_held, app, role, lambda connection: handler(connection, robot_id))

    return route


async def _held(
    app: ArenaApp, role: str, serve: Callable[[Connection], Awaitable[None]], ws: WebSocket
) -> None:
    """Serve a connection; once it ends it is no longer counted as its caller's."""
    connection = Connection(app, ws, role)
    try:
        await serve(connection)
    finally:
        connection.let_go()


async def _refused(connection: Connection, robot_id: str, error: ArenaError) -> None:
    """A connection refused before it reaches a robot (its key checked first, then whether
    the caller may see the robot, so that one it may not is as absent as ever): the error,
    then the close."""
    if not await connection.authorized():
        return
    if not connection.sees(robot_id):
        error = ArenaError(ErrorCode.UNKNOWN_ROBOT, f"No robot with id {robot_id!r}.")
    await connection.refuse(error)


def _remote_node(app: ArenaApp, robot_id: str) -> str | None:
    """The other node of the fleet that owns `robot_id`, if it is not here (`owner_of`:
    NODE_LOST if its node is gone)."""
    fleet = app.fleet
    if fleet is None or robot_id in {robot.robot_id for robot in app.manager.robots()}:
        return None
    node = fleet.owner_of(robot_id)
    return None if node == fleet.name else node
