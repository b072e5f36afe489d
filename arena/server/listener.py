"""The listening sockets: WebSocket upgrades to Arena's own transport, the rest to hypercorn.

The first bytes of each connection decide. A `GET /ws/...` asking for a WebSocket on a path
the router knows is answered here (`ws_transport`); anything else (REST, the dashboard, HTTP/2)
is handed, with the bytes already read, to hypercorn's connection handler, exactly as
hypercorn's own `serve` would. Hypercorn and Quart cost some 100 us per WebSocket frame
(wsproto, the ASGI wrapper, a task hop each way, a system call per frame); the robot's hot
endpoints skip all of it.

Every connection counts against two bounds (`ConnectionLimits`): so many from one client
address, so many in all. One beyond either is answered 503 OVERLOADED and closed, unless its
first request is an e-stop (up to `ESTOP_RESERVE` such connections are read, for 2 s each, to
see): so no client can take the file descriptors the REST e-stop needs, nor keep an operator on
its own address (a proxy, the same machine) from stopping the robots. An
HTTP connection is closed after a response to `Connection: close`, and once it has been idle
(no request under way) for hypercorn's `keep_alive_timeout`; one that says nothing at all is
closed after the same time.

This uses hypercorn's per-connection `TCPServer`, `Lifespan` and `WorkerContext`, which are
not public API: pyproject pins hypercorn below 0.19.
"""

from __future__ import annotations

import contextlib
import logging
import math
import re
from collections import Counter
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from functools import partial
from typing import Any
from urllib.parse import parse_qsl, unquote, urlsplit

import msgspec
import trio
from hypercorn.config import Config as HypercornConfig
from hypercorn.config import Sockets
from hypercorn.events import Closed, Event, Updated
from hypercorn.trio.lifespan import Lifespan
from hypercorn.trio.tcp_server import TCPServer
from hypercorn.trio.worker_context import WorkerContext
from hypercorn.typing import ConnectionState
from hypercorn.utils import repr_socket_addr, wrap_app

from arena.protocol import ws_frames
from arena.protocol.errors import ArenaError, ErrorCode
from arena.protocol.ws_frames import UpgradeRequest
from arena.server.read_poller import ReadPoller
from arena.server.ws_transport import WebSocket

log = logging.getLogger(__name__)

WebSocketHandler = Callable[[WebSocket], Awaitable[None]]
#: Picks the handler for an upgrade request, or None to let hypercorn answer it.
Router = Callable[[UpgradeRequest], WebSocketHandler | None]
#: Serves a long-lived HTTP response on the raw stream (a camera's MJPEG stream).
StreamHandler = Callable[[trio.abc.Stream], Awaitable[None]]
StreamRouter = Callable[[UpgradeRequest], StreamHandler | None]

_WS_PREFIX = b"GET /ws/"
_STREAM_PREFIX = b"GET /api/robots/"
_PREFIXES = (_WS_PREFIX, _STREAM_PREFIX)
MAX_HEAD_BYTES = 16 * 1024
HEAD_TIMEOUT = 10.0
#: Connections beyond a bound kept, at most, to see whether they carry an e-stop (then served),
#: and how long each has to say so; anything else is turned away.
ESTOP_RESERVE = 8
ESTOP_HEAD_TIMEOUT = 2.0
#: The request lines of the e-stops: a robot's, a group's, every robot's, the fleet's.
ESTOP_REQUEST = re.compile(rb"POST /api/(?:(?:robots|groups)/[^/ ?]+/|fleet/)?estop[ ?]")
#: How long a closed WebSocket waits for the peer's close frame and for its last bytes to go.
CLOSE_TIMEOUT = 2.0


@dataclass(frozen=True)
class ConnectionLimits:
    """The most connections (HTTP and WebSocket alike) open at once: `per_client` from one
    client address, `total` from all."""

    total: int = 1024
    per_client: int = 256


class _Server(TCPServer):
    """Hypercorn's connection, with its ends bounded and shielded.

    Hypercorn ends a response in the task of the request, and quart-trio cancels that task as
    soon as the response is out (hypercorn's `http.disconnect` wakes it): the close after a
    `Connection: close` and the restart of the keep-alive timer, begun there, were cancelled
    at their first checkpoint, and the socket stayed open until the client left. Those two
    run shielded here; every close is bounded (a TLS peer that reads nothing cannot hold its
    `close_notify`), then forced.
    """

    async def protocol_send(self, event: Event) -> None:
        if isinstance(event, Closed | Updated):
            with trio.CancelScope(shield=True), trio.move_on_after(CLOSE_TIMEOUT) as bounded:
                await super().protocol_send(event)
            if bounded.cancelled_caught:
                await trio.aclose_forcefully(self.stream)
        else:
            await super().protocol_send(event)

    async def _close(self) -> None:
        try:
            with trio.move_on_after(CLOSE_TIMEOUT):
                await super()._close()
        finally:
            await trio.aclose_forcefully(self.stream)

    async def _initiate_server_close(self) -> None:
        try:
            with trio.move_on_after(CLOSE_TIMEOUT):
                await super()._initiate_server_close()
        finally:
            await trio.aclose_forcefully(self.stream)


class _Replay:
    """A stream that first gives back bytes already read from it (for hypercorn)."""

    def __init__(self, stream: trio.abc.Stream, head: bytes) -> None:
        self._stream = stream
        self._head = head

    async def receive_some(self, max_bytes: int | None = None) -> bytes | bytearray:
        if self._head:
            head, self._head = self._head, b""
            await trio.lowlevel.checkpoint()
            return head
        return await self._stream.receive_some(max_bytes)

    def __getattr__(self, name: str) -> Any:  # send_all, aclose, socket, do_handshake...
        return getattr(self._stream, name)


def parse_upgrade(head: bytes) -> UpgradeRequest | None:
    """The upgrade request in an HTTP/1.1 request head, or None if it is not one."""
    request = parse_get(head)
    if request is None or request.headers.get("upgrade", "").lower() != "websocket":
        return None
    return request


def parse_get(head: bytes) -> UpgradeRequest | None:
    """The GET request in an HTTP/1.1 request head, or None if it is not one."""
    lines = head.decode("latin-1").split("\r\n")
    parts = lines[0].split(" ")
    if len(parts) != 3 or parts[0] != "GET" or not parts[2].startswith("HTTP/1."):
        return None
    headers: dict[str, str] = {}
    for line in lines[1:]:
        name, colon, value = line.partition(":")
        if not colon:
            continue
        key = name.strip().lower()
        headers[key] = f"{headers[key]}, {value.strip()}" if key in headers else value.strip()
    target = urlsplit(parts[1])
    args: dict[str, str] = {}
    for key, value in parse_qsl(target.query, keep_blank_values=True):
        args.setdefault(key, value)
    return UpgradeRequest(unquote(target.path), args, headers)


def _handshake_problem(request: UpgradeRequest) -> str | None:
    tokens = request.headers.get("connection", "").split(",")
    if "upgrade" not in {token.strip().lower() for token in tokens}:
        return "The Connection header must include 'Upgrade'."
    if request.headers.get("sec-websocket-version") != "13":
        return "Only WebSocket version 13 is spoken here."
    if not ws_frames.valid_client_key(request.headers.get("sec-websocket-key", "")):
        return "Sec-WebSocket-Key must be 16 bytes in base64."
    return None


def _client_address(stream: trio.abc.Stream) -> str:
    """The address of the client at the other end (its IP, without the port)."""
    transport: Any = getattr(stream, "transport_stream", stream)  # (TLS: the socket beneath)
    try:
        peer = transport.socket.getpeername()
    except (AttributeError, OSError):
        return "unknown"
    return str(peer[0]) if isinstance(peer, tuple) else str(peer)


def http_error(status: str, message: str, code: ErrorCode = ErrorCode.INVALID_MESSAGE) -> bytes:
    """A whole HTTP/1.1 error response in Arena's error shape, closing the connection."""
    body = msgspec.json.encode({"error": {"code": str(code), "message": message}})
    head = (
        f"HTTP/1.1 {status}\r\nContent-Type: application/json\r\n"
        f"Content-Length: {len(body)}\r\nConnection: close\r\n\r\n"
    )
    return head.encode("latin-1") + body


class ArenaListener:
    """Serves an ASGI app (hypercorn) with Arena's WebSocket routes in front of it."""

    def __init__(
        self,
        app: Any,
        config: HypercornConfig,
        router: Router,
        max_message: int,
        *,
        queue_bytes: int = 16 * 1024,
        stream_router: StreamRouter | None = None,
        sockets: Sockets | None = None,
        limits: ConnectionLimits | None = None,
    ) -> None:
        self.config = config
        self.limits = limits or ConnectionLimits()
        #: Connections open now, by client address (the sum: `open_connections`).
        self.clients: Counter[str] = Counter()
        self.open_connections = 0
        self.turned_away = 0  # connections refused beyond a bound, since the start
        self.reserved = 0  # connections beyond a bound being looked at for an e-stop
        self._next_warning = -math.inf
        #: Sockets bound beforehand (`run.bind`); None: bind them in `serve`.
        self.sockets = sockets
        self.router = router
        self.stream_router = stream_router
        self.max_message = max_message
        self.queue_bytes = queue_bytes
        self._app = wrap_app(app, config.wsgi_max_body_size, "asgi")
        self._lifespan_state: dict[str, Any] = {}
        self._context = WorkerContext(None)
        self._poller = ReadPoller() if ReadPoller.available() else None

    async def serve(
        self,
        shutdown_trigger: Callable[[], Awaitable[None]],
        *,
        task_status: trio.TaskStatus[list[str]] = trio.TASK_STATUS_IGNORED,
    ) -> None:
        """Bind, serve until `shutdown_trigger` returns, then give connections the grace time."""
        lifespan = Lifespan(self._app, self.config, self._lifespan_state)
        async with trio.open_nursery() as lifespan_nursery:
            await lifespan_nursery.start(lifespan.handle_lifespan)
            await lifespan.wait_for_startup()
            if self._poller is not None:  # outlives every connection: cancelled below
                lifespan_nursery.start_soon(self._poller.run)
            ssl_context = self.config.create_ssl_context()
            scheme = "https" if ssl_context else "http"
            sockets = self.sockets or self.config.create_sockets()
            listeners, urls = [], []
            for sock in [*sockets.secure_sockets, *sockets.insecure_sockets]:
                sock.listen(self.config.backlog)
                listeners.append(trio.SocketListener(trio.socket.from_stdlib_socket(sock)))
                urls.append(f"{scheme}://{repr_socket_addr(sock.family, sock.getsockname())}")
            async with trio.open_nursery() as connections:
                async with trio.open_nursery() as accepting:
                    accepting.start_soon(
                        partial(
                            trio.serve_listeners,
                            partial(self._connection, ssl_context=ssl_context),
                            listeners,
                            handler_nursery=connections,
                        )
                    )
                    task_status.started(urls)
                    await shutdown_trigger()
                    accepting.cancel_scope.cancel()
                await self._context.terminated.set()
                connections.cancel_scope.deadline = (
                    trio.current_time() + self.config.graceful_timeout
                )
            await lifespan.wait_for_shutdown()
            lifespan_nursery.cancel_scope.cancel()

    async def _connection(self, stream: trio.abc.Stream, ssl_context: Any) -> None:
        client = _client_address(stream)
        limits = self.limits
        if self.open_connections >= limits.total or self.clients[client] >= limits.per_client:
            if self.reserved >= ESTOP_RESERVE:
                await self._turn_away(stream, ssl_context is not None, client)
                return
            self.reserved += 1  # an operator's e-stop still passes a leaky client's bound
            try:
                await self._serve_connection(stream, ssl_context, estop_only=client)
            finally:
                self.reserved -= 1
            return
        self.clients[client] += 1
        self.open_connections += 1
        try:
            await self._serve_connection(stream, ssl_context)
        finally:
            self.open_connections -= 1
            self.clients[client] -= 1
            if not self.clients[client]:
                del self.clients[client]

    async def _turn_away(self, stream: trio.abc.Stream, tls: bool, client: str) -> None:
        """A connection beyond a bound: 503 (in plain HTTP; a TLS one is just closed), then
        closed at once (read, if at all, only to see whether it carried an e-stop)."""
        full = self.clients[client] >= self.limits.per_client
        self.turned_away += 1
        now = trio.current_time()
        if now >= self._next_warning:  # a flood is one line every 10 s, not one a connection
            self._next_warning = now + 10.0
            log.warning(
                "refused a connection from %s (%d refused so far): %s",
                client,
                self.turned_away,
                "its address holds its most" if full else "the server holds its most",
            )
        if not tls:
            most = self.limits.per_client if full else self.limits.total
            whose = "from your address" if full else "on this server"
            message = f"{most} connections are open {whose}, the most allowed: close some."
            with trio.move_on_after(CLOSE_TIMEOUT), contextlib.suppress(trio.BrokenResourceError):
                await stream.send_all(
                    http_error("503 Service Unavailable", message, ErrorCode.OVERLOADED)
                )
        await trio.aclose_forcefully(stream)

    async def _serve_connection(
        self, stream: trio.abc.Stream, ssl_context: Any, estop_only: str | None = None
    ) -> None:
        """Serve one connection; `estop_only` (its client's address): a connection beyond a
        bound, served only if its first request is an e-stop, and closed after it."""
        if ssl_context is not None:
            stream = trio.SSLStream(stream, ssl_context, server_side=True, https_compatible=True)
            try:
                with trio.fail_after(self.config.ssl_handshake_timeout):
                    await stream.do_handshake()
            except (trio.BrokenResourceError, trio.TooSlowError):
                await trio.aclose_forcefully(stream)
                return
            if stream.selected_alpn_protocol() == "h2" and estop_only is None:
                await self._to_hypercorn(stream, b"")
                return
        if estop_only is not None:
            await self._estop_only(stream, estop_only)
            return
        head = b""
        with trio.move_on_after(HEAD_TIMEOUT) as timer:
            try:
                head = await self._read_head(stream)
            except (trio.BrokenResourceError, trio.ClosedResourceError):
                head = b""
        if timer.cancelled_caught or not head:
            await trio.aclose_forcefully(stream)
            return
        end = head.find(b"\r\n\r\n")
        if head.startswith(_STREAM_PREFIX) and end > 0 and self.stream_router is not None:
            get = parse_get(head[:end])
            streamer = self.stream_router(get) if get is not None else None
            if get is not None and streamer is not None:
                get.scheme = "https" if ssl_context is not None else "http"
                await self._stream(stream, streamer)
            else:
                await self._to_hypercorn(stream, head)
            return
        request = parse_upgrade(head[:end]) if head.startswith(_WS_PREFIX) and end > 0 else None
        if request is not None and ssl_context is not None:
            request.scheme = "https"
        try:
            handler = self.router(request) if request is not None else None
        except ArenaError as refusal:  # a page or host name the server does not answer to
            with contextlib.suppress(trio.BrokenResourceError, trio.ClosedResourceError):
                await stream.send_all(http_error("403 Forbidden", refusal.message, refusal.code))
            await trio.aclose_forcefully(stream)
            return
        if request is None or handler is None:
            await self._to_hypercorn(stream, head)
            return
        await self._websocket(stream, request, handler, head[end + 4 :])

    async def _estop_only(self, stream: trio.abc.Stream, client: str) -> None:
        """Serve the e-stop a connection beyond a bound carries (its request line within
        `ESTOP_HEAD_TIMEOUT`), asking hypercorn to close it after; anything else: 503."""
        head = b""
        with trio.move_on_after(ESTOP_HEAD_TIMEOUT):
            with contextlib.suppress(trio.BrokenResourceError, trio.ClosedResourceError):
                while b"\r\n" not in head and len(head) < MAX_HEAD_BYTES:
                    chunk = await stream.receive_some(MAX_HEAD_BYTES)
                    if not chunk:
                        break
                    head += chunk
        if not ESTOP_REQUEST.match(head):
            await self._turn_away(stream, False, client)
            return
        line = head.index(b"\r\n")
        # One request, then closed: `Connection: close` wins over any keep-alive it asked.
        await self._to_hypercorn(stream, head[:line] + b"\r\nConnection: close" + head[line:])

    async def _read_head(self, stream: trio.abc.Stream) -> bytes:
        """Enough bytes to tell a WebSocket upgrade or a stream (its whole head) from
        anything else; nothing from a client that says nothing for `keep_alive_timeout`."""
        data = b""
        with trio.move_on_after(self.config.keep_alive_timeout):
            data = bytes(await stream.receive_some(MAX_HEAD_BYTES))
        if not data:
            return b""
        while True:
            if not any(prefix.startswith(data[: len(prefix)]) for prefix in _PREFIXES):
                return data  # not for us: hypercorn reads the rest
            if len(data) >= len(_WS_PREFIX) and b"\r\n\r\n" in data:
                return data
            if len(data) > MAX_HEAD_BYTES:
                return data  # hypercorn answers an oversized head
            chunk = await stream.receive_some(MAX_HEAD_BYTES)
            if not chunk:
                return data
            data += chunk

    async def _to_hypercorn(self, stream: trio.abc.Stream, head: bytes) -> None:
        state = ConnectionState(self._lifespan_state.copy())
        await _Server(self._app, self.config, self._context, state, _Replay(stream, head))  # type: ignore[arg-type]

    async def _stream(self, stream: trio.abc.Stream, handler: StreamHandler) -> None:
        try:
            await handler(stream)
        except (trio.BrokenResourceError, trio.ClosedResourceError):
            pass  # the client went away
        except Exception:
            log.exception("stream failed")
        finally:
            with trio.CancelScope(shield=True):
                await trio.aclose_forcefully(stream)

    async def _websocket(
        self,
        stream: trio.abc.Stream,
        request: UpgradeRequest,
        handler: WebSocketHandler,
        rest: bytes,
    ) -> None:
        try:
            problem = _handshake_problem(request)
            if problem is not None:
                await stream.send_all(http_error("400 Bad Request", problem))
                return
            key = ws_frames.accept_key(request.headers["sec-websocket-key"])
            await stream.send_all(
                b"HTTP/1.1 101 Switching Protocols\r\nUpgrade: websocket\r\n"
                b"Connection: Upgrade\r\nSec-WebSocket-Accept: " + key.encode("ascii") + b"\r\n\r\n"
            )
            websocket = WebSocket(
                stream,
                request,
                max_message=self.max_message,
                high_water=self.queue_bytes,
                poller=self._poller,
            )
            if self._poller is not None and isinstance(stream, trio.SocketStream):
                self._poller.attach(stream.socket)
            if rest:
                websocket.feed(rest)
            async with trio.open_nursery() as nursery:
                nursery.start_soon(websocket.run_writer)
                try:
                    await handler(websocket)
                finally:
                    websocket.close_nowait(1000)
                    with trio.CancelScope(shield=True):
                        await websocket.wait_for_peer_close(CLOSE_TIMEOUT)
                    websocket.finish()
                    nursery.cancel_scope.deadline = trio.current_time() + CLOSE_TIMEOUT
        except (trio.BrokenResourceError, trio.ClosedResourceError):
            pass
        except Exception:
            log.exception("WebSocket %s failed", request.path)
        finally:
            if self._poller is not None and isinstance(stream, trio.SocketStream):
                self._poller.forget(stream.socket)
            with trio.CancelScope(shield=True):
                await trio.aclose_forcefully(stream)
