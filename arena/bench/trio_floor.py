"""The floor relay written on trio: parse and forward, nothing else (a benchmark reference).

`shared/bench/floor_relay.py` is the least a relay can do on aiohttp, uvloop and orjson, whose
loops and parsers are C. This is the same relay on what Arena is built on (trio, Arena's own
WebSocket frames, the standard library's `json`, and `os.read`/`os.write` on the descriptor
as Arena's transport does), so that `arena bench versus` can tell what the event loop costs
from what Arena's own work costs:

    ARENA_FLOOR_PYTHON=.venv/bin/python ARENA_FLOOR_SCRIPT=arena/bench/trio_floor.py \\
        arena bench versus

It serves `POST /api/robots` (201), `GET /` (200), `/ws/slave/{id}` and `/ws/master/{id}`: a
master's `command` is re-sent to the robot's slave as `execute_command`. No joint states, no
safety, no recording, no checks: never serve anything with it.

With `--acks` it also answers each command to its master as Arena does, with a plain
acceptance (`{"type":"ack",...,"data":{"status":"accepted"}}`, after the slave's write): the
*contract floor*, the least that the contract's messages cost on trio (a read and two writes
a command), which `arena bench versus` sets beside Arena.
Usage: python trio_floor.py PORT [--acks]
"""

from __future__ import annotations

import json
import os
import sys

import trio

from arena.protocol.messages import now_iso
from arena.protocol.ws_frames import (
    OP_CLOSE,
    OP_PING,
    OP_PONG,
    OP_TEXT,
    FrameParser,
    accept_key,
    encode_frame,
)

_slaves: dict[str, int] = {}
_acks = "--acks" in sys.argv[2:]


async def _write(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        try:
            view = view[os.write(fd, view) :]
        except BlockingIOError:
            await trio.lowlevel.wait_writable(fd)


async def _head(stream: trio.SocketStream) -> tuple[str, str, dict[str, str], bytes] | None:
    data = b""
    while b"\r\n\r\n" not in data:
        chunk = await stream.receive_some(65536)
        if not chunk:
            return None
        data += chunk
    head, _, rest = data.partition(b"\r\n\r\n")
    first, *lines = head.decode("latin-1").split("\r\n")
    method, path, _ = first.split(" ", 2)
    headers = {k.strip().lower(): v.strip() for k, _, v in (line.partition(":") for line in lines)}
    return method, path, headers, rest


async def _serve(stream: trio.SocketStream) -> None:
    request = await _head(stream)
    if request is None:
        return
    method, path, headers, rest = request
    if "sec-websocket-key" not in headers:
        body = b'{"id":"floor"}'
        status = "201 Created" if method == "POST" else "200 OK"
        reply = f"HTTP/1.1 {status}\r\ncontent-length: {len(body)}\r\nconnection: close\r\n\r\n"
        await stream.send_all(reply.encode() + body)
        return
    accept = accept_key(headers["sec-websocket-key"])
    await stream.send_all(
        b"HTTP/1.1 101 Switching Protocols\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
        + f"Sec-WebSocket-Accept: {accept}\r\n\r\n".encode()
    )
    _, _, role, robot_id = path.split("?")[0].split("/")[:4]
    fd = stream.socket.fileno()
    parser = FrameParser(1 << 20)
    parser.feed(rest)
    if role == "slave":
        _slaves[robot_id] = fd
    while True:
        while (message := parser.next()) is not None:
            if message.opcode == OP_TEXT and role == "master":
                data = json.loads(message.payload)
                if data.get("type") != "command":
                    continue
                slave = _slaves.get(robot_id)
                if slave is not None:
                    out = {"type": "execute_command", "timestamp": data.get("timestamp")}
                    out["data"] = {"joints": data["data"]["joints"]}
                    text = json.dumps(out, separators=(",", ":")).encode()
                    await _write(slave, encode_frame(OP_TEXT, text))
                if _acks:
                    ack = {"type": "ack", "timestamp": now_iso(), "data": {"status": "accepted"}}
                    text = json.dumps(ack, separators=(",", ":")).encode()
                    await _write(fd, encode_frame(OP_TEXT, text))
            elif message.opcode == OP_PING:
                await _write(fd, encode_frame(OP_PONG, message.payload))
            elif message.opcode == OP_CLOSE:
                return
        await trio.lowlevel.wait_readable(fd)
        try:
            data = os.read(fd, 65536)
        except BlockingIOError:
            continue
        if not data:
            return
        parser.feed(data)


async def _main(port: int) -> None:
    await trio.serve_tcp(_serve, port, host="127.0.0.1")


if __name__ == "__main__":
    trio.run(_main, int(sys.argv[1]))
