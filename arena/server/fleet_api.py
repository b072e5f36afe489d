"""The fleet on the server: REST (`/api/fleet/...`), and any robot of the fleet through any node.

A WebSocket for a robot that lives on another node is carried there through a Zenoh tunnel
(`fleet.node.Tunnel`): this node checks the client's key, the robot's node serves the
connection with its own handlers (`TunnelSocket` stands in for the socket), so ownership,
takeover, e-stops, rate limits and acknowledgments are that node's, as if the client had
connected there. A REST call for such a robot is forwarded the same way (the `http` service)
and run by the robot's node through its own app. Frames in a tunnel: `t` + text, `c` + close
JSON; an empty frame (local only) means the other node is gone.
"""

from __future__ import annotations

import base64
import json
import logging
import secrets
from typing import Any

import trio
from quart import Blueprint, Response, current_app, request

import arena
from arena.fleet.node import ESTOP_TIMEOUT, FleetNode, Tunnel
from arena.protocol.errors import ArenaError, ErrorCode
from arena.protocol.rest import ReasonBody
from arena.protocol.ws_frames import UpgradeRequest, WebSocketClosed
from arena.robot.actor import Robot
from arena.robot.events import StateChanged
from arena.server.base import ArenaApp, error_response, read_body

log = logging.getLogger(__name__)
blueprint = Blueprint("fleet", __name__)

#: The header that marks a REST call forwarded by another node (its value is this process's
#: secret, so no client can send it).
FORWARDED = "X-Arena-Fleet-Forwarded"
#: Request headers a forwarded call keeps.
_KEPT_HEADERS = ("content-type", "accept")


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
    """Every node seen since this one started: name, alive, version, robots, endpoints."""
    fleet = _fleet()
    await fleet.refresh_all()
    return {
        "fleet": fleet.fleet,
        "node": fleet.name,
        "nodes": [
            {
                "name": view.name,
                "alive": view.alive,
                "version": view.version,
                "robots": [robot["id"] for robot in view.robots],
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
            # `url`: the owner's own address, for a client that wants to go there directly
            entry = {**robot, "node": view.name, "url": view.http}
            if not view.alive:
                entry["state"] = "offline"
            robots.append(entry)
    return {"fleet": fleet.fleet, "robots": robots}


@blueprint.post("/api/fleet/estop")
async def fleet_estop() -> dict[str, Any]:
    """E-stop every robot of every live node. Complete (200) only when every live node said
    its robots are stopped; otherwise 503 ESTOP_INCOMPLETE, naming the nodes that answered
    with a failure (and why) and those that did not answer within 100 ms."""
    body: ReasonBody = await read_body(ReasonBody, optional=True)  # the body's faults first
    fleet = _fleet()
    reason = body.reason or f"fleet e-stop from node {fleet.name}"
    answers = await fleet.ask_all("estop", {"reason": reason}, timeout=ESTOP_TIMEOUT)
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


def robot_summary(robot: Robot) -> dict[str, Any]:
    """What the fleet shows of one robot."""
    snapshot = robot.snapshot()
    return {
        "id": robot.robot_id,
        "name": robot.name,
        "robot_type": robot.model.robot_type,
        "state": str(snapshot.mode),
        "owner": snapshot.owner,
        "estop_reason": snapshot.estop_reason,
    }


def install(app: ArenaApp, fleet: FleetNode) -> None:
    """Offer this node's services to the fleet and follow its robots."""
    app.fleet = fleet
    app.fleet_secret = secrets.token_hex(16)

    async def info(_: bytes) -> dict[str, Any]:
        return {
            "name": fleet.name,
            "version": arena.__version__,
            "robots": [robot_summary(robot) for robot in app.manager.robots()],
            "locators": await fleet.locators(),
            "http": app.own_url,
        }

    async def estop(payload: bytes) -> dict[str, Any]:
        reason = str(json.loads(payload or b"{}").get("reason") or "fleet e-stop")
        robots = app.manager.robots()
        await app.manager.estop_all(reason)
        return {"node": fleet.name, "robots": [robot.robot_id for robot in robots]}

    async def http(payload: bytes) -> dict[str, Any]:
        return await _run_forwarded(app, json.loads(payload))

    async def tunnel(payload: bytes) -> dict[str, Any]:
        return await _serve_tunnel(app, fleet, json.loads(payload))

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
    node = fleet.owner_of(robot_id)  # NODE_LOST for a robot of a node that is gone
    if node is None or node == fleet.name:
        return None
    raw = await request.get_data(cache=True, as_text=False)
    body = raw.encode() if isinstance(raw, str) else raw
    call = {
        "method": request.method,
        "path": request.path,
        "query": request.query_string.decode("latin-1"),
        "headers": {k: v for k, v in request.headers.items() if k.lower() in _KEPT_HEADERS},
        "body": base64.b64encode(body).decode(),
    }
    answer = await fleet.ask(node, "http", call, timeout=10.0)
    response = Response(
        base64.b64decode(answer["body"]),
        status=answer["status"],
        content_type=answer["content_type"],
    )
    response.headers["X-Arena-Node"] = node
    return response


async def _run_forwarded(app: ArenaApp, call: dict[str, Any]) -> dict[str, Any]:
    """Run a forwarded REST call through this node's own app (its rules, its robot)."""
    client: Any = app.test_client()
    headers = {**call.get("headers", {}), FORWARDED: app.fleet_secret}
    response = await client.open(
        call["path"],
        method=call["method"],
        query_string=call.get("query") or None,
        headers=headers,
        data=base64.b64decode(call.get("body", "")),
    )
    data: bytes = await response.get_data(as_text=False)
    return {
        "status": response.status_code,
        "content_type": response.content_type,
        "body": base64.b64encode(data).decode(),
    }


def is_forwarded(app: ArenaApp, value: str | None) -> bool:
    """True for a call another node of the fleet forwarded (it checked the key)."""
    return bool(app.fleet_secret) and value == app.fleet_secret


# -- WebSockets for robots of other nodes -----------------------------------------------------


#: Tunnel frames `TunnelSocket.next_in_hand` looks through for a message.
_IN_HAND = 32


class TunnelSocket:
    """The robot's node's end of a tunnel, as the WebSocket handlers see a socket. The
    client's node checked the key: `trusted`."""

    trusted = True
    backlogged = False
    queued_bytes = 0

    def __init__(self, tunnel: Tunnel, request: UpgradeRequest) -> None:
        self.tunnel = tunnel
        self.request = request
        self.close_sent = False

    async def receive(self) -> str:
        while True:
            try:
                data = await self.tunnel.inbox.receive()
            except (trio.EndOfChannel, trio.ClosedResourceError):
                raise WebSocketClosed(1006, "tunnel closed") from None
            message = self._message(data)
            if message is not None:
                return message

    def next_in_hand(self) -> str | None:
        """The next message if one is in the inbox already (as `WebSocket.next_in_hand`)."""
        for _ in range(_IN_HAND):
            try:
                data = self.tunnel.inbox.receive_nowait()
            except trio.WouldBlock:
                return None
            except (trio.EndOfChannel, trio.ClosedResourceError):
                raise WebSocketClosed(1006, "tunnel closed") from None
            message = self._message(data)
            if message is not None:
                return message
        return None

    def _message(self, data: bytes) -> str | None:
        """A text message, None for anything else; the end of the tunnel raises."""
        if data[:1] == b"t":
            return data[1:].decode("utf-8")
        if not data:
            raise WebSocketClosed(1006, "the client's node is gone")
        if data[:1] == b"c":
            close = json.loads(data[1:] or b"{}")
            self.close_sent = True
            raise WebSocketClosed(int(close.get("code", 1000)), str(close.get("reason", "")))
        return None

    def holds_more(self) -> bool:
        return self.tunnel.inbox.statistics().current_buffer_used > 0

    def offer(self, *texts: str, whole: bool = False) -> bool:
        for text in texts:  # (each goes into the tunnel at once, `whole` or not)
            self.tunnel.send(b"t" + text.encode("utf-8"))
        return True

    async def send(self, *texts: str) -> None:
        self.offer(*texts)
        await trio.lowlevel.checkpoint()

    def send_nowait(self, text: str) -> None:
        self.offer(text)

    def send_now(self, *texts: str) -> bool:
        return self.offer(*texts)

    def close_nowait(self, code: int, reason: str = "") -> None:
        if not self.close_sent:
            self.close_sent = True
            self.tunnel.send(b"c" + json.dumps({"code": code, "reason": reason}).encode())

    async def wait_drained(self) -> None:
        await trio.sleep_forever()  # never backlogged: nothing to wait for


async def _serve_tunnel(app: ArenaApp, fleet: FleetNode, call: dict[str, Any]) -> dict[str, Any]:
    """Serve a client of another node: the robot must be here; the connection runs as if the
    client had connected to this node."""
    from arena.server.websockets import Connection, serve_role

    robot_id, role = str(call["robot"]), str(call["role"])
    app.manager.get(robot_id)  # UNKNOWN_ROBOT if it is not here (any more)
    if role not in ("master", "slave", "viewer"):
        raise ArenaError(ErrorCode.INVALID_VALUE, f"No such role {role!r}.")
    tunnel = fleet.open_tunnel(str(call["origin"]), str(call["tunnel"]), serving=True)
    path = f"/ws/robots/{robot_id}/state" if role == "viewer" else f"/ws/{role}/{robot_id}"
    socket = TunnelSocket(tunnel, UpgradeRequest(path, dict(call.get("args", {})), {}))

    async def serve() -> None:
        try:
            await serve_role(Connection(app, socket, role), robot_id)  # type: ignore[arg-type]
        finally:
            socket.close_nowait(1000, "")
            tunnel.close()

    assert fleet.nursery is not None
    fleet.nursery.start_soon(serve)
    return {"tunnel": tunnel.tunnel_id, "node": fleet.name}


def _kind_of(text: str) -> str:
    """The `type` of a message (encoded with `type` first), for latest-wins toward a slow
    client; anything else counts as rare."""
    if text.startswith('{"type":"'):
        end = text.find('"', 9)
        if end > 0:
            return text[9:end]
    return ""


async def proxy(connection: Any, robot_id: str, node: str) -> None:
    """A client of this node for a robot of `node`: carry its connection there."""
    from arena.server.websockets import Encoded, authorized

    app: ArenaApp = connection.app
    fleet = app.fleet
    assert fleet is not None
    if not await authorized(connection):
        return
    tunnel = fleet.open_tunnel(node, serving=False)
    args = {k: v for k, v in connection.args.items() if k != "token"}
    call = {
        "tunnel": tunnel.tunnel_id,
        "origin": fleet.name,
        "role": connection.role,
        "robot": robot_id,
        "args": args,
    }
    try:
        await fleet.ask(node, "tunnel", call)
    except ArenaError as error:
        tunnel.close()
        await connection.refuse(error)
        return

    async def body(nursery: trio.Nursery) -> None:
        async def to_robot() -> None:
            while True:
                try:
                    frame = await connection.ws.receive()
                except WebSocketClosed as closed:
                    tunnel.send(b"c" + json.dumps({"code": closed.code}).encode())
                    nursery.cancel_scope.cancel()
                    return
                if isinstance(frame, str):
                    tunnel.send(b"t" + frame.encode("utf-8"))
                else:
                    await connection.send_error(
                        ErrorCode.BINARY_NOT_SUPPORTED, "Send JSON text frames, not binary frames."
                    )

        nursery.start_soon(to_robot)
        async for data in tunnel.inbox:
            if not data:
                await connection.refuse(
                    ArenaError(
                        ErrorCode.NODE_LOST,
                        f"Node {node!r}, which owns robot {robot_id!r}, left the fleet.",
                    )
                )
                return
            if data[:1] == b"c":
                close = json.loads(data[1:] or b"{}")
                await connection.close(int(close.get("code", 1000)), str(close.get("reason", "")))
                return
            text = data[1:].decode("utf-8")
            await connection.send(Encoded(_kind_of(text), text))

    try:
        await connection.run(body)
    finally:
        tunnel.close()
