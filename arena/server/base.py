"""What the app and its blueprints share: the app's type, the error shape, the body reader,
and the registry of hardware slaves. It sits below `app` and every blueprint, which import it
and never each other."""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

import msgspec
import trio
from quart import g, request
from quart_trio import QuartTrio

from arena.protocol.errors import ArenaError, ErrorCode
from arena.protocol.messages import MAX_MESSAGE_BYTES
from arena.protocol.rest import MasterBody, SlaveBody
from arena.protocol.validation import refusal
from arena.recording.recorder import Recorder
from arena.robot.groups import GroupRegistry
from arena.robot.handle import Robot
from arena.robot.manager import RobotManager
from arena.server.access import AccessControl
from arena.server.config import ServerConfig
from arena.server.identity import TokenVerifier
from arena.server.link_quality import LinkQuality
from arena.server.metrics import Metrics
from arena.server.origin import OriginPolicy

if TYPE_CHECKING:
    from arena.fleet.node import FleetNode
    from arena.ros2.bridge import Ros2Bridge
    from arena.sensors.camera import Cameras
    from arena.server.foxglove_bridge import FoxgloveBridge  # imports the SDK
    from arena.server.sim_leaders import SimLeaders
    from arena.server.ws.acks import AckCache

#: HTTP status for each error code (anything missing is 400).
STATUS_FOR: dict[ErrorCode, int] = {
    ErrorCode.UNKNOWN_ROBOT: 404,
    ErrorCode.UNKNOWN_SEQUENCE: 404,
    ErrorCode.UNKNOWN_SLAVE: 404,
    ErrorCode.UNKNOWN_RECORDING: 404,
    ErrorCode.INVALID_RECORDING: 422,
    ErrorCode.POLICY_INVALID: 422,
    ErrorCode.POLICY_NOT_READY: 504,
    ErrorCode.SCRIPT_INVALID: 422,
    ErrorCode.NOT_FOUND: 404,
    ErrorCode.ROBOT_STOPPED: 404,
    ErrorCode.METHOD_NOT_ALLOWED: 405,
    ErrorCode.MASTER_ACTIVE: 409,
    ErrorCode.NOT_OWNER: 409,
    ErrorCode.MASTER_PAUSED: 409,
    ErrorCode.NO_MASTER: 409,
    ErrorCode.INTERVENTION_ACTIVE: 409,
    ErrorCode.NO_INTERVENTION: 409,
    ErrorCode.NO_HIGHLIGHT: 409,
    ErrorCode.ROBOT_EXISTS: 409,
    ErrorCode.ESTOPPED: 423,
    ErrorCode.MESSAGE_TOO_LARGE: 413,
    ErrorCode.INVALID_JSON: 422,
    ErrorCode.INVALID_BODY: 422,
    ErrorCode.UNKNOWN_FIELD: 400,
    ErrorCode.INVALID_VALUE: 422,
    ErrorCode.INVALID_CONFIG: 422,
    ErrorCode.UNKNOWN_JOINT: 422,
    ErrorCode.EMPTY_COMMAND: 422,
    ErrorCode.UNKNOWN_ROBOT_TYPE: 422,
    ErrorCode.RATE_LIMITED: 429,
    ErrorCode.LIMIT_REACHED: 429,
    ErrorCode.COLLISION: 422,
    ErrorCode.UNREACHABLE: 422,
    ErrorCode.NO_PATH: 422,
    ErrorCode.UNAUTHORIZED: 401,
    ErrorCode.FORBIDDEN: 403,
    ErrorCode.ORIGIN_NOT_ALLOWED: 403,
    ErrorCode.HOST_NOT_ALLOWED: 403,
    ErrorCode.UNSUPPORTED_MEDIA_TYPE: 415,
    ErrorCode.OVERLOADED: 503,
    ErrorCode.INTERNAL_ERROR: 500,
    ErrorCode.NOT_INSTALLED: 501,
    ErrorCode.NO_HARDWARE: 404,
    ErrorCode.NO_LEADER: 404,
    ErrorCode.LEADER_NOT_SIMULATED: 409,
    ErrorCode.PORT_NOT_FOUND: 404,
    ErrorCode.PORT_BUSY: 409,
    ErrorCode.CALIBRATION_STATE: 409,
    ErrorCode.PORT_PERMISSION_DENIED: 403,
    ErrorCode.PORT_DISCONNECTED: 503,
    ErrorCode.SERVO_TIMEOUT: 504,
    ErrorCode.SERVO_WRONG_MODEL: 422,
    ErrorCode.SERVO_OUT_OF_RANGE: 422,
    ErrorCode.REMOTE_UNREACHABLE: 502,
    ErrorCode.REMOTE_REFUSED: 502,
    ErrorCode.UNKNOWN_GROUP: 404,
    ErrorCode.GROUP_EXISTS: 409,
    ErrorCode.UNKNOWN_CAMERA: 404,
    ErrorCode.CAMERA_EXISTS: 409,
    ErrorCode.CAMERA_FAILED: 422,
    ErrorCode.NO_TWIN: 409,
    ErrorCode.EPISODE_ACTIVE: 409,
    ErrorCode.NO_EPISODE: 409,
    ErrorCode.ROBOT_ELSEWHERE: 409,
    ErrorCode.NODE_LOST: 503,
    ErrorCode.ESTOP_INCOMPLETE: 503,
}


class Audit:
    """Who changes what over REST (specs/api.md, "Audit"): the caller, the route and the
    robots it acts on, recorded on each robot once the change is made: a refusal changes
    nothing and is not recorded, and nothing is recorded twice."""

    def __init__(self, user: str, route: str, robots: Iterable[Robot]) -> None:
        self.user = user
        self.route = route
        self.robots = list(robots)

    def also(self, robots: Iterable[Robot]) -> None:
        """Robots the request acts on that did not exist before it (a robot it creates)
        or that it named in its body (a group's members)."""
        self.robots.extend(robots)

    def record(self, detail: str) -> None:
        """Record it on each robot now, and never again (`detail`: the answer's status, or
        `requested` for a change after which there is nowhere to record it: a robot
        deleted, the recording stopped)."""
        robots, self.robots = self.robots, []
        for robot in robots:
            robot.audit(self.user, self.route, detail)


def record_audit_now() -> None:
    """Record the request's audit before the change it asks for, which leaves nowhere to
    record it (called once every check has passed, so a refusal is still not recorded)."""
    audit: Audit | None = g.get("audit")
    if audit is not None:
        audit.record("requested")


class OpenConnection(Protocol):
    """What the app knows of an open WebSocket connection."""

    role: str
    robots: tuple[str, ...]  # the robots it is a peer of, once counted open

    @property
    def queued_bytes(self) -> int:
        """Bytes waiting for the peer to read."""
        ...


class Hardware:
    """The hardware slaves attached over REST, by robot and slave id (and the physics twins,
    which twin cameras render)."""

    def __init__(self) -> None:
        self._drivers: dict[tuple[str, str], object] = {}
        self._twins: dict[tuple[str, str], object] = {}

    def add(self, robot_id: str, slave_id: str, driver: object) -> None:
        """Remember `driver` if it can be calibrated, or rendered."""
        if hasattr(driver, "calibration_status"):
            self._drivers[(robot_id, slave_id)] = driver
        if getattr(driver, "kind", None) == "physics-slave":
            self._twins[(robot_id, slave_id)] = driver

    def twin(self, robot_id: str, slave_id: str, attached: set[str]) -> Any:
        """The robot's physics slave (`slave_id`, or the only one when ""), or
        `ArenaError(NO_TWIN)`."""
        for key in [k for k in self._twins if k[1] not in attached and k[0] == robot_id]:
            del self._twins[key]  # detached since
        found = [
            driver
            for (rid, sid), driver in self._twins.items()
            if rid == robot_id and slave_id in ("", sid)
        ]
        if len(found) == 1:
            return found[0]
        which = f"physics slave {slave_id!r}" if slave_id else "physics slave"
        if not found:
            raise ArenaError(
                ErrorCode.NO_TWIN,
                f"Robot {robot_id!r} has no {which} to render: attach a physics-slave first.",
            )
        raise ArenaError(
            ErrorCode.NO_TWIN,
            f'Robot {robot_id!r} has several physics slaves: say which with "twin:SLAVE_ID".',
        )

    def servo_readings(self, robot_id: str, attached: set[str]) -> list[tuple[str, float, float]]:
        """Each servo of the robot's attached, running hardware slaves as its last telemetry
        read it, by joint: (joint, temperature C, load in percent of full torque); a joint
        on several arms, the first arm's."""
        found: dict[str, tuple[str, float, float]] = {}
        for (rid, sid), driver in self._drivers.items():
            servo_state = getattr(driver, "servo_state", None)
            if rid != robot_id or sid not in attached or servo_state is None:
                continue
            if not getattr(driver, "running", False):
                continue
            for joint, (celsius, load) in servo_state().items():
                found.setdefault(joint, (joint, celsius, load))
        return list(found.values())

    def find(self, robot_id: str, slave_id: str | None, attached: set[str]) -> tuple[str, Any]:
        """The robot's calibratable slave (`slave_id`, or the only one)."""
        for key in [k for k in self._drivers if k[1] not in attached and k[0] == robot_id]:
            del self._drivers[key]  # detached since
        found = [
            (sid, driver)
            for (rid, sid), driver in self._drivers.items()
            if rid == robot_id and (slave_id is None or sid == slave_id)
        ]
        if not found:
            which = f"slave {slave_id!r}" if slave_id else "a hardware slave"
            raise ArenaError(
                ErrorCode.NO_HARDWARE,
                f"Robot {robot_id!r} has no {which} to calibrate: attach a usb-slave first.",
            )
        if len(found) > 1:
            raise ArenaError(
                ErrorCode.INVALID_BODY,
                f'Robot {robot_id!r} has several hardware slaves: say which with "slave".',
            )
        return found[0]


@dataclass
class Parts:
    """The bodies the live parts were made from, by robot: its slaves' by slave id, its
    master's with the master's id. A part detached since is told by the robot itself (its
    snapshot), so nothing here needs to hear of detaches."""

    slaves: dict[str, dict[str, SlaveBody]] = field(default_factory=dict)
    masters: dict[str, tuple[str, MasterBody]] = field(default_factory=dict)

    def forget(self, robot_id: str) -> None:
        """The robot is gone."""
        self.slaves.pop(robot_id, None)
        self.masters.pop(robot_id, None)

    def slaves_of(self, robot: Robot) -> dict[str, SlaveBody]:
        """The bodies of the robot's slaves still attached, in the order they were."""
        attached = {slave.peer_id for slave in robot.snapshot().slaves}
        made = self.slaves.get(robot.robot_id, {})
        return {sid: body for sid, body in made.items() if sid in attached}

    def master_of(self, robot: Robot) -> MasterBody | None:
        """The body of the robot's master, if it is still the one made from it."""
        made = self.masters.get(robot.robot_id)
        master = robot.snapshot().master
        if made is None or master is None or master.peer_id != made[0]:
            return None
        return made[1]


class Declared(Protocol):
    """The setup of the configuration file on a running server (`arena.server.declared`)."""

    def pending_of(self, robot_id: str) -> list[dict[str, Any]]:
        """The robot's declared parts not up yet."""

    def not_ready(self) -> list[str]:
        """A sentence for each declared part not up."""

    def running(self) -> str:
        """The running setup in the file's form."""

    async def reload(self) -> dict[str, Any]:
        """Read the file again and apply its changes."""


class ArenaApp(QuartTrio):
    """The Quart app, carrying the manager, the settings and the metrics."""

    manager: RobotManager
    arena_config: ServerConfig
    metrics: Metrics
    shutting_down: trio.Event
    started_at: float
    recorder: Recorder
    hardware: Hardware
    groups: GroupRegistry
    #: The open WebSocket connections (their queued bytes show in /metrics).
    connections: set[OpenConnection]
    #: WebSockets open by caller (tenant, name), against `max_websockets_per_caller`.
    websockets_held: Counter[tuple[str, str]]
    #: Each robot's WebSocket master's link (round trip, jitter, stale commands), by robot.
    #: Each robot's WebSocket masters' links, by master id (an intervention makes two).
    master_links: dict[str, dict[str, LinkQuality]]
    #: The masters' acks encoded (one entry, shared: the acks of a millisecond are one text).
    acks: AckCache
    #: Robots' tenants, and which robots each caller sees (see `access`).
    access: AccessControl
    #: Verifies JSON Web Tokens, when the server takes them (see `identity`).
    tokens: TokenVerifier | None = None
    #: Which pages and host names may reach the server (see `origin`).
    origin_policy: OriginPolicy
    #: Every robot's cameras (`arena/sensors`).
    cameras: Cameras
    #: The simulated leader arms the server owns, and the leader arms attached to robots.
    sim_leaders: SimLeaders
    #: The bodies the live parts were made from (`GET /api/config` writes them back).
    parts: Parts
    #: The setup the configuration file declares, once brought up (None: no file).
    declared: Declared | None = None
    #: This node's membership of a fleet, with `--node`.
    fleet: FleetNode | None = None
    #: Marks REST calls another node of the fleet forwarded (known only in this process).
    fleet_secret: str = ""
    #: The server's own URL once it listens (told to the fleet).
    own_url: str | None = None
    #: The live Foxglove server, with `--foxglove-port`.
    foxglove: FoxgloveBridge | None = None
    #: Every robot a ROS 2 node, with `--ros2`.
    ros2: Ros2Bridge | None = None


def error_response(code: ErrorCode, message: str) -> tuple[dict[str, Any], int]:
    """The one error shape: `{"error": {"code", "message"}}` with a fitting status."""
    return {"error": {"code": str(code), "message": message}}, STATUS_FOR.get(code, 400)


def too_large(size: int | None) -> ArenaError:
    """A body over the limit, said as the WebSocket says it of a message (`size`: its bytes,
    when the request declared them)."""
    body = "The request body" if size is None else f"A request body of {size} bytes"
    return ArenaError(
        ErrorCode.MESSAGE_TOO_LARGE,
        f"{body} is over the {MAX_MESSAGE_BYTES}-byte limit (64 KiB): send less at a time.",
    )


async def refuse_any_body(route: str) -> None:
    """For a route that reads no body: a body with fields is refused, never ignored (an empty
    one, `{}` or `null` passes: clients send those for "nothing")."""
    raw = await request.get_data(cache=True)
    if len(raw) > MAX_MESSAGE_BYTES:
        raise too_large(len(raw))
    if not raw.strip():
        return
    try:
        value = msgspec.json.decode(raw)
    except (msgspec.DecodeError, RecursionError):
        raise ArenaError(
            ErrorCode.INVALID_JSON, f"{route} takes no body; this one is not JSON."
        ) from None
    if value is None or value == {}:
        return
    if isinstance(value, dict):
        names = ", ".join(repr(str(k)) for k in list(value)[:5])
        raise ArenaError(
            ErrorCode.UNKNOWN_FIELD,
            f"{route} takes no body, so {names} would be ignored: send none.",
        )
    raise ArenaError(ErrorCode.INVALID_BODY, f"{route} takes no body: send none.")


async def read_body(kind: Any, *, optional: bool = False) -> Any:
    """Decode and validate the JSON body as `kind`, or raise `ArenaError`: INVALID_BODY,
    UNKNOWN_FIELD (a field `kind` does not have), INVALID_JSON or MESSAGE_TOO_LARGE."""
    raw = await request.get_data(cache=False)
    if len(raw) > MAX_MESSAGE_BYTES:
        raise too_large(len(raw))
    if not raw.strip():
        if not optional:  # (msgspec would say "Input data was truncated", as of a cut body)
            raise ArenaError(
                ErrorCode.INVALID_JSON,
                "The body is empty: this route takes a JSON object (send it with "
                "Content-Type: application/json; see /docs for its fields).",
            )
        raw = b"{}"
    try:
        return msgspec.json.decode(raw, type=kind)
    except msgspec.ValidationError as exc:
        raise refusal(kind, raw, exc, what="body", code=ErrorCode.INVALID_BODY) from None
    except msgspec.DecodeError as exc:
        raise ArenaError(ErrorCode.INVALID_JSON, f"The body is not valid JSON: {exc}") from None
    except RecursionError:  # msgspec's own depth guard (found by the fuzz tests)
        raise ArenaError(ErrorCode.INVALID_JSON, "The body is nested too deeply.") from None
