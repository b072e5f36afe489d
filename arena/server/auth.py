"""API keys: who may use the server. Keys are compared in constant time and never logged."""

from __future__ import annotations

import hmac
from typing import TYPE_CHECKING

from arena.protocol.errors import ArenaError, ErrorCode

if TYPE_CHECKING:
    from arena.server.app import ArenaApp


def check_token(
    app: ArenaApp, authorization: str | None, token: str | None, mutating: bool = True
) -> None:
    """Raise UNAUTHORIZED / FORBIDDEN unless the request carries a configured API key."""
    keys = app.arena_config.api_keys
    if not keys or (not mutating and app.arena_config.open_reads):
        return
    if authorization and authorization.lower().startswith("bearer "):
        token = authorization[7:].strip()
    if not token:
        raise ArenaError(
            ErrorCode.UNAUTHORIZED,
            "An API key is required: send 'Authorization: Bearer KEY' "
            "(or ?token=KEY on a WebSocket).",
        )
    given = token.encode()
    # Compare against every key, in constant time, so timing tells nothing about any key.
    matched = False
    for key in keys:
        matched |= hmac.compare_digest(given, key.encode())
    if not matched:
        raise ArenaError(ErrorCode.FORBIDDEN, "That API key is not valid here.")
