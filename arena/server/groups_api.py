"""REST for robot groups: create, list, read, delete, and e-stop or reset a whole group."""

from __future__ import annotations

import contextlib
from typing import Any

from quart import Blueprint, current_app, g

from arena.protocol.errors import ArenaError
from arena.protocol.rest import GroupBody, ReasonBody
from arena.server import parts
from arena.server.base import ArenaApp, read_body

blueprint = Blueprint("groups", __name__)


def _app() -> ArenaApp:
    return current_app  # type: ignore[return-value]


@blueprint.get("/api/groups")
async def list_groups() -> dict[str, Any]:
    """Every group with its members' states."""
    app = _app()
    principal = g.principal
    return {
        "groups": [
            group.describe(app.manager)
            for group in app.groups.all(principal.tenant)
            if app.access.sees_group(principal, group.members)
        ]
    }


@blueprint.post("/api/groups")
async def create_group() -> tuple[dict[str, Any], int]:
    """Create a group of existing robots."""
    app = _app()
    body: GroupBody = await read_body(GroupBody)
    for robot_id in body.members:  # a robot the caller does not see is as if absent
        app.access.check_robot(g.principal, robot_id)
    group = parts.create_group(app, body, g.principal.tenant)
    g.audit.also(app.manager.get(robot_id) for robot_id in group.members)
    return group.describe(app.manager), 201


@blueprint.get("/api/groups/<group_id>")
async def read_group(group_id: str) -> dict[str, Any]:
    """One group."""
    app = _app()
    return app.groups.get(group_id, g.principal.tenant).describe(app.manager)


@blueprint.delete("/api/groups/<group_id>")
async def delete_group(group_id: str) -> dict[str, Any]:
    """Forget a group (its robots and their masters stay)."""
    _app().groups.delete(group_id, g.principal.tenant)
    return {"deleted": group_id}


@blueprint.post("/api/groups/<group_id>/estop")
async def estop_group(group_id: str) -> dict[str, Any]:
    """E-stop every member."""
    app = _app()
    group = app.groups.get(group_id, g.principal.tenant)
    body: ReasonBody = await read_body(ReasonBody, optional=True)
    reason = body.reason or f"group {group_id!r} e-stop"
    for robot_id in group.members:
        with contextlib.suppress(ArenaError):  # a deleted member
            await app.manager.get(robot_id).estop(reason)
    return group.describe(app.manager)


@blueprint.post("/api/groups/<group_id>/reset")
async def reset_group(group_id: str) -> dict[str, Any]:
    """Clear every member's e-stop."""
    app = _app()
    group = app.groups.get(group_id, g.principal.tenant)
    for robot_id in group.members:
        with contextlib.suppress(ArenaError):
            robot = app.manager.get(robot_id)
            if str(robot.snapshot().mode) == "estopped":
                await robot.reset()
    return group.describe(app.manager)
