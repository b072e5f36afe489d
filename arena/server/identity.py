"""Who is asking: roles, a caller's scope, and JSON Web Tokens verified offline (no I/O but
reading the key files at start).

A caller is a `Principal`: a name (a token's `sub`, or which API key), a role, a tenant and a
scope (glob patterns on robot ids and group ids; None means every one). An API key is an
admin of the `default` tenant, a viewer key its viewer. Tokens are signed with a shared secret
(HS256) or by an identity provider whose public keys are in a JWKS file (RS256, ES256): the
algorithm is chosen by the key, never by the token, so `alg: none` and a public key used as
an HMAC secret are refused.
"""

from __future__ import annotations

import enum
import fnmatch
import json
import math
import re
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from arena.protocol.errors import ArenaError, ErrorCode
from arena.protocol.rest import DEFAULT_TENANT, TENANT_PATTERN

if TYPE_CHECKING:
    import jwt  # PyJWT: imported where tokens are used, so a server without them starts fast

#: The algorithms a JWKS key may sign with (a secret signs HS256 only).
PUBLIC_KEY_ALGORITHMS = ("RS256", "ES256")
#: Tenants, robot ids and globs are short names: bounded so a token cannot carry a novel.
_NAME = re.compile(r"[A-Za-z0-9_.*?\[\]-]{1,64}")
#: A tenant is a name, not a pattern (it names recording files too).
_TENANT = re.compile(TENANT_PATTERN)
_MOST_PATTERNS = 64


class Role(enum.IntEnum):
    """What a caller may do; each role may do everything of the roles below it."""

    VIEWER = 1  # read, watch, download recordings, e-stop what it sees
    OPERATOR = 2  # command, take over, reset, sequences, episodes, replays
    ADMIN = 3  # robots, drivers, calibration, workspace, cameras, recording on and off

    def __str__(self) -> str:
        return self.name.lower()

    @classmethod
    def named(cls, name: str) -> Role:
        """The role of a claim's value; ValueError naming the valid ones."""
        try:
            return cls[name.upper()]
        except KeyError:
            raise ValueError(f"role must be viewer, operator or admin, not {name!r}") from None


@dataclass(frozen=True)
class Principal:
    """A caller as checked: who, with what role, over which robots of which tenant."""

    name: str
    role: Role
    tenant: str = DEFAULT_TENANT
    robots: tuple[str, ...] | None = None  # glob patterns on robot ids; None: all
    groups: tuple[str, ...] | None = None  # glob patterns on group ids; None: all
    expires: float | None = None  # Unix seconds after which the token is refused (leeway in)

    @property
    def unlimited(self) -> bool:
        """Every robot of its tenant is in scope."""
        return self.robots is None and self.groups is None

    def covers(self, robot_id: str, groups: Iterable[str] = ()) -> bool:
        """The robot is in scope: its id matches `robots`, or a group it is a member of
        (`groups`) matches `groups`. With one claim absent only the other decides."""
        if self.unlimited:
            return True
        if self.robots is not None and _matches(robot_id, self.robots):
            return True
        return self.groups is not None and any(_matches(g, self.groups) for g in groups)

    def audit_name(self) -> str:
        """How records name this caller."""
        return self.name

    def to_wire(self) -> dict[str, Any]:
        """As claims, for a node of the fleet that serves this caller's call (`of_wire`)."""
        claims: dict[str, Any] = {"sub": self.name, "role": str(self.role), "tenant": self.tenant}
        if self.robots is not None:
            claims["robots"] = list(self.robots)
        if self.groups is not None:
            claims["groups"] = list(self.groups)
        return claims

    @classmethod
    def of_wire(cls, claims: Any, *, open_server: bool) -> Principal:
        """The caller another node of the fleet sent (`to_wire`), checked as a token's
        claims are. A call without one (a node of an older version) is refused on a node
        with keys or tokens (`open_server` False): it would run as the unlimited admin; on
        an open server it is the anonymous admin, as every caller there. ValueError for
        claims of the wrong shape, or missing where they are needed."""
        if claims is None:
            if not open_server:
                raise ValueError("the call names no caller, and this node needs one")
            return ANONYMOUS
        if not isinstance(claims, Mapping):
            raise ValueError("the caller must be claims")
        return principal_of(claims)


#: The caller of a server without keys or tokens (a loopback server for one person).
ANONYMOUS = Principal("anonymous", Role.ADMIN)


def _matches(name: str, patterns: tuple[str, ...]) -> bool:
    return any(fnmatch.fnmatchcase(name, pattern) for pattern in patterns)


def key_principal(index: int, viewer: bool) -> Principal:
    """The caller of the `index`-th API key (from 1): named by position, never by its text."""
    if viewer:
        return Principal(f"viewer-key-{index}", Role.VIEWER)
    return Principal(f"api-key-{index}", Role.ADMIN)


def unauthorized(message: str) -> ArenaError:
    """401: no credentials, or credentials that prove nothing."""
    return ArenaError(ErrorCode.UNAUTHORIZED, message)


class TokenVerifier:
    """Checks tokens against a shared secret and/or the public keys of a JWKS document."""

    def __init__(
        self,
        secret: bytes | None = None,
        jwks: Mapping[str, Any] | None = None,
        *,
        issuer: str | None = None,
        audience: str | None = None,
        leeway: float = 30.0,
    ) -> None:
        if secret is not None and len(secret) < 32:
            raise ArenaError(
                ErrorCode.INVALID_CONFIG,
                "The JWT secret must be 32 bytes or more (`openssl rand -hex 32` makes one).",
            )
        import jwt

        self.secret = secret
        self.keys: dict[str | None, jwt.PyJWK] = {}
        if jwks is not None:
            try:
                keyset = jwt.PyJWKSet.from_dict(dict(jwks))
            except (jwt.PyJWKSetError, jwt.InvalidKeyError) as exc:
                raise ArenaError(ErrorCode.INVALID_CONFIG, f"Invalid JWKS: {exc}") from None
            for key in keyset.keys:
                if key.algorithm_name not in PUBLIC_KEY_ALGORITHMS:
                    raise ArenaError(
                        ErrorCode.INVALID_CONFIG,
                        f"JWKS key {key.key_id!r} signs {key.algorithm_name}: Arena takes "
                        f"{', '.join(PUBLIC_KEY_ALGORITHMS)}.",
                    )
                self.keys[key.key_id] = key
        self.issuer = issuer
        self.audience = audience
        self.leeway = leeway

    @classmethod
    def from_files(
        cls,
        secret_file: str | None,
        jwks_file: str | None,
        *,
        issuer: str | None = None,
        audience: str | None = None,
        leeway: float = 30.0,
    ) -> TokenVerifier:
        """Read the secret (its first line) and the JWKS document; INVALID_CONFIG if either
        cannot be read."""
        secret = None if secret_file is None else read_secret(secret_file)
        jwks = None
        if jwks_file is not None:
            try:
                jwks = json.loads(Path(jwks_file).read_text(encoding="utf-8"))
            except (OSError, ValueError) as exc:
                raise ArenaError(
                    ErrorCode.INVALID_CONFIG, f"Cannot read the JWKS file {jwks_file}: {exc}"
                ) from None
        return cls(secret, jwks, issuer=issuer, audience=audience, leeway=leeway)

    def verify(self, token: str, now: float | None = None) -> Principal:
        """The caller a token names; `ArenaError(UNAUTHORIZED)` saying what is wrong with it
        (the token's text never appears in the message)."""
        import jwt

        try:
            header = jwt.get_unverified_header(token)
        except jwt.DecodeError:
            raise unauthorized("The credential is neither an API key nor a valid token.") from None
        algorithm = header.get("alg")
        if algorithm == "HS256" and self.secret is not None:
            key: Any = self.secret
        elif algorithm in PUBLIC_KEY_ALGORITHMS and self.keys:
            found = self.keys.get(header.get("kid"))
            if found is None and len(self.keys) == 1 and header.get("kid") is None:
                found = next(iter(self.keys.values()))
            if found is None or found.algorithm_name != algorithm:
                raise unauthorized("The token is signed by a key this server does not know.")
            key = found.key
        else:
            raise unauthorized(f"Tokens signed with alg {algorithm!r} are not accepted here.")
        try:  # the types first: PyJWT would read "exp": "1700000000" as a number
            check_claim_types(jwt.decode(token, options={"verify_signature": False}))
        except jwt.DecodeError:
            raise unauthorized("The credential is neither an API key nor a valid token.") from None
        except ValueError as exc:
            raise unauthorized(f"The token's claims are not valid: {exc}.") from None
        options: dict[str, Any] = {
            "require": ["exp", "sub"],
            "verify_aud": self.audience is not None,
            "verify_iss": self.issuer is not None,
        }
        try:
            claims = _decode(token, key, algorithm, self, options, now)
        except jwt.ExpiredSignatureError:
            raise unauthorized("The token has expired: get a new one.") from None
        except jwt.InvalidIssuerError:
            raise unauthorized(f"The token was not issued by {self.issuer!r}.") from None
        except jwt.InvalidAudienceError:
            raise unauthorized(f"The token is not meant for {self.audience!r}.") from None
        except jwt.MissingRequiredClaimError as exc:
            raise unauthorized(f"The token has no {exc.claim!r} claim.") from None
        except jwt.InvalidSignatureError:
            raise unauthorized("The token's signature is not valid.") from None
        except jwt.InvalidTokenError as exc:
            raise unauthorized(f"The token is not valid: {exc}.") from None
        try:
            return principal_of(claims, self.leeway)
        except ValueError as exc:
            raise unauthorized(f"The token's claims are not valid: {exc}.") from None


def _decode(
    token: str,
    key: Any,
    algorithm: str,
    verifier: TokenVerifier,
    options: dict[str, Any],
    now: float | None,
) -> dict[str, Any]:
    """PyJWT's decode, with `now` for tests (PyJWT reads the clock itself): the leeway is
    shifted by the difference, which is what a clock at `now` would decide."""
    import jwt

    shift = 0.0 if now is None else time.time() - now
    claims: dict[str, Any] = jwt.decode(
        token,
        key,
        algorithms=[algorithm],
        audience=verifier.audience,
        issuer=verifier.issuer,
        leeway=verifier.leeway + shift,
        options=options,  # type: ignore[arg-type]
    )
    return claims


#: Registered claims that are a time (seconds since 1970) and the ones that are a string.
_TIME_CLAIMS = ("exp", "nbf", "iat")
_STRING_CLAIMS = ("sub", "iss", "jti", "role", "tenant")


def check_claim_types(claims: Any) -> None:
    """ValueError naming the first claim of a type it may not have: a time that is not a
    finite number (a string such as "1700000000" included), a string claim that is not one,
    `aud` neither a string nor a list of strings, `robots` or `groups` not a list of strings.
    A token with such a claim is invalid, whatever a library would make of it."""
    if not isinstance(claims, Mapping):
        raise ValueError("the claims must be a JSON object")
    for name in _TIME_CLAIMS:
        if name in claims and not _is_time(claims[name]):
            raise ValueError(f"{name!r} must be a number of seconds since 1970")
    for name in _STRING_CLAIMS:
        if name in claims and not isinstance(claims[name], str):
            raise ValueError(f"{name!r} must be a string")
    aud = claims.get("aud")
    if aud is not None and not _strings(aud) and not isinstance(aud, str):
        raise ValueError("'aud' must be a string or a list of strings")
    for name in ("robots", "groups"):
        value = claims.get(name)
        if value is not None and not _strings(value):
            raise ValueError(f"{name!r} must be a list of glob patterns")


def _strings(value: Any) -> bool:
    return isinstance(value, list) and all(isinstance(item, str) for item in value)


def _is_time(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def principal_of(claims: Mapping[str, Any], leeway: float = 0.0) -> Principal:
    """The caller of verified claims; ValueError naming a claim of the wrong shape."""
    sub = claims.get("sub")
    if not isinstance(sub, str) or not sub or len(sub) > 200:
        raise ValueError("'sub' must be a name")
    role = claims.get("role", "viewer")
    if not isinstance(role, str):
        raise ValueError("'role' must be viewer, operator or admin")
    tenant = claims.get("tenant", DEFAULT_TENANT)
    if not isinstance(tenant, str) or not _TENANT.fullmatch(tenant):
        raise ValueError("'tenant' must be a name")
    exp = claims.get("exp")
    if exp is not None and not _is_time(exp):
        raise ValueError("'exp' must be a number of seconds since 1970")
    return Principal(
        sub,
        Role.named(role),
        tenant,
        _patterns(claims, "robots"),
        _patterns(claims, "groups"),
        None if exp is None else float(exp) + leeway,
    )


def _patterns(claims: Mapping[str, Any], name: str) -> tuple[str, ...] | None:
    value = claims.get(name)
    if value is None:
        return None
    if (
        not isinstance(value, list)
        or len(value) > _MOST_PATTERNS
        or not all(isinstance(p, str) and _NAME.fullmatch(p) for p in value)
    ):
        raise ValueError(f"{name!r} must be a list of at most {_MOST_PATTERNS} glob patterns")
    return tuple(value)


def read_secret(path: str) -> bytes:
    """The secret of a secret file (its first line, spaces stripped)."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ArenaError(
            ErrorCode.INVALID_CONFIG, f"Cannot read the JWT secret file {path}: {exc}"
        ) from None
    lines = text.strip().splitlines()
    if not lines or not lines[0].strip():
        raise ArenaError(ErrorCode.INVALID_CONFIG, f"The JWT secret file {path} is empty.")
    return lines[0].strip().encode()


_UNITS = {"s": 1, "m": 60, "h": 3600, "d": 86400}


def parse_duration(text: str) -> float:
    """`90`, `90s`, `15m`, `8h`, `7d` as seconds; ValueError otherwise."""
    match = re.fullmatch(r"\s*(\d+(?:\.\d+)?)\s*([smhd]?)\s*", text)
    if match is None:
        raise ValueError(f"{text!r} is not a duration (such as 90s, 15m, 8h or 7d)")
    return float(match.group(1)) * _UNITS[match.group(2) or "s"]


def mint(
    secret: bytes,
    sub: str,
    role: Role,
    ttl: float,
    *,
    robots: tuple[str, ...] | None = None,
    groups: tuple[str, ...] | None = None,
    tenant: str | None = None,
    issuer: str | None = None,
    audience: str | None = None,
    now: float | None = None,
) -> str:
    """A token signed HS256 with `secret`, valid for `ttl` seconds from `now`."""
    issued = time.time() if now is None else now
    claims: dict[str, Any] = {
        "sub": sub,
        "role": str(role),
        "iat": int(issued),
        "exp": int(issued + ttl),
    }
    if robots is not None:
        claims["robots"] = list(robots)
    if groups is not None:
        claims["groups"] = list(groups)
    if tenant is not None:
        claims["tenant"] = tenant
    if issuer is not None:
        claims["iss"] = issuer
    if audience is not None:
        claims["aud"] = audience
    principal_of(claims)  # refuse to mint what the server would refuse
    import jwt

    return jwt.encode(claims, secret, algorithm="HS256")
