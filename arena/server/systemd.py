"""systemd's readiness protocol (`Type=notify`, deploy/arena.service): a datagram to the
socket named by `$NOTIFY_SOCKET` saying `READY=1` once the server listens and `STOPPING=1` when
it begins to stop. Without the variable (not under systemd) nothing is sent."""

from __future__ import annotations

import logging
import os
import socket

log = logging.getLogger(__name__)


def notify(state: str) -> bool:
    """Send `state` (`KEY=value` lines) to systemd; False when not under systemd or it failed
    (a notification never stops the server: systemd then times the start out itself)."""
    address = os.environ.get("NOTIFY_SOCKET", "")
    if not address:
        return False
    if address.startswith("@"):  # an abstract socket
        address = "\0" + address[1:]
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
            sock.connect(address)
            sock.sendall(state.encode())
    except OSError as exc:
        log.warning("cannot notify systemd at %s: %s", address.lstrip("\0"), exc)
        return False
    return True
