"""The connections clients open: closed when a client is done or idle, and bounded per client
address and in all, so that no client can take the file descriptors the e-stop needs.

The server runs in this process on 127.0.0.1; its sockets are told from the clients' by their
local port (the server's), read from /proc/net/tcp, and counted among /proc/self/fd. Waits are
for events (an end of stream, a count reached) under generous deadlines: a real keep-alive
timer runs on the real clock, and nothing here asserts how long anything took.
"""

from __future__ import annotations

import json
import os
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import pytest
import trio

from arena.cli import main
from arena.protocol.errors import ArenaError
from arena.server.config import ServerConfig, load_config
from tests.conftest import RunningServer, eventually

StartServer = Callable[..., Awaitable[RunningServer]]
#: Long enough to tell an end of stream that should come from one that never will.
DEADLINE = 30.0
_LISTENING = "0A"  # a socket's state in /proc/net/tcp


def server_sockets(port: int) -> int:
    """Open descriptors of this process on the server's side of a connection to `port` (its
    listening socket left out)."""
    inodes = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        for line in Path(table).read_text().splitlines()[1:]:
            fields = line.split()
            local_port = int(fields[1].rsplit(":", 1)[1], 16)
            if local_port == port and fields[3] != _LISTENING:
                inodes.add(fields[9])
    count = 0
    for fd in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:  # closed meanwhile (the listing's own descriptor among them)
            continue
        count += target.startswith("socket:[") and target[len("socket:[") : -1] in inodes
    return count


def port_of(server: RunningServer) -> int:
    port = urlsplit(server.url).port
    assert port is not None
    return port


async def connect(port: int, source: str = "127.0.0.1") -> trio.SocketStream:
    """A TCP connection to the server from the loopback address `source` (Linux routes all
    of 127.0.0.0/8 to this machine: each is a client address of its own)."""
    sock = trio.socket.socket()
    await sock.bind((source, 0))
    await sock.connect(("127.0.0.1", port))
    return trio.SocketStream(sock)


async def get(stream: trio.SocketStream, path: str, close: bool = False) -> None:
    header = "Connection: close\r\n" if close else ""
    await stream.send_all(f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\n{header}\r\n".encode())


async def read_until_closed(stream: trio.SocketStream) -> bytes:
    """Everything the server sends until it closes the connection (a failure past the
    deadline: it never does)."""
    received = b""
    with trio.fail_after(DEADLINE):
        while chunk := await stream.receive_some(65536):
            received += chunk
    return received


async def read_response(stream: trio.SocketStream) -> bytes:
    """One whole response with a Content-Length body (the connection left open)."""
    received = b""
    with trio.fail_after(DEADLINE):
        while b"\r\n\r\n" not in received:
            received += await stream.receive_some(65536)
        head, _, body = received.partition(b"\r\n\r\n")
        length = next(
            int(line.split(b":")[1])
            for line in head.split(b"\r\n")
            if line.lower().startswith(b"content-length:")
        )
        while len(body) < length:
            body += await stream.receive_some(65536)
    return head


async def test_a_connection_is_closed_after_a_response_to_connection_close(
    start_server: StartServer,
) -> None:
    server = await start_server(keep_alive_timeout=3600.0)  # only `Connection: close` closes
    port = port_of(server)
    closing = [await connect(port) for _ in range(10)]
    kept = [await connect(port) for _ in range(10)]
    for stream in closing:
        await get(stream, "/healthz", close=True)
    for stream in kept:
        await get(stream, "/healthz")
        assert (await read_response(stream)).startswith(b"HTTP/1.1 200")
    for stream in closing:  # the server closes its end once it has answered
        assert (await read_until_closed(stream)).startswith(b"HTTP/1.1 200")
    # ... and frees its descriptor: the ten kept alive are all that is left.
    await eventually(lambda: server_sockets(port) == len(kept), DEADLINE, "ten sockets left")
    for stream in kept:  # (which are still served)
        await get(stream, "/healthz")
        assert (await read_response(stream)).startswith(b"HTTP/1.1 200")
    for stream in closing + kept:
        await stream.aclose()


async def test_idle_connections_are_closed_after_the_keep_alive_timeout(
    start_server: StartServer,
) -> None:
    server = await start_server(keep_alive_timeout=0.5)
    port = port_of(server)
    answered = [await connect(port) for _ in range(10)]  # one request each, then idle
    silent = [await connect(port) for _ in range(10)]  # connected, never a byte
    for stream in answered:
        await get(stream, "/healthz")
        assert (await read_response(stream)).startswith(b"HTTP/1.1 200")
    for stream in answered + silent:  # each closed by the server, however it was left
        assert await read_until_closed(stream) == b""
    await eventually(lambda: server_sockets(port) == 0, DEADLINE, "every server socket closed")
    for stream in answered + silent:
        await stream.aclose()


async def test_the_rest_estop_answers_while_one_address_holds_its_most_connections(
    start_server: StartServer,
) -> None:
    server = await start_server(
        demo=True, keep_alive_timeout=3600.0, max_connections_per_client=8, max_connections=12
    )
    port = port_of(server)
    hostile = [await connect(port, "127.0.0.2") for _ in range(8)]  # idle, holding on
    await eventually(lambda: server_sockets(port) == 8, DEADLINE, "eight connections held")
    one_more = await connect(port, "127.0.0.2")  # silent: turned away (after 2 s of nothing)
    refused = await read_until_closed(one_more)
    assert refused.startswith(b"HTTP/1.1 503"), refused
    error = json.loads(refused.partition(b"\r\n\r\n")[2])["error"]
    assert error["code"] == "OVERLOADED" and "from your address" in error["message"]
    # From that full address, anything but an e-stop is turned away; an e-stop is served (an
    # operator's e-stop passes a leaky client's bound), and its connection closed after it.
    asks = await connect(port, "127.0.0.2")
    await get(asks, "/healthz")
    assert (await read_until_closed(asks)).startswith(b"HTTP/1.1 503")
    body = b'{"reason": "same address"}'
    stop = await connect(port, "127.0.0.2")
    await stop.send_all(
        b"POST /api/robots/demo-arm/estop HTTP/1.1\r\nHost: 127.0.0.1\r\n"
        b"Content-Type: application/json\r\nContent-Length: %d\r\n\r\n%s" % (len(body), body)
    )
    answer = await read_until_closed(stop)
    assert answer.startswith(b"HTTP/1.1 200"), answer
    assert json.loads(answer.partition(b"\r\n\r\n")[2])["estop_reason"] == "same address"
    async with server.client() as http:
        assert (await http.post("/api/robots/demo-arm/reset")).status_code == 200
    async with server.client() as http:  # another address is served, the e-stop first
        stopped = await http.post("/api/robots/demo-arm/estop", json={"reason": "held"})
        assert (stopped.status_code, stopped.json()["state"]) == (200, "estopped")
    await eventually(lambda: server_sockets(port) == 8, DEADLINE, "the e-stop's socket closed")
    # In all: four more from another address fill the server; a fifth address is turned away.
    others = [await connect(port, "127.0.0.3") for _ in range(4)]
    await eventually(lambda: server_sockets(port) == 12, DEADLINE, "twelve connections held")
    beyond = await connect(port, "127.0.0.4")
    error = json.loads((await read_until_closed(beyond)).partition(b"\r\n\r\n")[2])["error"]
    assert error["code"] == "OVERLOADED" and "on this server" in error["message"]
    for stream in hostile + others + [one_more, beyond]:
        await stream.aclose()
    async with server.client() as http:  # the bounds count connections open now
        await eventually(
            lambda: _is_ok(http.post("/api/robots/demo-arm/reset")), DEADLINE, "served again"
        )


async def _is_ok(reply: Awaitable[Any]) -> bool:
    return bool((await reply).status_code == 200)


def test_connection_settings_come_from_flags_the_environment_and_the_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    settings = tmp_path / "arena.toml"
    settings.write_text("keep_alive_timeout = 2.5\nmax_connections = 500\n")
    environ = {"ARENA_MAX_CONNECTIONS_PER_CLIENT": "50"}
    config = load_config(str(settings), environ)
    assert (config.keep_alive_timeout, config.max_connections) == (2.5, 500)
    assert config.max_connections_per_client == 50
    assert (ServerConfig().keep_alive_timeout, ServerConfig().max_connections) == (5.0, 1024)
    for bad in ({"keep_alive_timeout": 0.0}, {"max_connections_per_client": 2000}):
        with pytest.raises(ArenaError, match=next(iter(bad))):
            ServerConfig(**bad).check()  # type: ignore[arg-type]
    served: list[ServerConfig] = []

    async def run_server(config: ServerConfig, **_: Any) -> None:
        served.append(config)

    monkeypatch.setattr("arena.server.run.run_server", run_server)
    flags = ["--keep-alive-timeout", "1.5", "--max-connections", "64"]
    main(["serve", *flags, "--max-connections-per-client", "16"])
    assert (served[0].keep_alive_timeout, served[0].max_connections) == (1.5, 64)
    assert served[0].max_connections_per_client == 16
