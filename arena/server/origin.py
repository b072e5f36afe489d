"""Which web pages may talk to Arena: the `Origin` and `Host` checks (no I/O).

A browser lets any page send a "simple" POST (`Content-Type: text/plain`, no preflight) or open
a WebSocket to any server, the operator's lab machine included; only the `Origin` header says
which page did it. So every state-changing request and every WebSocket handshake that carries
an `Origin` must come from the server's own origin (the scheme, host and port the request was
sent to) or one the operator listed. Requests without one (the CLI, the Python client, curl)
are not from a page and pass.

DNS rebinding makes a foreign name resolve to 127.0.0.1, and the page becomes same-origin in
the browser's eyes; its `Host` header still carries the foreign name. A server listening on
loopback therefore answers only to its own names (as Jupyter does): localhost, loopback
addresses, the address it binds, and names the operator added.
"""

from __future__ import annotations

import ipaddress
from urllib.parse import urlsplit

from arena.protocol.errors import ArenaError, ErrorCode

#: Methods that change nothing (the Origin check leaves them alone).
SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})


def _hostname(host: str) -> str:
    """The name part of a `Host` header (`[::1]:8080` -> `::1`), lower case."""
    host = host.strip().lower()
    if host.startswith("["):
        return host[1 : host.find("]")] if "]" in host else host
    return host.rsplit(":", 1)[0] if host.count(":") == 1 else host


def _is_loopback_name(name: str) -> bool:
    if name == "localhost" or name.endswith(".localhost"):
        return True
    try:
        return ipaddress.ip_address(name).is_loopback
    except ValueError:
        return False


class OriginPolicy:
    """The checks for one server: where it listens, and what the operator allowed."""

    def __init__(
        self, bind_host: str, allowed_origins: tuple[str, ...], allowed_hosts: tuple[str, ...]
    ) -> None:
        self.loopback_only = _is_loopback_name(_hostname(bind_host))
        self.allowed_origins = frozenset(o.rstrip("/").lower() for o in allowed_origins)
        self.allowed_hosts = frozenset(_hostname(h) for h in (*allowed_hosts, bind_host))

    def check_host(self, host: str | None) -> None:
        """Refuse a `Host` that is not one of a loopback server's own names."""
        if not self.loopback_only or host is None:
            return
        name = _hostname(host)
        if _is_loopback_name(name) or name in self.allowed_hosts:
            return
        raise ArenaError(
            ErrorCode.HOST_NOT_ALLOWED,
            f"Host {host!r} is not a name of this server: it listens on loopback and answers "
            "to localhost and its addresses (add names with --allow-host).",
        )

    def check_origin(self, origin: str | None, host: str | None, scheme: str) -> None:
        """Refuse a page from another origin (a missing `Origin` is not a page)."""
        if origin is None:
            return
        given = origin.strip().rstrip("/").lower()
        if given in self.allowed_origins or (host and given == f"{scheme}://{host.lower()}"):
            return
        if host and _same_origin_default_port(given, scheme, host.lower()):
            return
        raise ArenaError(
            ErrorCode.ORIGIN_NOT_ALLOWED,
            f"Requests from the web page at {origin!r} are not allowed: only this server's own "
            "pages, and origins given with --allow-origin, may change anything.",
        )

    def check(self, method: str, origin: str | None, host: str | None, scheme: str) -> None:
        """Both checks for an HTTP request (`method` GET for a WebSocket handshake is not
        enough: call `check_origin` for those whatever the method)."""
        self.check_host(host)
        if method.upper() not in SAFE_METHODS:
            self.check_origin(origin, host, scheme)


def _same_origin_default_port(origin: str, scheme: str, host: str) -> bool:
    """`http://name` against `Host: name:80` (browsers leave default ports out of Origin)."""
    parts = urlsplit(origin)
    default = {"http": 80, "https": 443, "ws": 80, "wss": 443}.get(scheme)
    try:
        port = parts.port
    except ValueError:
        return False
    return (
        parts.scheme == scheme
        and port is None
        and default is not None
        and host == f"{parts.hostname}:{default}"
    )


def is_json(content_type: str | None) -> bool:
    """`application/json` or a `+json` type, whatever its parameters."""
    if not content_type:
        return False
    mime = content_type.split(";", 1)[0].strip().lower()
    return mime == "application/json" or (
        mime.startswith("application/") and mime.endswith("+json")
    )
