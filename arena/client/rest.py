"""The REST client: `Arena` (blocking, for plain scripts) and `AsyncArena` (awaited: it runs on
trio or asyncio, as httpx does), with every endpoint written once in `Endpoints`."""

from __future__ import annotations

from collections.abc import Awaitable, Mapping
from typing import Any, Generic, Self, TypeVar
from urllib.parse import quote

import httpx

from arena.client.errors import ArenaClientError

T = TypeVar("T")


class Endpoints(Generic[T]):
    """Every REST call once; `_call` makes it blocking (`Arena`) or awaitable (`AsyncArena`)."""

    def _call(self, method: str, path: str, body: Any = None) -> T:
        raise NotImplementedError

    def status(self) -> T:
        """`GET /`: the server's status."""
        return self._call("GET", "/")

    def robots(self) -> T:
        """Every robot."""
        return self._call("GET", "/api/robots")

    def robot(self, robot_id: str) -> T:
        """One robot: state, peers, joints."""
        return self._call("GET", f"/api/robots/{quote(robot_id)}")

    def create_robot(self, robot_id: str | None = None, robot_type: str = "so-arm100") -> T:
        """Create a robot."""
        body = {"robot_type": robot_type, **({"id": robot_id} if robot_id else {})}
        return self._call("POST", "/api/robots", body)

    def delete_robot(self, robot_id: str) -> T:
        """Delete a robot (its peers are let go)."""
        return self._call("DELETE", f"/api/robots/{quote(robot_id)}")

    def attach_slave(self, robot_id: str, config: Mapping[str, Any]) -> T:
        """Attach a slave driver (`{"type": "mock-slave"}`, `usb-slave`, `websocket-slave`)."""
        return self._call("POST", f"/api/robots/{quote(robot_id)}/slaves", dict(config))

    def detach_slave(self, robot_id: str, slave_id: str) -> T:
        """Detach one slave (a slave that just leaves counts as lost, which e-stops)."""
        return self._call("DELETE", f"/api/robots/{quote(robot_id)}/slaves/{quote(slave_id)}")

    def attach_master(self, robot_id: str, config: Mapping[str, Any]) -> T:
        """Attach a master driver (`mock-sequence`, `replay`, `usb-master`, `remote-server`)."""
        return self._call("POST", f"/api/robots/{quote(robot_id)}/master", dict(config))

    def detach_master(self, robot_id: str) -> T:
        """Detach the robot's master."""
        return self._call("DELETE", f"/api/robots/{quote(robot_id)}/master")

    def estop(self, robot_id: str | None = None, reason: str | None = None) -> T:
        """E-stop one robot, or every robot when `robot_id` is None."""
        path = f"/api/robots/{quote(robot_id)}/estop" if robot_id else "/api/estop"
        return self._call("POST", path, {"reason": reason} if reason else {})

    def reset(self, robot_id: str) -> T:
        """Clear a robot's e-stop."""
        return self._call("POST", f"/api/robots/{quote(robot_id)}/reset")

    def set_joints(self, robot_id: str, joints: Mapping[str, float]) -> T:
        """Manual control (no master): move joints to these degrees."""
        entries = [{"name": n, "value": v} for n, v in joints.items()]
        return self._call("PUT", f"/api/robots/{quote(robot_id)}/joints", {"joints": entries})

    def groups(self) -> T:
        """Every robot group."""
        return self._call("GET", "/api/groups")

    def create_group(self, group_id: str, members: list[str], *, stop_together: bool = False) -> T:
        """Create a group one master can drive."""
        body = {"id": group_id, "members": members, "stopTogether": stop_together}
        return self._call("POST", "/api/groups", body)

    def group(self, group_id: str) -> T:
        """One group with its members' states."""
        return self._call("GET", f"/api/groups/{quote(group_id)}")

    def estop_group(self, group_id: str, reason: str | None = None) -> T:
        """E-stop every member of a group."""
        body = {"reason": reason} if reason else {}
        return self._call("POST", f"/api/groups/{quote(group_id)}/estop", body)

    def reset_group(self, group_id: str) -> T:
        """Clear every member's e-stop."""
        return self._call("POST", f"/api/groups/{quote(group_id)}/reset")

    def delete_group(self, group_id: str) -> T:
        """Delete a group (its robots stay)."""
        return self._call("DELETE", f"/api/groups/{quote(group_id)}")

    def recordings(self) -> T:
        """Recordings and the recorder's status."""
        return self._call("GET", "/api/recordings")

    def fleet_nodes(self) -> T:
        """The nodes of this server's fleet (`--node`): name, alive, version, robots."""
        return self._call("GET", "/api/fleet/nodes")

    def fleet_robots(self) -> T:
        """Every robot of every node of the fleet, with its node and state; each one can be
        opened (REST or WebSocket) through this server whichever node owns it."""
        return self._call("GET", "/api/fleet/robots")

    def fleet_estop(self, reason: str | None = None) -> T:
        """E-stop every robot of every node; each node's acknowledgment and time. Raises
        `ArenaClientError` ESTOP_INCOMPLETE (503) naming any node that failed or did not answer."""
        return self._call("POST", "/api/fleet/estop", {"reason": reason} if reason else {})


def _unreachable(url: httpx.URL, error: Exception) -> ArenaClientError:
    return ArenaClientError("UNREACHABLE", f"cannot reach {url}: {error or type(error).__name__}")


def _answer(response: httpx.Response) -> Any:
    if response.status_code >= 400:
        try:
            error = response.json().get("error") or {}
            code, message = error.get("code", "HTTP_ERROR"), error.get("message", response.text)
        except ValueError:
            code, message = "HTTP_ERROR", response.text
        raise ArenaClientError(code, message, response.status_code)
    return response.json() if response.content else None


class Arena(Endpoints[Any]):
    """Blocking REST client, for plain scripts. Errors raise `ArenaClientError`."""

    def __init__(self, base_url: str, api_key: str | None = None, timeout: float = 10.0) -> None:
        headers = {"Authorization": f"Bearer {api_key}"} if api_key else {}
        self.http = httpx.Client(base_url=base_url, headers=headers, timeout=timeout)

    def _call(self, method: str, path: str, body: Any = None) -> Any:
        try:
            response = self.http.request(method, path, json=body)
        except httpx.TransportError as error:
            raise _unreachable(self.http.base_url, error) from None
        return _answer(response)

    def close(self) -> None:
        """Close the HTTP connections."""
        self.http.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class AsyncArena(Endpoints[Awaitable[Any]]):
    """The same REST client for trio code: every method is awaited."""

    def __init__(self, base_url: str, api_key: str | None = None, timeout: float = 10.0) -> None:
        headers = {"Authorization": f"Bearer {api_key}"} if api_key else {}
        self.http = httpx.AsyncClient(base_url=base_url, headers=headers, timeout=timeout)

    async def _request(self, method: str, path: str, body: Any) -> Any:
        try:
            response = await self.http.request(method, path, json=body)
        except httpx.TransportError as error:
            raise _unreachable(self.http.base_url, error) from None
        return _answer(response)

    def _call(self, method: str, path: str, body: Any = None) -> Awaitable[Any]:
        return self._request(method, path, body)

    async def aclose(self) -> None:
        """Close the HTTP connections."""
        await self.http.aclose()

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()
