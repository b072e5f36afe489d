"""The fleet on the server: REST (`/api/fleet/...`), the node's services, and any robot of
the fleet through any node.

A REST call for a robot that lives on another node is forwarded there (`fleet.forward`, the
`http` service) and run by the robot's node through its own app; a WebSocket is carried
there through a tunnel (`fleet.tunnel`, served by `ws.fleet`).
"""

from __future__ import annotations

import json
import logging
import secrets
from functools import partial
from typing import Any

from quart import Blueprint, Response, current_app, g, request

import arena
from arena.fleet import forward
from arena.fleet.node import ESTOP_TIMEOUT, FleetNode
from arena.protocol.errors import ArenaError, ErrorCode
from arena.protocol.rest import DEFAULT_TENANT, ReasonBody
from arena.robot.events import StateChanged
from arena.robot.handle import Robot
from arena.robot.manager import estop_together
from arena.server.auth import refuse
from arena.server.base import ArenaApp, error_response, read_body
from arena.server.identity import Principal, Role
from arena.server.ws.fleet import serve_tunnel

log = logging.getLogger(__name__)
blueprint = Blueprint("fleet", __name__)

#: The header that marks a REST call forwarded by another node (its value is this process's
#: secret, so no client can send it).
FORWARDED = "X-Arena-Fleet-Forwarded"
#: The header of a forwarded call that says who called (JSON claims, `Principal.to_wire`);
#: read only beside `FORWARDED`.
CALLER = "X-Arena-Fleet-Caller"


def _app() -> ArenaApp:
    return current_app  # type: ignore[return-value]


def _fleet() -> FleetNode:
    fleet = _app().fleet
    if fleet is None:
        raise ArenaError(
            ErrorCode.NOT_FOUND, "This server is not in a fleet (start it with --node NAME)."
        )
    return fleet


# -- REST ------------------------------------------------------------------------------------


@blueprint.get("/api/fleet/nodes")
async def fleet_nodes() -> dict[str, Any]:
    """Every node seen since this one started: name, alive, version, the robots the caller
    sees, endpoints."""
    fleet = _fleet()
    await fleet.refresh_all()
    access, principal = _app().access, g.principal
    return {
        "fleet": fleet.fleet,
        "node": fleet.name,
        "nodes": [
            {
                "name": view.name,
                "alive": view.alive,
                "version": view.version,
                "robots": [
                    robot["id"] for robot in view.robots if access.sees(principal, str(robot["id"]))
                ],
                "locators": view.locators,
                "http": view.http,
            }
            for view in sorted(fleet.nodes.values(), key=lambda v: v.name)
        ],
    }


@blueprint.get("/api/fleet/robots")
async def fleet_robots() -> dict[str, Any]:
    """Every robot of every node, with its node and state (`offline` on a node that is gone)."""
    fleet = _fleet()
    await fleet.refresh_all()
    robots = []
    for view in sorted(fleet.nodes.values(), key=lambda v: v.name):
        for robot in view.robots:
            if not _app().access.sees(g.principal, str(robot.get("id"))):
                continue
            # `url`: the owner's own address, for a client that wants to go there directly
            entry = {**robot, "node": view.name, "url": view.http}
            if not view.alive:
                entry["state"] = "offline"
            robots.append(entry)
    return {"fleet": fleet.fleet, "robots": robots}


#: How a fleet e-stop is named in the audit of each robot it stops (on that robot's node).
FLEET_ESTOP = "POST /api/fleet/estop"


@blueprint.post("/api/fleet/estop")
async def fleet_estop() -> dict[str, Any]:
    """E-stop every robot of every live node. Complete (200) only when every live node said
    its robots are stopped; otherwise 503 ESTOP_INCOMPLETE, naming the nodes that answered
    with a failure (and why) and those that did not answer within 100 ms."""
    body: ReasonBody = await read_body(ReasonBody, optional=True)  # the body's faults first
    fleet = _fleet()
    reason = body.reason or f"fleet e-stop from node {fleet.name}"
    # Each node stops the robots this caller sees there (its tenant and scope go along).
    principal: Principal = g.principal
    whose = {"tenant": principal.tenant, "robots": principal.robots, "groups": principal.groups}
    # ... and who asked, from where: each node records it on the robots it stops.
    whose.update(sub=principal.audit_name(), node=fleet.name)
    answers = await fleet.ask_all("estop", {"reason": reason, **whose}, timeout=ESTOP_TIMEOUT)
    acks, failed = [], []
    for node, (answer, seconds) in sorted(answers.items()):
        if "ok" in answer:
            robots = answer["ok"].get("robots", [])
            acks.append({"node": node, "robots": robots, "ms": round(seconds * 1000, 3)})
        else:
            error = answer.get("error") or {}
            failed.append(
                {
                    "node": node,
                    "code": str(error.get("code", ErrorCode.INTERNAL_ERROR)),
                    "message": str(error.get("message", "no reason given")),
                }
            )
    live = {name for name, view in fleet.nodes.items() if view.alive}
    missing = sorted(live - set(answers))
    result: dict[str, Any] = {
        "reason": reason,
        "acks": acks,
        "failed": failed,
        "missing": missing,
        "complete": not missing and not failed,
    }
    if result["complete"]:
        return result
    said = [f"node {f['node']!r} failed ({f['code']}: {f['message']})" for f in failed]
    within = f"{ESTOP_TIMEOUT * 1000:g} ms"
    said += [f"node {node!r} did not answer within {within}" for node in missing]
    message = "The fleet e-stop is incomplete: " + "; ".join(said) + "."
    raise EstopIncomplete(result, message)


class EstopIncomplete(ArenaError):
    """A fleet e-stop that not every live node acknowledged: ESTOP_INCOMPLETE, with the
    answer (`acks`, `failed`, `missing`) beside the error, so a script sees who stopped."""

    def __init__(self, answer: dict[str, Any], message: str) -> None:
        super().__init__(ErrorCode.ESTOP_INCOMPLETE, message)
        self.answer = answer


@blueprint.errorhandler(EstopIncomplete)
async def estop_incomplete(error: EstopIncomplete) -> tuple[dict[str, Any], int]:
    """The error's shape and status (503), and the e-stop's answer with it."""
    _app().metrics.message_errors[str(error.code)] += 1
    body, status = error_response(error.code, error.message)
    return {**error.answer, **body}, status


# -- the node's services ---------------------------------------------------------------------


def robot_summary(robot: Robot, tenant: str) -> dict[str, Any]:
    """What the fleet shows of one robot."""
    snapshot = robot.snapshot()
    return {
        "id": robot.robot_id,
        "name": robot.name,
        "tenant": tenant,
        "robot_type": robot.model.robot_type,
        "state": str(snapshot.mode),
        "owner": snapshot.owner,
        "estop_reason": snapshot.estop_reason,
    }


def caller_of(asked: dict[str, Any]) -> Principal:
    """Whose fleet e-stop this is: the tenant and scope the asking node sent (a node of an
    older version sends none: every robot, as it asked then)."""

    def patterns(value: Any) -> tuple[str, ...] | None:
        return None if not isinstance(value, list) else tuple(str(p) for p in value)

    tenant = asked.get("tenant")
    return Principal(
        "fleet",
        Role.VIEWER,
        tenant if isinstance(tenant, str) else DEFAULT_TENANT,
        patterns(asked.get("robots")),
        patterns(asked.get("groups")),
    )


def install(app: ArenaApp, fleet: FleetNode) -> None:
    """Offer this node's services to the fleet and follow its robots."""
    app.fleet = fleet
    app.fleet_secret = secrets.token_hex(16)
    app.access.tenant_elsewhere = partial(_tenant_elsewhere, fleet)

    async def info(_: bytes) -> dict[str, Any]:
        return {
            "name": fleet.name,
            "version": arena.__version__,
            "robots": [
                robot_summary(robot, app.access.tenant_of(robot.robot_id))
                for robot in app.manager.robots()
            ],
            "locators": await fleet.locators(),
            "http": app.own_url,
        }

    async def estop(payload: bytes) -> dict[str, Any]:
        asked = json.loads(payload or b"{}")
        reason = str(asked.get("reason") or "fleet e-stop")
        every = app.manager.robots()
        robots = app.access.visible(caller_of(asked), every)
        if len(robots) == len(every):
            await app.manager.estop_all(reason)
        else:
            await estop_together(robots, reason)
        user, origin = asked.get("sub"), asked.get("node")
        for robot in robots:  # (a node of an older version says not who)
            robot.audit(str(user or "fleet"), FLEET_ESTOP, f"from node {origin or '?'}")
        return {"node": fleet.name, "robots": [robot.robot_id for robot in robots]}

    async def run(call: forward.Call) -> forward.Answer:
        return await _run_forwarded(app, call)

    async def tunnel(payload: bytes) -> dict[str, Any]:
        return serve_tunnel(app, fleet, json.loads(payload))

    http = forward.http_service(run)
    fleet.services.update(info=info, estop=estop, http=http, tunnel=tunnel)
    app.manager.on_create.append(lambda robot: _follow(fleet, robot))
    app.before_request(_forward_remote_robot)


def _follow(fleet: FleetNode, robot: Robot) -> None:
    """Declare the robot to the fleet and publish its state changes while it lives."""
    fleet.robot_added(robot.robot_id)

    async def publish() -> None:
        try:
            with robot.subscribe(maxlen=256, kinds=[StateChanged]) as events:
                async for event in events:
                    if isinstance(event, StateChanged):
                        fleet.publish_state(
                            robot.robot_id,
                            json.dumps(
                                {
                                    "mode": str(event.mode),
                                    "owner": event.owner,
                                    "estop_reason": event.estop_reason,
                                    "cause": event.cause,
                                    "wall_time": event.wall_time,
                                }
                            ).encode(),
                        )
        finally:
            fleet.robot_removed(robot.robot_id)

    if fleet.nursery is not None:
        fleet.nursery.start_soon(publish)


# -- REST calls for robots of other nodes -----------------------------------------------------


async def _forward_remote_robot() -> Response | None:
    """Before a request: a robot call for a robot another node owns goes there."""
    app = _app()
    fleet = app.fleet
    parts = request.path.split("/")
    if fleet is None or len(parts) < 4 or parts[1:3] != ["api", "robots"] or not parts[3]:
        return None
    robot_id = parts[3]
    if robot_id in {robot.robot_id for robot in app.manager.robots()}:
        return None
    principal: Principal = g.principal
    if not app.access.sees(principal, robot_id):  # before anything that tells it exists
        refuse(app, "scope")
        raise ArenaError(ErrorCode.UNKNOWN_ROBOT, f"No robot with id {robot_id!r}.")
    node = fleet.owner_of(robot_id)  # NODE_LOST for a robot of a node that is gone
    if node is None or node == fleet.name:
        return None
    raw = await request.get_data(cache=True, as_text=False)
    body = raw.encode() if isinstance(raw, str) else raw
    query = request.query_string.decode("latin-1")
    call = forward.request_call(
        request.method, request.path, query, request.headers.items(), body, principal.to_wire()
    )
    answer = await forward.forward(fleet, node, call)
    response = Response(answer.body, status=answer.status, content_type=answer.content_type)
    response.headers["X-Arena-Node"] = node
    return response


async def _run_forwarded(app: ArenaApp, call: forward.Call) -> forward.Answer:
    """Run a forwarded REST call through this node's own app (its rules, its robot, and the
    caller checked again against them)."""
    client: Any = app.test_client()
    headers = {**call.headers, FORWARDED: app.fleet_secret}
    if call.caller is not None:
        headers[CALLER] = json.dumps(call.caller)
    response = await client.open(
        call.path,
        method=call.method,
        query_string=call.query or None,
        headers=headers,
        data=call.body,
    )
    data: bytes = await response.get_data(as_text=False)
    return forward.Answer(response.status_code, response.content_type, data)


def forwarded_caller(app: ArenaApp, secret: str | None, caller: str | None) -> Principal | None:
    """Who called, for a call another node of the fleet forwarded (`secret` is this
    process's: that node checked the key or token, and `caller` says who it proved to be);
    None for any other request. UNAUTHORIZED for a caller that cannot be read."""
    if not app.fleet_secret or secret != app.fleet_secret:
        return None
    try:
        claims = None if caller is None else json.loads(caller)
        return Principal.of_wire(claims, open_server=not app.arena_config.auth_enabled)
    except ValueError as exc:
        raise ArenaError(
            ErrorCode.UNAUTHORIZED, f"The forwarded caller is not valid: {exc}."
        ) from None


def _tenant_elsewhere(fleet: FleetNode, robot_id: str) -> str | None:
    """The tenant of a robot another node of the fleet owns, as that node said: the live
    owner's word first (an id deleted on a node that then left may be made anew on another,
    of another tenant), a dead node's only when no live node has the robot."""
    owner = fleet.robot_nodes.get(robot_id)
    if owner is not None:  # (its view may not list the robot yet: not known then)
        views = [fleet.nodes[owner]] if owner in fleet.nodes else []
    else:
        views = [view for view in fleet.nodes.values() if not view.alive]
    for view in views:
        for robot in view.robots:
            if robot.get("id") == robot_id:
                return str(robot.get("tenant", DEFAULT_TENANT))
    return None
