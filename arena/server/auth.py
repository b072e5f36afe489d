"""API keys: who may use the server. Keys are compared in constant time and never logged."""

from __future__ import annotations

import hmac

from arena.protocol.errors import ArenaError, ErrorCode
from arena.server.base import ArenaApp


def check_token(
    app: ArenaApp, authorization: str | None, token: str | None, mutating: bool = True
) -> None:
    """Raise UNAUTHORIZED / FORBIDDEN unless the request carries a key that allows it.

    API keys allow everything; viewer keys only reads (GET, the state WebSocket).
    """
    settings = app.arena_config
    keys = settings.api_keys
    if not keys or (not mutating and settings.open_reads):
        return
    if authorization and authorization.lower().startswith("bearer "):
        token = authorization[7:].strip()
    if not token:
        raise ArenaError(
            ErrorCode.UNAUTHORIZED,
            "An API key is required: send 'Authorization: Bearer KEY' "
            "(or ?token=KEY on a WebSocket).",
        )
    if _matches(token, keys):
        return
    if _matches(token, settings.viewer_keys):
        if not mutating:
            return
        raise ArenaError(
            ErrorCode.FORBIDDEN, "That key may only watch: commands and changes need an API key."
        )
    raise ArenaError(ErrorCode.FORBIDDEN, "That API key is not valid here.")


def _matches(token: str, keys: tuple[str, ...]) -> bool:
    """Compare against every key, in constant time, so timing tells nothing about any key."""
    given = token.encode()
    matched = False
    for key in keys:
        matched |= hmac.compare_digest(given, key.encode())
    return matched
