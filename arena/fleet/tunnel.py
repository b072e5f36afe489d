"""A WebSocket carried to the node that owns its robot, through a Zenoh `Tunnel`.

The client's node checks the client's key or token and pumps its frames into the tunnel
(`carry`); the robot's node serves the connection with its own handlers, through a
`TunnelSocket` that stands in for the socket, so ownership, takeover, e-stops, rate limits and
acknowledgments are that node's, as if the client had connected there. The caller goes along
(its claims, never its token), and the robot's node checks its tenant and scope again. Frames
in a tunnel: `t` + text, `c` + close JSON; an empty frame (local only) means the other node is
gone.
"""

from __future__ import annotations

import json
from collections.abc import Awaitable, Callable
from typing import Any, Protocol

import trio

from arena.fleet.node import FleetNode, Tunnel
from arena.protocol.errors import ArenaError, ErrorCode
from arena.protocol.ws_frames import UpgradeRequest, WebSocketClosed

#: Tunnel frames `TunnelSocket.next_in_hand` looks through for a message.
IN_HAND = 32
#: The roles a tunnel carries, and the path each is served at.
ROLES = ("master", "slave", "viewer")


def text_frame(text: str) -> bytes:
    """A WebSocket text message, as a tunnel frame."""
    return b"t" + text.encode("utf-8")


def close_frame(code: int, reason: str = "") -> bytes:
    """A WebSocket close, as a tunnel frame."""
    return b"c" + json.dumps({"code": code, "reason": reason}).encode()


def _closed_by(data: bytes) -> WebSocketClosed:
    close = json.loads(data[1:] or b"{}")
    return WebSocketClosed(int(close.get("code", 1000)), str(close.get("reason", "")))


class TunnelSocket:
    """The robot's node's end of a tunnel, as the WebSocket handlers see a socket. The
    client's node checked the key: `trusted`. Never backlogged: a tunnel drops what its
    reader cannot take (`Tunnel.deliver`)."""

    trusted = True
    backlogged = False
    queued_bytes = 0

    def __init__(self, tunnel: Tunnel, request: UpgradeRequest) -> None:
        self.tunnel = tunnel
        self.request = request
        self.close_sent = False

    async def receive(self) -> str:
        """The next text message; raises `WebSocketClosed` at the end of the tunnel."""
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
        for _ in range(IN_HAND):
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
            self.close_sent = True
            raise _closed_by(data)
        return None

    def holds_more(self) -> bool:
        """True when a message waits in the inbox."""
        return self.tunnel.inbox.statistics().current_buffer_used > 0

    def offer(self, *texts: str, whole: bool = False) -> bool:
        """Send at once (as `WebSocket.offer`; a tunnel always takes them)."""
        for text in texts:  # (each goes into the tunnel at once, `whole` or not)
            self.tunnel.send(text_frame(text))
        return True

    async def send(self, *texts: str) -> None:
        """Send at once."""
        self.offer(*texts)
        await trio.lowlevel.checkpoint()

    def send_nowait(self, text: str) -> None:
        """Send at once."""
        self.offer(text)

    def send_now(self, *texts: str) -> bool:
        """Send at once."""
        return self.offer(*texts)

    def close_nowait(self, code: int, reason: str = "") -> None:
        """Send the close, once."""
        if not self.close_sent:
            self.close_sent = True
            self.tunnel.send(close_frame(code, reason))

    async def wait_drained(self) -> None:
        """Never returns: never backlogged, nothing to wait for."""
        await trio.sleep_forever()


def serve_tunnel(
    fleet: FleetNode,
    call: dict[str, Any],
    serve: Callable[[TunnelSocket, str, str], Awaitable[None]],
) -> dict[str, Any]:
    """The robot's node: a client of another node asked for a tunnel (`call`); `serve`
    (socket, role, robot id) runs in the fleet's nursery until the connection ends."""
    robot_id, role = str(call["robot"]), str(call["role"])
    if role not in ROLES:
        raise ArenaError(ErrorCode.INVALID_VALUE, f"No such role {role!r}.")
    tunnel = fleet.open_tunnel(str(call["origin"]), str(call["tunnel"]), serving=True)
    path = f"/ws/robots/{robot_id}/state" if role == "viewer" else f"/ws/{role}/{robot_id}"
    socket = TunnelSocket(tunnel, UpgradeRequest(path, dict(call.get("args", {})), {}))

    async def run() -> None:
        try:
            await serve(socket, role, robot_id)
        finally:
            socket.close_nowait(1000, "")
            tunnel.close()

    assert fleet.nursery is not None
    fleet.nursery.start_soon(run)
    return {"tunnel": tunnel.tunnel_id, "node": fleet.name}


class ClientSocket(Protocol):
    """What `carry` reads from: the client's WebSocket on this node."""

    async def receive(self) -> str | bytes:
        """The next message; raises `WebSocketClosed` once the client has closed."""
        ...


class ClientEnd(Protocol):
    """The client's connection on this node, as `carry` uses it."""

    @property
    def ws(self) -> ClientSocket:
        """The client's socket."""
        ...

    async def send_error(self, code: ErrorCode | str, message: str) -> None:
        """Send an `error` message."""
        ...

    async def refuse(self, error: ArenaError) -> None:
        """Send the error, then close."""
        ...

    async def close(self, code: int, reason: str = "") -> None:
        """Close once."""
        ...


async def open_to(
    fleet: FleetNode,
    node: str,
    robot_id: str,
    role: str,
    args: dict[str, str],
    caller: dict[str, Any] | None = None,
) -> Tunnel:
    """The client's node: open a tunnel to `node` for a client of `robot_id` in `role`
    (`args`: its query parameters, the key left out: this node checked it; `caller`: who
    the client proved to be, as claims)."""
    tunnel = fleet.open_tunnel(node, serving=False)
    call = {
        "tunnel": tunnel.tunnel_id,
        "origin": fleet.name,
        "role": role,
        "robot": robot_id,
        "args": {k: v for k, v in args.items() if k != "token"},
        "caller": caller,
    }
    try:
        await fleet.ask(node, "tunnel", call)
    except BaseException:
        tunnel.close()
        raise
    return tunnel


async def carry(
    client: ClientEnd,
    tunnel: Tunnel,
    robot_id: str,
    deliver: Callable[[str], Awaitable[None]],
    nursery: trio.Nursery,
) -> None:
    """Pump the client's frames into `tunnel` (a task in `nursery`, cancelled when the client
    closes) and the robot's node's messages to `deliver`, until either end closes."""

    async def to_robot() -> None:
        while True:
            try:
                frame = await client.ws.receive()
            except WebSocketClosed as closed:
                tunnel.send(b"c" + json.dumps({"code": closed.code}).encode())
                nursery.cancel_scope.cancel()
                return
            if isinstance(frame, str):
                tunnel.send(text_frame(frame))
            else:
                await client.send_error(
                    ErrorCode.BINARY_NOT_SUPPORTED, "Send JSON text frames, not binary frames."
                )

    nursery.start_soon(to_robot)
    async for data in tunnel.inbox:
        if not data:
            await client.refuse(
                ArenaError(
                    ErrorCode.NODE_LOST,
                    f"Node {tunnel.peer!r}, which owns robot {robot_id!r}, left the fleet.",
                )
            )
            return
        if data[:1] == b"c":
            closed = _closed_by(data)
            await client.close(closed.code, closed.reason)
            return
        await deliver(data[1:].decode("utf-8"))
