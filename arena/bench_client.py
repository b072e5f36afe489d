"""A lean, blocking WebSocket client for the benchmarks: it measures the server, not a library.

A Python WebSocket library spends about as long per message as the server under test (the
`websockets` client adds some 100 us to a relay round). This client sends pre-masked frames
with one `sendall` and parses replies with a few slices, so what the figures show is the
server and the loopback. Text frames only, no fragmentation, no extensions: enough for Arena.
"""

from __future__ import annotations

import base64
import os
import socket
import struct
from urllib.parse import urlsplit


def masked_frame(text: str) -> bytes:
    """A client text frame (masked, as RFC 6455 requires of clients)."""
    payload = text.encode("utf-8")
    size = len(payload)
    if size < 126:
        header = struct.pack("!BB", 0x81, 0x80 | size)
    elif size < 65536:
        header = struct.pack("!BBH", 0x81, 0x80 | 126, size)
    else:
        header = struct.pack("!BBQ", 0x81, 0x80 | 127, size)
    mask = os.urandom(4)
    key = (mask * (size // 4 + 1))[:size]
    body = (int.from_bytes(payload, "big") ^ int.from_bytes(key, "big")).to_bytes(size, "big")
    return header + mask + body


class BlockingWebSocket:
    """One connection: `send_raw` frames, `receive` text messages (blocking)."""

    def __init__(self, url: str, timeout: float = 30.0) -> None:
        target = urlsplit(url)
        host, port = target.hostname or "127.0.0.1", target.port or 80
        self.sock = socket.create_connection((host, port), timeout=timeout)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        path = target.path + (f"?{target.query}" if target.query else "")
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall(
            (
                f"GET {path} HTTP/1.1\r\nHost: {host}:{port}\r\nUpgrade: websocket\r\n"
                f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n"
                "Sec-WebSocket-Version: 13\r\n\r\n"
            ).encode()
        )
        buffer = b""
        while b"\r\n\r\n" not in buffer:
            chunk = self.sock.recv(4096)
            if not chunk:
                raise ConnectionError("the server closed during the handshake")
            buffer += chunk
        head, _, self._buffer = buffer.partition(b"\r\n\r\n")
        if b" 101 " not in head.split(b"\r\n", 1)[0]:
            raise ConnectionError(head.split(b"\r\n", 1)[0].decode(errors="replace"))

    def send_raw(self, frames: bytes) -> None:
        """Send frames made with `masked_frame` (one or many, joined)."""
        self.sock.sendall(frames)

    def send(self, text: str) -> None:
        """Send one text message."""
        self.sock.sendall(masked_frame(text))

    def receive(self) -> str:
        """The next text message; raises `ConnectionError` on a close frame or end of stream."""
        while True:
            buffer = self._buffer
            if len(buffer) >= 2:
                size, start = buffer[1] & 0x7F, 2
                if size == 126 and len(buffer) >= 4:
                    size, start = struct.unpack_from("!H", buffer, 2)[0], 4
                elif size == 127 and len(buffer) >= 10:
                    size, start = struct.unpack_from("!Q", buffer, 2)[0], 10
                if size < 126 or start > 2:
                    end = start + size
                    if len(buffer) >= end:
                        opcode = buffer[0] & 0x0F
                        self._buffer = buffer[end:]
                        if opcode == 0x1:
                            return buffer[start:end].decode("utf-8")
                        if opcode == 0x8:
                            raise ConnectionError(f"closed by the server: {buffer[start:end]!r}")
                        continue  # ping/pong: not expected from Arena, skipped
            chunk = self.sock.recv(65536)
            if not chunk:
                raise ConnectionError("the server closed the connection")
            self._buffer += chunk

    def close(self) -> None:
        """Send a close frame (1000) and close the socket."""
        try:
            mask = os.urandom(4)
            code = bytes(a ^ b for a, b in zip(struct.pack("!H", 1000), mask, strict=False))
            self.sock.sendall(b"\x88\x82" + mask + code)
        except OSError:
            pass
        self.sock.close()
