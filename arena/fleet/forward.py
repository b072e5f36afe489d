"""REST calls for a robot of another node: carried to that node (the `http` service) and run
there by its own app, so its rules and its robot answer, as if the client had called it. The
caller goes along (its name, role, tenant and scope as checked by the client's node, never its
key or token), so the robot's node checks it again against what it knows of its robots."""

from __future__ import annotations

import base64
import json
from collections.abc import Awaitable, Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from arena.fleet.node import FleetNode

#: Request headers a forwarded call keeps.
KEPT_HEADERS = ("content-type", "accept")
#: Seconds the robot's node has to answer.
FORWARD_TIMEOUT = 10.0


@dataclass(frozen=True, slots=True)
class Call:
    """A REST request, as it crosses the fleet."""

    method: str
    path: str
    query: str
    headers: dict[str, str]
    body: bytes
    #: Who called, as claims (`Principal.to_wire`); None from a node of an older version.
    caller: dict[str, Any] | None = None

    def to_wire(self) -> dict[str, Any]:
        """As the `http` service's payload (the body in base64)."""
        return {
            "method": self.method,
            "path": self.path,
            "query": self.query,
            "headers": self.headers,
            "body": base64.b64encode(self.body).decode(),
            "caller": self.caller,
        }

    @classmethod
    def from_wire(cls, call: Mapping[str, Any]) -> Call:
        """Read the `http` service's payload."""
        return cls(
            str(call["method"]),
            str(call["path"]),
            str(call.get("query") or ""),
            dict(call.get("headers", {})),
            base64.b64decode(call.get("body", "")),
            call.get("caller"),
        )


@dataclass(frozen=True, slots=True)
class Answer:
    """A REST response, as it crosses the fleet."""

    status: int
    content_type: str | None
    body: bytes

    def to_wire(self) -> dict[str, Any]:
        """As the `http` service's answer (the body in base64)."""
        return {
            "status": self.status,
            "content_type": self.content_type,
            "body": base64.b64encode(self.body).decode(),
        }

    @classmethod
    def from_wire(cls, answer: Mapping[str, Any]) -> Answer:
        """Read the `http` service's answer."""
        return cls(int(answer["status"]), answer["content_type"], base64.b64decode(answer["body"]))


def request_call(
    method: str,
    path: str,
    query: str,
    headers: Iterable[tuple[str, str]],
    body: bytes,
    caller: dict[str, Any] | None = None,
) -> Call:
    """The call for a request, with only the headers that matter to the robot's node (the
    key or token never: `caller` says who it proved to be)."""
    kept = {k: v for k, v in headers if k.lower() in KEPT_HEADERS}
    return Call(method, path, query, kept, body, caller)


async def forward(fleet: FleetNode, node: str, call: Call) -> Answer:
    """Run `call` on `node` and return its answer."""
    return Answer.from_wire(await fleet.ask(node, "http", call.to_wire(), timeout=FORWARD_TIMEOUT))


def http_service(
    run: Callable[[Call], Awaitable[Answer]],
) -> Callable[[bytes], Awaitable[dict[str, Any]]]:
    """The `http` service of the robot's node: each call run by `run` (its own app)."""

    async def serve(payload: bytes) -> dict[str, Any]:
        return (await run(Call.from_wire(json.loads(payload)))).to_wire()

    return serve
