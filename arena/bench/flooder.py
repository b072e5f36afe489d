"""A hostile viewer for `arena bench flood`, in a process of its own (sharing the bench's
would slow the bench's own clients): it sends masked empty pings as fast as TCP takes them and
never reads the pongs. `python -m arena.bench.flooder HOST PORT ROBOT` until killed."""

from __future__ import annotations

import os
import socket
import sys

from arena.protocol.ws_frames import OP_PING, encode_frame


def flood(host: str, port: int, robot_id: str) -> None:
    """Open a viewer socket with a 4 KiB receive buffer and ping it until the end of time."""
    sock = socket.create_connection((host, port))
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.sendall(
        (
            f"GET /ws/robots/{robot_id}/state HTTP/1.1\r\nHost: {host}:{port}\r\n"
            "Upgrade: websocket\r\nConnection: Upgrade\r\n"
            "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n"
        ).encode()
    )
    burst = encode_frame(OP_PING, b"", mask=os.urandom(4)) * 10_000
    while True:
        try:
            sock.sendall(burst)
        except OSError:
            return  # closed by the server


if __name__ == "__main__":
    flood(sys.argv[1], int(sys.argv[2]), sys.argv[3])
