"""The client's side of the WebSocket opening handshake (RFC 6455, section 4.1), without I/O:
the request's bytes and the check of the answer's head.

`Session` leaves the handshake to trio-websocket; the two raw clients that own their sockets
use this: the benchmarks' lean client (`arena.bench.client`) and the tests' raw client, which
sends frames no library would.
"""

from __future__ import annotations

import base64
import os


def new_key() -> str:
    """A fresh `Sec-WebSocket-Key`: 16 random bytes in base64."""
    return base64.b64encode(os.urandom(16)).decode()


def upgrade_request(host: str, port: int, path: str, key: str | None = None) -> bytes:
    """The GET that asks `host:port` to upgrade `path` (with its query) to a WebSocket."""
    lines = [
        f"GET {path} HTTP/1.1",
        f"Host: {host}:{port}",
        "Upgrade: websocket",
        "Connection: Upgrade",
        f"Sec-WebSocket-Key: {key or new_key()}",
        "Sec-WebSocket-Version: 13",
    ]
    return ("\r\n".join(lines) + "\r\n\r\n").encode()


def split_answer(buffer: bytes) -> tuple[bytes, bytes] | None:
    """(the answer's head, the bytes after it: the first frames) once `buffer` holds the whole
    head; None while it does not."""
    head, found, rest = buffer.partition(b"\r\n\r\n")
    return (head, rest) if found else None


def refusal(head: bytes) -> str | None:
    """Why the server did not switch protocols (its status line), or None if it did (101)."""
    status = head.split(b"\r\n", 1)[0]
    parts = status.split()
    if len(parts) >= 2 and parts[0].startswith(b"HTTP/1.1") and parts[1] == b"101":
        return None
    return status.decode(errors="replace") or "no answer"
