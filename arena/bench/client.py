"""A lean, blocking WebSocket client for the benchmarks: it measures the server, not a library.

A Python WebSocket library spends about as long per message as the server under test (the
`websockets` client adds some 100 us to a relay round). This client sends pre-masked frames
with one `sendall` and parses replies with a few slices, so what the figures show is the
server and the loopback. Text frames only, no fragmentation, no extensions: enough for Arena.

So it stays apart from `arena.client`'s sessions (trio, JSON parsing, acks matched to requests)
and is built of the pieces they share: the handshake (`arena.client.handshake`), the frame codec
(`ws_frames`) and the protocol's messages (`bench.common`).
"""

from __future__ import annotations

import contextlib
import os
import select
import socket
import struct
from urllib.parse import urlsplit

from arena.client.handshake import refusal, split_answer, upgrade_request
from arena.protocol.ws_frames import OP_CLOSE, OP_TEXT, encode_frame, split_unmasked


def masked_frame(text: str) -> bytes:
    """A client text frame (masked, as RFC 6455 requires of clients)."""
    return encode_frame(OP_TEXT, text.encode("utf-8"), mask=os.urandom(4))


class BlockingWebSocket:
    """One connection: `send_raw` frames, `receive` text messages (blocking)."""

    def __init__(self, url: str, timeout: float = 30.0, receive_buffer: int | None = None) -> None:
        target = urlsplit(url)
        host, port = target.hostname or "127.0.0.1", target.port or 80
        self.sock = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET)
        self.sock.settimeout(timeout)
        if receive_buffer is not None:  # a client that stops reading pushes back sooner
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, receive_buffer)
        self.sock.connect((host, port))
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        path = target.path + (f"?{target.query}" if target.query else "")
        self.sock.sendall(upgrade_request(host, port, path))
        buffer = b""
        while (answer := split_answer(buffer)) is None:
            chunk = self.sock.recv(4096)
            if not chunk:
                raise ConnectionError("the server closed during the handshake")
            buffer += chunk
        head, self._buffer = answer
        refused = refusal(head)
        if refused is not None:
            raise ConnectionError(refused)

    def send_raw(self, frames: bytes) -> None:
        """Send frames made with `masked_frame` (one or many, joined)."""
        self.sock.sendall(frames)

    def send(self, text: str) -> None:
        """Send one text message."""
        self.sock.sendall(masked_frame(text))

    def receive(self) -> str:
        """The next text message; raises `ConnectionError` on a close frame or end of stream."""
        while True:
            frame = split_unmasked(self._buffer)
            if frame is not None:
                opcode, payload, used = frame
                self._buffer = self._buffer[used:]
                if opcode == OP_TEXT:
                    return payload.decode("utf-8")
                if opcode == OP_CLOSE:
                    raise ConnectionError(f"closed by the server: {payload!r}")
                continue  # ping/pong: not expected from Arena, skipped
            chunk = self.sock.recv(65536)
            if not chunk:
                raise ConnectionError("the server closed the connection")
            self._buffer += chunk

    def drop_received(self) -> int:
        """Drop the text messages received already (in hand or waiting in the socket), without
        waiting for more; how many. Raises `ConnectionError` on a close frame or end of
        stream."""
        dropped = 0
        while True:
            while (frame := split_unmasked(self._buffer)) is not None:
                opcode, payload, used = frame
                self._buffer = self._buffer[used:]
                if opcode == OP_CLOSE:
                    raise ConnectionError(f"closed by the server: {payload!r}")
                dropped += opcode == OP_TEXT
            if not select.select([self.sock], [], [], 0)[0]:
                return dropped
            chunk = self.sock.recv(65536)
            if not chunk:
                raise ConnectionError("the server closed the connection")
            self._buffer += chunk

    def receive_ready(self) -> list[str]:
        """The text messages that one `recv` completes (for a socket a selector says is
        readable); raises `ConnectionError` on a close frame or end of stream."""
        chunk = self.sock.recv(65536)
        if not chunk:
            raise ConnectionError("the server closed the connection")
        self._buffer += chunk
        messages = []
        while (frame := split_unmasked(self._buffer)) is not None:
            opcode, payload, used = frame
            self._buffer = self._buffer[used:]
            if opcode == OP_TEXT:
                messages.append(payload.decode("utf-8"))
            elif opcode == OP_CLOSE:
                raise ConnectionError(f"closed by the server: {payload!r}")
        return messages

    def close(self) -> None:
        """Send a close frame (1000) and close the socket."""
        with contextlib.suppress(OSError):
            self.sock.sendall(encode_frame(OP_CLOSE, struct.pack("!H", 1000), mask=os.urandom(4)))
        self.sock.close()


class BlockingHttp:
    """One keep-alive HTTP/1.1 connection: requests written whole, answers read by length.

    Enough for Arena's JSON answers (hypercorn sends a Content-Length); `send` and `answer`
    are apart so a benchmark can time what happens between the request and its answer.
    """

    def __init__(self, url: str, timeout: float = 30.0) -> None:
        target = urlsplit(url)
        self.host, self.port = target.hostname or "127.0.0.1", target.port or 80
        self.timeout = timeout
        self.sock = self._connect()
        self._buffer = b""
        self._closing = False  # the last answer said "Connection: close"

    def _connect(self) -> socket.socket:
        sock = socket.create_connection((self.host, self.port), timeout=self.timeout)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        return sock

    def request_bytes(self, method: str, path: str, body: bytes = b"") -> bytes:
        """The bytes of one request (made before a clock starts)."""
        head = (
            f"{method} {path} HTTP/1.1\r\nHost: {self.host}:{self.port}\r\n"
            f"Content-Type: application/json\r\nContent-Length: {len(body)}\r\n\r\n"
        )
        return head.encode() + body

    def send(self, request: bytes) -> None:
        """Send a request made with `request_bytes` (on a new connection if the server closed
        the last one: hypercorn ends a keep-alive connection after 1,000 requests)."""
        if self._closing:
            self.sock.close()
            self.sock, self._buffer, self._closing = self._connect(), b"", False
        self.sock.sendall(request)

    def answer(self) -> tuple[int, bytes]:
        """The status and body of the next answer."""
        while b"\r\n\r\n" not in self._buffer:
            self._receive()
        head, _, rest = self._buffer.partition(b"\r\n\r\n")
        lines = head.decode("latin-1").split("\r\n")
        status = int(lines[0].split()[1])
        fields = {
            name.strip().lower(): value.strip()
            for name, _, value in (line.partition(":") for line in lines[1:])
        }
        if "content-length" not in fields:
            raise ConnectionError(f"an answer without Content-Length: {lines[0]}")
        length = int(fields["content-length"])
        while len(rest) < length:
            self._receive()
            rest = self._buffer.partition(b"\r\n\r\n")[2]
        self._buffer = rest[length:]
        self._closing = fields.get("connection", "").lower() == "close"
        return status, rest[:length]

    def _receive(self) -> None:
        chunk = self.sock.recv(65536)
        if not chunk:
            raise ConnectionError("the server closed the connection")
        self._buffer += chunk

    def close(self) -> None:
        """Close the connection."""
        self.sock.close()
