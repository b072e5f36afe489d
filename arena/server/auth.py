"""Who is calling, and may they: API keys and tokens checked, the role asked for compared.

API keys are compared in constant time; neither keys nor tokens are ever logged or recorded.
Every refusal is counted in `/metrics` by reason (`arena_auth_refused_total{reason}`).
"""

from __future__ import annotations

import hmac
import logging

from arena.protocol.errors import ArenaError, ErrorCode
from arena.server.base import ArenaApp
from arena.server.identity import ANONYMOUS, Principal, Role, key_principal, unauthorized

log = logging.getLogger(__name__)

#: A refusal's reason in `/metrics`: none given, not valid (bad key, bad or expired token),
#: a role too low, a robot out of scope or of another tenant.
REASONS = ("missing", "invalid", "expired", "role", "scope")


def credential(authorization: str | None, token: str | None) -> str | None:
    """The key or token a request carries: `Authorization: Bearer X`, else `?token=X`."""
    if authorization and authorization.lower().startswith("bearer "):
        return authorization[7:].strip() or None
    return token or None


def authenticate(app: ArenaApp, given: str | None, read_only: bool) -> Principal:
    """The caller of a credential (the anonymous admin when the server has no keys or
    tokens; an anonymous viewer for a read of an `open_reads` server: `read_only` says it
    is one, e-stops are not); UNAUTHORIZED if it is missing or proves nothing."""
    settings = app.arena_config
    if not settings.auth_enabled:
        return ANONYMOUS
    if not given:
        if read_only and settings.open_reads:
            return Principal("anonymous", Role.VIEWER)
        refuse(app, "missing")
        raise unauthorized(
            "An API key or token is required: send 'Authorization: Bearer KEY' "
            "(or ?token=KEY on a WebSocket)."
        )
    found = _find_key(given, settings.api_keys)
    if found:
        return key_principal(found, viewer=False)
    found = _find_key(given, settings.viewer_keys)
    if found:
        return key_principal(found, viewer=True)
    if app.tokens is None:
        refuse(app, "invalid")
        raise ArenaError(ErrorCode.FORBIDDEN, "That API key is not valid here.")
    try:
        return app.tokens.verify(given)
    except ArenaError as error:
        refuse(app, "expired" if "expired" in error.message else "invalid")
        raise


def check_role(app: ArenaApp, principal: Principal, needed: Role, what: str) -> None:
    """FORBIDDEN unless `principal` has `needed` (`what` is the action, for the message)."""
    if principal.role >= needed:
        return
    refuse(app, "role", f"{principal.name!r}, a {principal.role}: {what}")
    raise ArenaError(
        ErrorCode.FORBIDDEN,
        f"{what} needs the {needed} role; {principal.name!r} is a {principal.role}.",
    )


def authorize(
    app: ArenaApp,
    authorization: str | None,
    token: str | None,
    needed: Role,
    what: str,
    read_only: bool = False,
) -> Principal:
    """The caller, if it may do `what`, which needs `needed` (and changes nothing if
    `read_only`); else UNAUTHORIZED or FORBIDDEN."""
    principal = authenticate(app, credential(authorization, token), read_only)
    check_role(app, principal, needed, what)
    return principal


def refuse(app: ArenaApp, reason: str, detail: str = "") -> None:
    """Count and log a refusal (never with the credential's text)."""
    app.metrics.auth_refused[reason] += 1
    log.info("refused a caller: %s%s", reason, f" ({detail})" if detail else "")


def _find_key(token: str, keys: tuple[str, ...]) -> int:
    """The position (from 1) of the key `token` is, or 0. Every key is compared, in constant
    time, so timing tells nothing about any key."""
    given = token.encode()
    found = 0
    for index, key in enumerate(keys, 1):
        if hmac.compare_digest(given, key.encode()):
            found = found or index
    return found
