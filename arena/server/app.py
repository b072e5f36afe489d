"""The quart-trio application: REST routes, error handling, auth, docs and metrics."""

from __future__ import annotations

import contextlib
import re
import time
from collections import Counter
from collections.abc import Iterable
from typing import Any

import msgspec
import trio
from quart import Response, g, redirect, request
from werkzeug.exceptions import HTTPException

import arena
from arena.drivers.hand_guide import HandGuide
from arena.drivers.sequence_master import SequenceMaster
from arena.drivers.sequences import demo_sequences, get_sequence
from arena.protocol.errors import ArenaError, ErrorCode
from arena.protocol.messages import MAX_MESSAGE_BYTES
from arena.protocol.rest import (
    ComplianceBody,
    CreateRobotBody,
    JointsBody,
    MasterBody,
    ReasonBody,
    ReplayMasterBody,
    SlaveBody,
    WorkspaceBody,
)
from arena.recording.recorder import Recorder
from arena.robot.groups import GroupRegistry
from arena.robot.handle import Robot
from arena.robot.manager import RobotManager, estop_together
from arena.robot.workspace import workspace_to_json
from arena.sensors.camera import Cameras
from arena.server import convert, dashboard, openapi, parts
from arena.server.access import (
    AccessControl,
    needed_role,
    reads_recordings,
    route_of,
    server_admin,
)
from arena.server.auth import authorize, check_role, refuse
from arena.server.base import (
    ArenaApp,
    Audit,
    Declared,
    Hardware,
    Parts,
    error_response,
    read_body,
    record_audit_now,
    refuse_any_body,
    too_large,
)
from arena.server.calibration_api import blueprint as calibration_blueprint
from arena.server.config import ServerConfig
from arena.server.dashboard import blueprint as dashboard_blueprint
from arena.server.drivers import attach_rest_master
from arena.server.fleet_api import CALLER, FORWARDED, forwarded_caller
from arena.server.fleet_api import blueprint as fleet_blueprint
from arena.server.groups_api import blueprint as groups_blueprint
from arena.server.hand_api import blueprint as hand_blueprint
from arena.server.health import blueprint as health_blueprint
from arena.server.identity import Principal, TokenVerifier
from arena.server.interventions_api import blueprint as interventions_blueprint
from arena.server.manual import move, operator_of, refusal
from arena.server.metrics import Metrics
from arena.server.move_api import blueprint as move_blueprint
from arena.server.origin import SAFE_METHODS, OriginPolicy, is_json
from arena.server.policies_api import blueprint as policies_blueprint
from arena.server.recordings_api import blueprint as recordings_blueprint
from arena.server.recordings_api import readable_recording, recorder_status
from arena.server.robot_types_api import blueprint as robot_types_blueprint
from arena.server.sensors_api import blueprint as sensors_blueprint
from arena.server.sim_leader_api import blueprint as sim_leader_blueprint
from arena.server.sim_leaders import SimLeaders
from arena.server.ws.acks import AckCache


def create_app(manager: RobotManager, config: ServerConfig, recorder: Recorder) -> ArenaApp:
    """Build the app around a running `RobotManager` and `Recorder`."""
    app = ArenaApp(__name__)
    app.manager = manager
    app.recorder = recorder
    app.arena_config = config
    app.metrics = Metrics()
    app.connections = set()
    app.websockets_held = Counter()
    app.acks = AckCache()
    app.master_links = {}
    app.origin_policy = OriginPolicy(config.host, config.allowed_origins, config.allowed_hosts)
    app.hardware = Hardware()
    app.groups = GroupRegistry(manager)
    app.access = AccessControl(manager, app.groups)
    if config.jwt_enabled:
        app.tokens = TokenVerifier.from_files(
            config.jwt_secret_file,
            config.jwt_jwks,
            issuer=config.jwt_issuer,
            audience=config.jwt_audience,
            leeway=config.jwt_leeway,
        )
    app.cameras = Cameras()
    app.parts = Parts()
    app.sim_leaders = SimLeaders()
    app.shutting_down = trio.Event()
    app.started_at = time.time()
    app.config["MAX_CONTENT_LENGTH"] = MAX_MESSAGE_BYTES
    app.register_blueprint(recordings_blueprint)
    app.register_blueprint(calibration_blueprint)
    app.register_blueprint(groups_blueprint)
    app.register_blueprint(robot_types_blueprint)
    app.register_blueprint(dashboard_blueprint)
    app.register_blueprint(sensors_blueprint)
    app.register_blueprint(fleet_blueprint)
    app.register_blueprint(health_blueprint)
    app.register_blueprint(interventions_blueprint)
    app.register_blueprint(policies_blueprint)
    app.register_blueprint(hand_blueprint)
    app.register_blueprint(move_blueprint)
    app.register_blueprint(sim_leader_blueprint)
    _register_errors(app)
    _register_routes(app)
    return app


def _register_errors(app: ArenaApp) -> None:
    @app.before_request
    async def check_request() -> Response | None:
        app.origin_policy.check(
            request.method,
            request.headers.get("Origin"),
            request.headers.get("Host"),
            request.scheme,
        )
        # A page's form or `fetch` can send text/plain without a preflight; a body is JSON,
        # declared so (or undeclared, as from a script: no browser sends that).
        mimetype = request.mimetype
        changing = request.method not in SAFE_METHODS
        if changing and mimetype and _has_body() and not is_json(mimetype):
            raise ArenaError(
                ErrorCode.UNSUPPORTED_MEDIA_TYPE,
                f"A request body must be JSON, not {mimetype}: "
                "send 'Content-Type: application/json'.",
            )
        if request.path == "/" and dashboard.is_built() and _wants_html():
            return redirect("/ui/")  # type: ignore[return-value]  # a browser: show the page
        rule = request.url_rule
        needed = needed_role(request.method, None if rule is None else rule.rule)
        if needed is None:
            return None  # a public route
        route = " ".join(route_of(request.method, rule.rule)) if rule else request.path
        # Forwarded by a node of the fleet, which checked the key or token: its caller is
        # checked here again against this node's robots, and named in its records.
        principal = forwarded_caller(
            app, request.headers.get(FORWARDED), request.headers.get(CALLER)
        )
        if principal is not None:
            check_role(app, principal, needed, route)
        else:
            # A page's <img> cannot send headers: a camera stream may carry its key in the
            # query, as a WebSocket does.
            stream = request.method == "GET" and request.path.endswith("/stream")
            principal = authorize(
                app,
                request.headers.get("Authorization"),
                request.args.get("token") if stream else None,
                needed,
                route,
                read_only=request.method in SAFE_METHODS,
            )
        g.principal = principal
        args = request.view_args or {}
        try:
            if "robot_id" in args:
                app.access.check_robot(principal, args["robot_id"])
            if "group_id" in args:
                app.access.check_group(principal, args["group_id"])
        except ArenaError:
            refuse(app, "scope")
            raise
        if request.method not in SAFE_METHODS:
            g.audit = Audit(principal.audit_name(), route, _audited_robots(app, principal))
        return None

    @app.before_request
    async def refuse_unread_body() -> None:
        rule = request.url_rule
        if request.method in SAFE_METHODS or rule is None or not _has_body():
            return
        route = (request.method, _RULE_PARAMETER.sub(r"{\1}", rule.rule))
        if route in _BODILESS:
            await refuse_any_body(" ".join(route))

    @app.after_request
    async def count(response: Response) -> Response:
        app.metrics.requests[f"{response.status_code // 100}xx"] += 1
        audit: Audit | None = g.get("audit")
        if audit is not None and response.status_code < 400:  # a refusal changed nothing
            audit.record(str(response.status_code))
        return response

    @app.errorhandler(ArenaError)
    async def arena_error(error: ArenaError) -> tuple[dict[str, Any], int]:
        app.metrics.message_errors[str(error.code)] += 1
        return error_response(error.code, error.message)

    @app.errorhandler(HTTPException)
    async def http_error(error: HTTPException) -> tuple[dict[str, Any], int]:
        status = error.code or 500
        if status == 413:  # the framework's sentence does not say the limit
            refused = too_large(request.content_length)
            return error_response(refused.code, refused.message)
        code = {
            404: ErrorCode.NOT_FOUND,
            405: ErrorCode.METHOD_NOT_ALLOWED,
        }.get(status, ErrorCode.INVALID_BODY)
        body, _ = error_response(code, error.description or error.name)
        return body, status

    @app.errorhandler(Exception)
    async def internal_error(error: Exception) -> tuple[dict[str, Any], int]:
        app.logger.exception("unhandled error on %s %s", request.method, request.path)
        return error_response(
            ErrorCode.INTERNAL_ERROR, "Something went wrong inside Arena; the log has the details."
        )


#: `<robot_id>`, `<path:name>` in a route's rule: `{robot_id}`, `{name}` as OpenAPI writes them.
_RULE_PARAMETER = re.compile(r"<(?:\w+:)?(\w+)>")
#: The state-changing routes that read no body (OpenAPI's table says which take one).
_BODILESS = frozenset(
    (method, path)
    for method, path, _, body in openapi.ROUTES
    if body is None and method not in SAFE_METHODS
)


#: State-changing routes that act on every robot the caller sees. (A route that creates a
#: robot or a group adds it: `Audit.also`; a fleet e-stop is recorded by each node it
#: stops robots on, this one included: `fleet_api`.)
_ON_EVERY_ROBOT = frozenset(
    {"/api/estop", "/api/recordings", "/api/recordings/<name>/stop", "/api/config/reload"}
)


def _audited_robots(app: ArenaApp, principal: Principal) -> list[Robot]:
    """The robots a state-changing request acts on (that the caller sees)."""
    args = request.view_args or {}
    rule = request.url_rule
    ids: list[str] = []
    if "robot_id" in args:
        ids = [args["robot_id"]]
    elif "group_id" in args:
        group = app.groups.find(args["group_id"], principal.tenant)
        ids = [] if group is None else list(group.members)
    elif rule is not None and rule.rule in _ON_EVERY_ROBOT:
        ids = [robot.robot_id for robot in app.manager.robots()]
    robots = []
    for robot_id in ids:
        with contextlib.suppress(ArenaError):
            robots.append(app.manager.get(robot_id))
    return app.access.visible(principal, robots)


def _has_body() -> bool:
    length = request.headers.get("Content-Length")
    if length is not None:
        return length.strip() not in ("", "0")
    return "chunked" in request.headers.get("Transfer-Encoding", "").lower()


def _register_routes(app: ArenaApp) -> None:
    manager = app.manager
    links = app.master_links  # each robot's WebSocket master's link

    def robots_seen() -> list[Robot]:
        return app.access.visible(g.principal, manager.robots())

    def sees(robot_id: str) -> bool:
        return app.access.sees(g.principal, robot_id)

    @app.get("/")
    async def status() -> dict[str, Any]:
        robots = robots_seen()
        return {
            "name": "Arena",
            "version": arena.__version__,
            "status": "running",
            "uptime_s": round(time.time() - app.started_at, 3),
            "robots": len(robots),
            "robots_by_state": dict(Counter(str(r.snapshot().mode) for r in robots)),
            "connections": app.metrics.connections_seen(sees),
            "commands": _sum_counters(r.command_counts for r in robots),
            "estops": sum(r.estop_count for r in robots),
            "auth": app.arena_config.auth_enabled,
            "heartbeat_timeout": app.arena_config.heartbeat_timeout,
            "recording": recorder_status(app, g.principal),
            "foxglove": None
            if app.foxglove is None
            else {"port": app.foxglove.port, "dropped": app.foxglove.dropped},
            "fleet": None
            if app.fleet is None
            else {"fleet": app.fleet.fleet, "node": app.fleet.name, "dropped": app.fleet.dropped},
            "links": {
                "robots": "/api/robots",
                "robot_types": "/api/robot-types",
                "dashboard": "/ui/",
                "docs": "/docs",
                "openapi": "/openapi.json",
                "metrics": "/metrics",
            },
        }

    @app.get("/api/robots")
    async def list_robots() -> list[dict[str, Any]]:
        return [
            convert.robot_summary(r, app.access.tenant_of(r.robot_id), links.get(r.robot_id))
            for r in robots_seen()
        ]

    @app.post("/api/robots")
    async def create_robot() -> tuple[dict[str, Any], int]:
        body = await read_body(CreateRobotBody)
        robot = await parts.create_robot(app, g.principal, body)
        g.audit.also([robot])
        return convert.robot_summary(robot, robot.tenant), 201

    @app.get("/api/robots/<robot_id>")
    async def get_robot(robot_id: str) -> dict[str, Any]:
        summary = convert.robot_summary(
            manager.get(robot_id), app.access.tenant_of(robot_id), links.get(robot_id)
        )
        # The parts the configuration file declares that are not up yet, being retried.
        summary["pending"] = [] if app.declared is None else app.declared.pending_of(robot_id)
        return summary

    @app.get("/api/config")
    async def get_config() -> Response:
        declared = _whole_server(app)
        return Response(declared.running(), content_type="application/toml; charset=utf-8")

    @app.post("/api/config/reload")
    async def reload_config() -> dict[str, Any]:
        return await _whole_server(app).reload()

    @app.get("/api/robots/<robot_id>/status")
    async def robot_status(robot_id: str) -> dict[str, Any]:
        return convert.robot_status(manager.get(robot_id), links.get(robot_id))

    @app.delete("/api/robots/<robot_id>")
    async def delete_robot(robot_id: str) -> dict[str, Any]:
        robot = manager.get(robot_id)
        record_audit_now()  # (gone once answered: nowhere to record it then)
        await parts.delete_robot(app, robot)
        return {"deleted": robot_id}

    @app.get("/api/sequences")
    async def list_sequences() -> list[dict[str, Any]]:
        return [s.summary() for s in demo_sequences().values()]

    @app.post("/api/robots/<robot_id>/play-sequence/<sequence_id>")
    async def play_sequence(robot_id: str, sequence_id: str) -> dict[str, Any]:
        robot = manager.get(robot_id)
        sequence = get_sequence(sequence_id)
        sequence.check_against(robot.model)
        master_id = await robot.attach_master(SequenceMaster([sequence]))
        return {
            "robot": robot_id,
            "sequence": sequence_id,
            "master": master_id,
            "duration": sequence.summary()["duration"],
        }

    @app.post("/api/robots/<robot_id>/stop-sequence")
    async def stop_sequence(robot_id: str) -> dict[str, Any]:
        robot = manager.get(robot_id)
        master = robot.snapshot().master
        if master is None or master.kind != SequenceMaster.kind:
            return {"robot": robot_id, "stopped": False}
        await robot.detach_master(master.peer_id, reason="sequence stopped on request")
        return {"robot": robot_id, "stopped": True, "master": master.peer_id}

    @app.post("/api/robots/<robot_id>/estop")
    async def estop(robot_id: str) -> dict[str, Any]:
        robot = manager.get(robot_id)
        body = await read_body(ReasonBody, optional=True)
        await robot.estop(body.reason or "e-stop over REST")
        return convert.robot_status(robot)

    @app.post("/api/robots/<robot_id>/reset")
    async def reset(robot_id: str) -> dict[str, Any]:
        robot = manager.get(robot_id)
        await robot.reset()
        return convert.robot_status(robot)

    @app.post("/api/estop")
    async def estop_all() -> dict[str, Any]:
        body = await read_body(ReasonBody, optional=True)
        robots = robots_seen()  # every robot the caller sees, and only those
        await estop_together(robots, body.reason or "e-stop of every robot over REST")
        return {"estopped": [r.robot_id for r in robots]}

    @app.get("/api/robots/<robot_id>/joints")
    async def get_joints(robot_id: str) -> list[dict[str, Any]]:
        data: list[dict[str, Any]] = msgspec.to_builtins(
            convert.joint_states(manager.get(robot_id)).data
        )
        return data

    @app.put("/api/robots/<robot_id>/joints")
    async def put_joints(robot_id: str) -> dict[str, Any]:
        robot = manager.get(robot_id)
        body = await read_body(JointsBody)
        result, short = await move(
            robot,
            convert.command_from_wire(body.joints, body.duration, {"source": "rest"}),
            operator_of(robot, g.principal),  # an operator's intervention: as its master
            body.wait,
        )
        if not result.accepted:
            raise refusal(robot, result)
        ack: dict[str, Any] = msgspec.to_builtins(convert.ack(result).data)
        if body.wait:
            ack["arrived"] = short is None
            if short is not None:
                ack["why"] = short
        return ack

    @app.get("/api/robots/<robot_id>/workspace")
    async def get_workspace(robot_id: str) -> dict[str, Any]:
        return workspace_to_json(manager.get(robot_id).workspace)

    @app.put("/api/robots/<robot_id>/workspace")
    async def put_workspace(robot_id: str) -> dict[str, Any]:
        robot = manager.get(robot_id)
        body = await read_body(WorkspaceBody)
        workspace = await parts.set_workspace(robot, body, robot.model.workspace)
        return workspace_to_json(workspace)

    @app.post("/api/robots/<robot_id>/slaves")
    async def attach_slave(robot_id: str) -> tuple[dict[str, Any], int]:
        robot = manager.get(robot_id)
        body = await read_body(SlaveBody)
        # hardware: a missing or busy port is the caller's error, now
        slave_id = await parts.attach_slave(app, robot, body, server_admin(g.principal))
        return {"id": slave_id, "type": type(body).__struct_config__.tag}, 201

    @app.delete("/api/robots/<robot_id>/slaves/<slave_id>")
    async def detach_slave(robot_id: str, slave_id: str) -> dict[str, Any]:
        await manager.get(robot_id).detach_slave(slave_id)
        return {"detached": slave_id}

    @app.post("/api/robots/<robot_id>/master")
    async def attach_master(robot_id: str) -> tuple[dict[str, Any], int]:
        robot = manager.get(robot_id)
        body: MasterBody = await read_body(MasterBody)
        if isinstance(body, ReplayMasterBody):
            await readable_recording(app, g.principal, body.recording, field="recording")
        # The whole server's admin: any calibration, any policy.
        master_id = await parts.attach_master(app, robot, body, server_admin(g.principal))
        return {"id": master_id, "type": type(body).__struct_config__.tag}, 201

    @app.delete("/api/robots/<robot_id>/master")
    async def detach_master(robot_id: str) -> dict[str, Any]:
        robot = manager.get(robot_id)
        master = robot.snapshot().master
        if master is not None:  # answered once its driver let go: a leader's port is free
            await robot.detach_master(master.peer_id, wait_closed=True)
        return {"detached": master.peer_id if master else None}

    def servo_readings(robot: Robot) -> list[tuple[str, float, float]]:
        attached = {slave.peer_id for slave in robot.snapshot().slaves}
        return app.hardware.servo_readings(robot.robot_id, attached)

    @app.post("/api/robots/<robot_id>/compliance")
    async def enter_compliance(robot_id: str) -> tuple[dict[str, Any], int]:
        robot = manager.get(robot_id)
        body = await read_body(ComplianceBody)
        attached = {slave.peer_id for slave in robot.snapshot().slaves}
        _, arm = app.hardware.find(robot_id, None, attached)
        if not hasattr(arm, "enter_compliance"):
            raise ArenaError(ErrorCode.NO_HARDWARE, f"Robot {robot_id!r} has no usb-slave.")
        joints = list(arm.servo_ids_of(body.joints))  # (unknown names refused here)
        holder = robot.snapshot().master
        if holder is not None:  # (before any torque changes)
            raise ArenaError(
                ErrorCode.MASTER_ACTIVE,
                f"Master {holder.peer_id!r} drives this robot: detach it to guide the arm by hand.",
            )
        await arm.enter_compliance(joints, body.torque)
        guide = HandGuide(arm, joints, body.torque, robot.model.safety.command_rate)
        try:
            master_id = await attach_rest_master(robot, guide)
        except BaseException:
            await arm.leave_compliance()
            raise
        return {"id": master_id, "joints": joints, "torque": body.torque}, 201

    @app.delete("/api/robots/<robot_id>/compliance")
    async def leave_compliance(robot_id: str) -> dict[str, Any]:
        robot = manager.get(robot_id)
        master = robot.snapshot().master
        if master is None or master.kind != HandGuide.kind:
            return {"detached": None}
        await robot.detach_master(master.peer_id)
        return {"detached": master.peer_id}

    @app.get("/metrics")
    async def metrics() -> Response:
        return Response(
            app.metrics.render(
                robots_seen(),
                sum(
                    c.queued_bytes
                    for c in app.connections
                    if c.robots and all(sees(robot_id) for robot_id in c.robots)
                ),
                recorder_status(app, g.principal),  # the caller's tenant's counts
                app.metrics.connections_seen(sees),
                whole_server=reads_recordings(g.principal),
                links=app.master_links,
                servos=servo_readings,
            ),
            content_type="text/plain; version=0.0.4",
        )

    @app.get("/openapi.json")
    async def openapi_json() -> dict[str, Any]:
        return openapi.document(app)

    @app.get("/docs")
    async def docs() -> Response:
        return Response(openapi.DOCS_PAGE, content_type="text/html; charset=utf-8")


def _whole_server(app: ArenaApp) -> Declared:
    """The declared setup, for the whole server's admin only (it spans every tenant)."""
    if not server_admin(g.principal):
        refuse(app, "scope")
        raise ArenaError(
            ErrorCode.FORBIDDEN,
            "The server's configuration is the whole server's: an admin of the default "
            "tenant with every robot in scope only.",
        )
    assert app.declared is not None
    return app.declared


def _wants_html() -> bool:
    """Whether the client prefers a page to JSON (a browser does; httpx, curl and clients don't)."""
    best = request.accept_mimetypes.best_match(["application/json", "text/html"])
    return best == "text/html"


def _sum_counters(counters: Iterable[Counter[str]]) -> dict[str, int]:
    total: Counter[str] = Counter()
    for counter in counters:
        total.update(counter)
    return dict(total)
