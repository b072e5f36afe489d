"""A bare WebSocket client on a TCP socket, for what polite clients never do.

It can stop reading (a slow consumer with a tiny receive buffer), cut the connection without a
close frame, and send frames no library would send (text that is not UTF-8). That is why it
stays raw beside `arena.client`, whose sessions never misbehave so; it uses their handshake
(`arena.client.handshake`) and the protocol's frame codec (`ws_frames`).
"""

from __future__ import annotations

import os
import socket
import struct
from dataclasses import dataclass, field

import trio

from arena.client.handshake import refusal, split_answer, upgrade_request
from arena.protocol.ws_frames import (
    OP_CLOSE,
    OP_PING,
    OP_PONG,
    OP_TEXT,
    encode_frame,
    split_unmasked,
)

__all__ = ["OP_CLOSE", "OP_TEXT", "Frame", "RawWebSocket"]


@dataclass
class Frame:
    """One frame from the server (servers never mask)."""

    opcode: int
    payload: bytes

    @property
    def close_code(self) -> int | None:
        """The code of a close frame."""
        if self.opcode != OP_CLOSE or len(self.payload) < 2:
            return None
        return int(struct.unpack("!H", self.payload[:2])[0])


@dataclass
class RawWebSocket:
    """A WebSocket connection with every frame in the test's hands."""

    stream: trio.SocketStream
    buffer: bytearray = field(default_factory=bytearray)
    #: A close frame was sent: nothing more goes out (a pong after it could reach a server that
    #: has already closed the connection, which the kernel answers with a reset).
    closing: bool = False

    @classmethod
    async def connect(cls, url: str, path: str, receive_buffer: int | None = None) -> RawWebSocket:
        """Connect to `url` (http://host:port) and upgrade `path`.

        `receive_buffer` shrinks the socket's receive buffer before it connects, so a client
        that stops reading pushes back on the server after a few kilobytes.
        """
        host, port = url.split("//")[1].rsplit(":", 1)
        sock = trio.socket.socket()
        if receive_buffer is not None:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, receive_buffer)
        await sock.connect((host, int(port)))
        connection = cls(trio.SocketStream(sock))
        await connection.stream.send_all(upgrade_request(host, int(port), path))
        while (answer := split_answer(bytes(connection.buffer))) is None:
            if not await connection._fill():
                break
        head, rest = answer or (bytes(connection.buffer), b"")
        refused = refusal(head)
        if refused is not None:
            raise ConnectionError(f"upgrade refused: {refused[:80]!r}")
        connection.buffer = bytearray(rest)
        return connection

    async def _fill(self) -> bool:
        chunk = await self.stream.receive_some(65536)
        self.buffer += chunk
        return bool(chunk)

    async def send_frame(self, opcode: int, payload: bytes) -> None:
        """Send one final, masked frame as a client must."""
        await self.stream.send_all(encode_frame(opcode, payload, mask=os.urandom(4)))
        self.closing = self.closing or opcode == OP_CLOSE

    async def receive_frame(self) -> Frame | None:
        """The next frame, or None once the server has closed the TCP connection. The server's
        pings (it times a master's link with them) are answered on the way, as any client's
        library does."""
        while True:
            frame = self._parse()
            if frame is not None and frame.opcode == OP_PING:
                if not self.closing:
                    await self.send_frame(OP_PONG, frame.payload)
                continue
            if frame is not None:
                return frame
            if not await self._fill():
                return None

    def _parse(self) -> Frame | None:
        found = split_unmasked(self.buffer)
        if found is None:
            return None
        opcode, payload, used = found
        del self.buffer[:used]
        return Frame(opcode, payload)

    async def aclose(self) -> None:
        """Cut the TCP connection (no close frame)."""
        await self.stream.aclose()
