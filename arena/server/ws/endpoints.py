"""The endpoints by role, for a robot (or group) of this node."""

from __future__ import annotations

from collections.abc import Awaitable, Callable

from arena.server.ws import group_master, master, slave, viewer
from arena.server.ws.connection import Connection


async def serve_master(connection: Connection, robot_id: str) -> None:
    """A master of a robot, or of a group by its id: a group of the caller's tenant whose
    every member it sees (any other is as absent as a robot that does not exist)."""
    if not await connection.authorized():
        return
    app = connection.app
    group = app.groups.find(robot_id, connection.principal.tenant)
    if group is not None and app.access.sees_group(connection.principal, group.members):
        await group_master.serve(connection, group)
    else:
        await master.serve(connection, robot_id)


ENDPOINTS: dict[str, Callable[[Connection, str], Awaitable[None]]] = {
    "master": serve_master,
    "slave": slave.serve,
    "viewer": viewer.serve,
}
#: The roles whose path is `/ws/{role}/{robot id}` (a viewer's is `/ws/robots/{id}/state`).
PEER_ROLES = ("master", "slave")


async def serve_role(connection: Connection, robot_id: str) -> None:
    """Serve a connection of its role (master, slave or viewer) for a robot of this node."""
    await ENDPOINTS[connection.role](connection, robot_id)
