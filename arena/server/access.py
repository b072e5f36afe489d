"""What each caller may reach: the role every REST route and WebSocket endpoint needs, and
which robots a caller sees (its tenant and its scope).

`ROLE_FOR` is the table of routes; `tests/test_access.py` checks that every route of the app
is in it (or public), so a new route cannot be added without deciding who may call it. A
robot outside a caller's tenant or scope is invisible in every listing and answers 404 as if
it did not exist: a caller learns nothing of robots that are not theirs.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterable
from typing import NamedTuple, TypeVar

from arena.protocol.errors import ArenaError, ErrorCode
from arena.protocol.rest import DEFAULT_TENANT
from arena.robot.groups import GroupRegistry
from arena.robot.manager import RobotManager
from arena.server.identity import Principal, Role

V, OP, A = Role.VIEWER, Role.OPERATOR, Role.ADMIN

#: Routes anyone may call, keys or not: the documentation, the dashboard's files and the
#: orchestrators' health probes.
PUBLIC_ROUTES = frozenset(
    {
        ("GET", "/docs"),
        ("GET", "/openapi.json"),
        ("GET", "/ui"),
        ("GET", "/ui/"),
        ("GET", "/ui/{name}"),
        ("GET", "/healthz"),
        ("GET", "/readyz"),
    }
)

#: (method, route) -> the least role that may call it. Stopping a robot needs no more than
#: seeing it; changing what it does needs an operator; changing what it is, an admin.
ROLE_FOR: dict[tuple[str, str], Role] = {
    ("GET", "/"): V,
    ("GET", "/metrics"): V,
    ("GET", "/api/robots"): V,
    ("POST", "/api/robots"): A,
    ("GET", "/api/robots/{robot_id}"): V,
    ("GET", "/api/robots/{robot_id}/status"): V,
    ("DELETE", "/api/robots/{robot_id}"): A,
    ("GET", "/api/sequences"): V,
    ("POST", "/api/robots/{robot_id}/play-sequence/{sequence_id}"): OP,
    ("POST", "/api/robots/{robot_id}/stop-sequence"): OP,
    ("POST", "/api/robots/{robot_id}/estop"): V,
    ("POST", "/api/robots/{robot_id}/reset"): OP,
    ("POST", "/api/estop"): V,
    ("GET", "/api/robots/{robot_id}/joints"): V,
    ("PUT", "/api/robots/{robot_id}/joints"): OP,
    ("GET", "/api/robots/{robot_id}/pose"): V,
    ("PUT", "/api/robots/{robot_id}/pose"): OP,
    ("POST", "/api/robots/{robot_id}/move"): OP,
    ("GET", "/api/robots/{robot_id}/teleop"): V,
    ("PUT", "/api/robots/{robot_id}/teleop"): A,
    ("GET", "/api/robots/{robot_id}/workspace"): V,
    ("PUT", "/api/robots/{robot_id}/workspace"): A,
    ("POST", "/api/robots/{robot_id}/slaves"): A,
    ("DELETE", "/api/robots/{robot_id}/slaves/{slave_id}"): A,
    ("POST", "/api/robots/{robot_id}/master"): OP,
    ("DELETE", "/api/robots/{robot_id}/master"): OP,
    ("POST", "/api/robots/{robot_id}/master/pause"): OP,
    ("POST", "/api/robots/{robot_id}/master/resume"): OP,
    ("POST", "/api/robots/{robot_id}/intervention"): OP,
    ("DELETE", "/api/robots/{robot_id}/intervention"): OP,
    ("GET", "/api/robots/{robot_id}/leader"): V,
    ("PUT", "/api/robots/{robot_id}/leader/joints"): OP,
    ("POST", "/api/robots/{robot_id}/compliance"): OP,
    ("DELETE", "/api/robots/{robot_id}/compliance"): OP,
    ("POST", "/api/robots/{robot_id}/replay"): OP,
    ("GET", "/api/robots/{robot_id}/policies"): V,
    ("GET", "/api/robots/{robot_id}/calibration"): V,
    ("POST", "/api/robots/{robot_id}/calibration/start"): A,
    ("POST", "/api/robots/{robot_id}/calibration/capture"): A,
    ("POST", "/api/robots/{robot_id}/calibration/finish"): A,
    ("POST", "/api/robots/{robot_id}/calibration/cancel"): A,
    ("GET", "/api/robots/{robot_id}/cameras"): V,
    ("POST", "/api/robots/{robot_id}/cameras"): A,
    ("GET", "/api/robots/{robot_id}/cameras/{name}"): V,
    ("DELETE", "/api/robots/{robot_id}/cameras/{name}"): A,
    ("GET", "/api/robots/{robot_id}/cameras/{name}/frame"): V,
    ("GET", "/api/robots/{robot_id}/cameras/{name}/stream"): V,
    ("GET", "/api/robots/{robot_id}/episodes"): V,
    ("POST", "/api/robots/{robot_id}/episodes/start"): OP,
    ("POST", "/api/robots/{robot_id}/episodes/stop"): OP,
    ("POST", "/api/robots/{robot_id}/episodes/discard"): OP,
    ("POST", "/api/robots/{robot_id}/highlight"): OP,
    ("GET", "/api/groups"): V,
    ("POST", "/api/groups"): A,
    ("GET", "/api/groups/{group_id}"): V,
    ("DELETE", "/api/groups/{group_id}"): A,
    ("POST", "/api/groups/{group_id}/estop"): V,
    ("POST", "/api/groups/{group_id}/reset"): OP,
    ("GET", "/api/robot-types"): V,
    ("GET", "/api/robot-types/{robot_type}"): V,
    ("GET", "/api/robot-types/{robot_type}/urdf"): V,
    ("GET", "/api/robot-types/{robot_type}/files/{name}"): V,
    ("GET", "/api/recordings"): V,
    ("POST", "/api/recordings"): A,
    ("POST", "/api/recordings/{name}/stop"): A,
    ("GET", "/api/recordings/{name}"): V,
    ("GET", "/api/recordings/{name}/joints"): V,
    ("GET", "/api/recordings/{name}/file"): V,
    ("GET", "/api/config"): A,
    ("POST", "/api/config/reload"): A,
    ("GET", "/api/fleet/nodes"): V,
    ("GET", "/api/fleet/robots"): V,
    ("POST", "/api/fleet/estop"): V,
}

#: WebSocket endpoints by role: a master commands, a slave is a driver, a viewer watches.
WS_ROLE_FOR: dict[str, Role] = {"master": OP, "slave": A, "viewer": V}

#: `<robot_id>`, `<path:name>` in a rule: `{robot_id}`, `{name}` as OpenAPI writes them.
_RULE_PARAMETER = re.compile(r"<(?:\w+:)?(\w+)>")


def route_of(method: str, rule: str) -> tuple[str, str]:
    """(method, route) of a request's rule as `ROLE_FOR` names it (HEAD is GET)."""
    method = "GET" if method.upper() in ("HEAD", "OPTIONS") else method.upper()
    return method, _RULE_PARAMETER.sub(r"{\1}", rule)


def needed_role(method: str, rule: str | None) -> Role | None:
    """The role a request needs, None for a public route. A path with no route (a 404)
    needs a viewer, so that strangers learn nothing; a route missing from the table needs
    an admin (the test makes that never happen)."""
    if rule is None:
        return V
    route = route_of(method, rule)
    if route in PUBLIC_ROUTES:
        return None
    return ROLE_FOR.get(route, A)


def reads_recordings(principal: Principal) -> bool:
    """The caller is of the default tenant and its scope is every robot: it may turn
    recording on and off, and read files whose robots are not known."""
    return principal.tenant == DEFAULT_TENANT and principal.unlimited


def server_admin(principal: Principal) -> bool:
    """The whole server's admin: an admin of the default tenant with every robot in scope.
    Only it may name files outside the tenants' folders (a path, `lerobot:ID`)."""
    return principal.role >= Role.ADMIN and reads_recordings(principal)


RobotLike = TypeVar("RobotLike")


class Contents(NamedTuple):
    """Whose a recording file is (None: not said, a file of an older version) and the
    robots in it (None: not known)."""

    tenant: str | None
    robots: frozenset[str] | None


class AccessControl:
    """Robots' tenants and who sees which robot and group."""

    def __init__(self, manager: RobotManager, groups: GroupRegistry) -> None:
        self.manager = manager
        self.groups = groups
        #: The tenant of each robot deleted since the start (a live robot says its own).
        self.tenants: dict[str, str] = {}
        #: The tenant of a robot of another node of the fleet (`fleet_api` sets it).
        self.tenant_elsewhere: Callable[[str], str | None] = lambda robot_id: None

    def tenant_of(self, robot_id: str) -> str:
        """The robot's tenant: a robot here says its own, a robot of another node is as that
        node says, and a robot deleted here is as it was (after the others: its id may be
        another node's robot now)."""
        robot = self.manager.find(robot_id)
        if robot is not None:
            return robot.tenant
        tenant = self.tenant_elsewhere(robot_id)
        if tenant is None:
            tenant = self.tenants.get(robot_id)
        return DEFAULT_TENANT if tenant is None else tenant

    def sees(self, principal: Principal, robot_id: str) -> bool:
        """The robot is of the caller's tenant and in its scope."""
        return self.tenant_of(robot_id) == principal.tenant and self.in_scope(principal, robot_id)

    def sees_group(self, principal: Principal, members: Iterable[str]) -> bool:
        """A group is seen when each of its members is."""
        return all(self.sees(principal, robot_id) for robot_id in members)

    def visible(
        self, principal: Principal, items: Iterable[RobotLike], key: str = "robot_id"
    ) -> list[RobotLike]:
        """The items (robots, or anything with a robot id as `key`) the caller sees."""
        return [item for item in items if self.sees(principal, str(getattr(item, key)))]

    def check_robot(self, principal: Principal, robot_id: str) -> None:
        """UNKNOWN_ROBOT, worded as for a robot that does not exist, unless the caller sees
        it (a robot of another node of the fleet too: it is of the default tenant here)."""
        if not self.sees(principal, robot_id):
            raise ArenaError(ErrorCode.UNKNOWN_ROBOT, f"No robot with id {robot_id!r}.")

    def check_group(self, principal: Principal, group_id: str) -> None:
        """UNKNOWN_GROUP, as for a group that does not exist, unless the caller sees every
        member (or it is no group of its tenant: the route says so)."""
        group = self.groups.find(group_id, principal.tenant)
        if group is None:
            return
        if not self.sees_group(principal, group.members):
            raise ArenaError(ErrorCode.UNKNOWN_GROUP, f"No group {group_id!r}.")

    def sees_recording(self, principal: Principal, contents: Contents) -> bool:
        """A recording is the caller's when it is of the caller's tenant and every robot in
        it is in the caller's scope. A file of an older version (no tenant said) is the
        caller's when it sees every robot in it now (a deleted robot keeps its tenant). A
        file whose robots are not known (none in its metadata, or cut short where they
        were) is read only by a caller unconfined in its tenant (the default tenant for an
        older file: `reads_recordings`)."""
        tenant, robots = contents
        if tenant is None:
            if not robots:
                return reads_recordings(principal)
            return all(self.sees(principal, robot_id) for robot_id in robots)
        if tenant != principal.tenant:
            return False
        if principal.unlimited:
            return True
        return bool(robots) and all(self.in_scope(principal, r) for r in robots or ())

    def in_scope(self, principal: Principal, robot_id: str) -> bool:
        """The robot's id, or a group it is in, is in the caller's scope (tenants aside)."""
        if principal.unlimited:
            return True
        groups = [g.group_id for g in self.groups.all(principal.tenant) if robot_id in g.members]
        return principal.covers(robot_id, groups)
