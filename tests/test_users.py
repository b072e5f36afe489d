"""Users, roles and tenants (issue 49): tokens checked offline, a role per route, scope and
tenants that hide robots, tokens that expire mid-session, and who did what in the recording."""

from __future__ import annotations

import base64
import json
import logging
import re
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import httpx
import jwt
import pytest
import trio
from cryptography.hazmat.primitives.asymmetric import ec, rsa
from jwt.algorithms import ECAlgorithm, RSAAlgorithm
from trio_websocket import ConnectionClosed, open_websocket_url

from arena.cli import main
from arena.protocol.errors import ArenaError
from arena.recording import analysis
from arena.recording.mcap_file import read_recording
from arena.server.access import PUBLIC_ROUTES, ROLE_FOR, route_of
from arena.server.config import load_config
from arena.server.identity import Principal, Role, TokenVerifier, mint, parse_duration
from tests.conftest import RunningServer
from tests.test_server_ws import closed_with, command, receive

StartServer = Callable[..., Awaitable[RunningServer]]
SECRET = b"s3cret-for-the-tests-0123456789abcdef"
ADMIN_KEY = "adm1n-k3y-users"


def token(role: str = "operator", ttl: float = 3600, **claims: Any) -> str:
    """A token of the tests' secret."""
    return mint(SECRET, claims.pop("sub", f"{role}-user"), Role.named(role), ttl, **claims)


def bearer(text: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {text}"}


@pytest.fixture
def secret_file(tmp_path: Path) -> Path:
    path = tmp_path / "jwt-secret"
    path.write_bytes(SECRET + b"\n")
    return path


# -- tokens, offline ---------------------------------------------------------------------------


def _refusal(verifier: TokenVerifier, text: str) -> str:
    with pytest.raises(ArenaError) as refused:
        verifier.verify(text)
    assert str(refused.value.code) == "UNAUTHORIZED"
    return refused.value.message


def test_bad_tokens_are_refused_each_with_its_reason() -> None:
    verifier = TokenVerifier(SECRET, issuer="lab-idp", audience="arena", leeway=30)
    good = token(issuer="lab-idp", audience="arena")
    assert verifier.verify(good).role is Role.OPERATOR
    now = time.time()
    claims = {"sub": "mallory", "role": "admin", "exp": int(now) + 600, "iss": "lab-idp"}
    claims["aud"] = "arena"
    unsigned = jwt.encode(claims, None, algorithm="none")  # alg: none
    assert "alg 'none'" in _refusal(verifier, unsigned)
    other = jwt.encode(claims, b"another-secret-of-32-bytes-or-more!!", algorithm="HS256")
    assert "signature" in _refusal(verifier, other)
    head, body, signature = good.split(".")
    grown = json.loads(base64.urlsafe_b64decode(body + "=="))
    grown["role"] = "admin"  # a user who makes themselves admin
    forged = base64.urlsafe_b64encode(json.dumps(grown).encode()).rstrip(b"=").decode()
    assert "signature" in _refusal(verifier, f"{head}.{forged}.{signature}")
    wrong_issuer = token(issuer="elsewhere", audience="arena")
    assert "lab-idp" in _refusal(verifier, wrong_issuer)
    wrong_audience = token(issuer="lab-idp", audience="another-service")
    assert "'arena'" in _refusal(verifier, wrong_audience)
    expired = mint(SECRET, "bob", Role.VIEWER, 60, issuer="lab-idp", audience="arena",
                   now=now - 120)  # fmt: skip
    assert "expired" in _refusal(verifier, expired)
    # ... but within the leeway (30 s) a token just past its `exp` still passes.
    late = mint(SECRET, "bob", Role.VIEWER, 60, issuer="lab-idp", audience="arena", now=now - 75)
    assert verifier.verify(late).name == "bob"
    no_sub = jwt.encode({k: v for k, v in claims.items() if k != "sub"}, SECRET, "HS256")
    assert "'sub'" in _refusal(verifier, no_sub)
    bad_role = jwt.encode({**claims, "role": "root"}, SECRET, "HS256")
    assert "role" in _refusal(verifier, bad_role)
    assert "neither" in _refusal(verifier, "not-a-token")


def test_public_keys_of_a_jwks_file_verify_rs256_and_es256_and_nothing_else(
    tmp_path: Path,
) -> None:
    rsa_key = rsa.generate_private_key(public_exponent=65537, key_size=2048)
    ec_key = ec.generate_private_key(ec.SECP256R1())
    keys = [
        {**json.loads(RSAAlgorithm.to_jwk(rsa_key.public_key())), "kid": "r1", "alg": "RS256"},
        {**json.loads(ECAlgorithm.to_jwk(ec_key.public_key())), "kid": "e1", "alg": "ES256"},
    ]
    jwks = tmp_path / "jwks.json"
    jwks.write_text(json.dumps({"keys": keys}))
    verifier = TokenVerifier.from_files(None, str(jwks), audience="arena")
    claims = {"sub": "carol", "role": "admin", "exp": int(time.time()) + 600, "aud": "arena"}
    claims["robots"] = ["lab-*"]
    by_rsa = jwt.encode(claims, rsa_key, algorithm="RS256", headers={"kid": "r1"})
    by_ec = jwt.encode(claims, ec_key, algorithm="ES256", headers={"kid": "e1"})
    assert verifier.verify(by_rsa) == verifier.verify(by_ec)
    assert verifier.verify(by_rsa).covers("lab-3") and not verifier.verify(by_rsa).covers("x")
    assert "does not know" in _refusal(
        verifier, jwt.encode(claims, rsa_key, algorithm="RS256", headers={"kid": "e1"})
    )
    # The public key as an HMAC secret (algorithm confusion), and a secret-signed token on a
    # server that has no secret: refused.
    assert "HS256" in _refusal(verifier, jwt.encode(claims, SECRET, algorithm="HS256"))


def test_scope_globs_and_durations() -> None:
    scoped = Principal("a", Role.OPERATOR, robots=("lab-*",), groups=("cell-?",))
    assert scoped.covers("lab-1") and not scoped.covers("arm-1")
    assert scoped.covers("arm-1", ["cell-2"]) and not scoped.covers("arm-1", ["cell-10"])
    assert Principal("b", Role.VIEWER).covers("anything")
    assert [parse_duration(t) for t in ("90", "90s", "15m", "8h", "7d")] == [
        90,
        90,
        900,
        28800,
        604800,
    ]
    with pytest.raises(ValueError):
        parse_duration("8 hours")


def test_arena_token_mints_what_the_server_takes(
    secret_file: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["token", "--sub", "alice", "--role", "operator", "--robots", "lab-*,cell-1"]
    assert (
        main([*argv, "--ttl", "8h", "--tenant", "acme", "--jwt-secret-file", str(secret_file)]) == 0
    )
    principal = TokenVerifier(SECRET).verify(capsys.readouterr().out.strip())
    assert principal == Principal(
        "alice", Role.OPERATOR, "acme", ("lab-*", "cell-1"), None, principal.expires
    )
    assert principal.expires is not None
    assert abs(principal.expires - 30 - (time.time() + 8 * 3600)) < 60
    assert main(["token", "--sub", "alice"]) == 2  # no secret: one line, exit 2
    assert "jwt-secret-file" in capsys.readouterr().err


# -- every route has a role ---------------------------------------------------------------------


async def test_every_route_of_the_app_has_a_role_or_is_public(start_server: StartServer) -> None:
    server = await start_server()
    routes = {
        route_of(method, rule.rule)
        for rule in server.app.url_map.iter_rules()
        if rule.endpoint != "static"
        for method in rule.methods or ()
        if method not in ("HEAD", "OPTIONS")
    }
    assert routes - set(ROLE_FOR) - PUBLIC_ROUTES == set()
    assert set(ROLE_FOR) - routes == set()  # no stale entry either
    assert not set(ROLE_FOR) & PUBLIC_ROUTES


def test_the_role_table_of_the_api_spec_is_the_code_s() -> None:
    spec = (Path(__file__).resolve().parent.parent / "specs" / "api.md").read_text()
    written: dict[tuple[str, str], Role] = {}
    for line in spec.splitlines():
        cells = line.split(" | ")
        if len(cells) == 2 and cells[0].lstrip("| ") in ("viewer", "operator", "admin"):
            role = Role.named(cells[0].lstrip("| "))
            for route in re.findall(r"`(GET|POST|PUT|DELETE) ([^`]+)`", cells[1]):
                written[route] = role
    assert written == ROLE_FOR


# -- the matrix: role x action x scope x tenant, over REST and WebSocket ----------------------


async def _tenanted_server(start_server: StartServer, secret_file: Path) -> RunningServer:
    """Robots lab-1, lab-2 (tenant default) and acme-1 (tenant acme)."""
    server = await start_server(api_keys=(ADMIN_KEY,), jwt_secret_file=str(secret_file))
    async with server.client() as http:
        for robot_id in ("lab-1", "lab-2"):
            made = await http.post("/api/robots", json={"id": robot_id}, headers=bearer(ADMIN_KEY))
            assert (made.status_code, made.json()["tenant"]) == (201, "default")
        acme = bearer(token("admin", tenant="acme"))
        made = await http.post("/api/robots", json={"id": "acme-1"}, headers=acme)
        assert (made.status_code, made.json()["tenant"]) == (201, "acme")
        # A tenant's admin creates only in its own tenant.
        elsewhere = await http.post(
            "/api/robots", json={"id": "x", "tenant": "default"}, headers=acme
        )
        assert elsewhere.status_code == 403
    return server


#: (action, role it needs, method, path under /api/robots/{id}, body)
ACTIONS: list[tuple[str, Role, str, str, Any]] = [
    ("read", Role.VIEWER, "GET", "", None),
    ("joints", Role.VIEWER, "GET", "/joints", None),
    ("estop", Role.VIEWER, "POST", "/estop", None),
    ("reset", Role.OPERATOR, "POST", "/reset", None),
    ("command", Role.OPERATOR, "PUT", "/joints", {"joints": [{"name": "Rotation", "value": 5}]}),
    ("release master", Role.OPERATOR, "DELETE", "/master", None),
    ("workspace", Role.ADMIN, "PUT", "/workspace", {"floor": None, "keep_out": []}),
    ("slave", Role.ADMIN, "POST", "/slaves", {"type": "mock-slave"}),
]


async def test_rest_matrix_of_roles_scope_and_tenants(
    start_server: StartServer, secret_file: Path
) -> None:
    server = await _tenanted_server(start_server, secret_file)
    targets = {"lab-1": "in scope", "lab-2": "out of scope", "acme-1": "other tenant"}
    async with server.client() as http:
        for role in Role:
            caller = bearer(token(str(role), robots=["lab-1"]))
            listed = (await http.get("/api/robots", headers=caller)).json()
            assert [robot["id"] for robot in listed] == ["lab-1"], role
            for robot_id, where in targets.items():
                for action, needed, method, path, body in ACTIONS:
                    reply = await http.request(
                        method, f"/api/robots/{robot_id}{path}", headers=caller, json=body
                    )
                    # The role is checked first, whatever the robot (so a refusal tells
                    # nothing about robots); then a robot not the caller's is as if absent.
                    if role < needed:
                        expected = (403, "FORBIDDEN")
                    elif where != "in scope":
                        expected = (404, "UNKNOWN_ROBOT")
                    else:
                        expected = (reply.status_code, None)
                        assert reply.status_code < 300, (role, action, reply.text)
                    code = reply.json()["error"]["code"] if reply.status_code >= 400 else None
                    assert (reply.status_code, code) == expected, (role, action, where)
            # A robot of another tenant answers exactly as one that does not exist.
            ghost = await http.get("/api/robots/no-such-robot", headers=caller)
            hidden = await http.get("/api/robots/acme-1", headers=caller)
            assert hidden.json() == ghost.json() | {
                "error": {**ghost.json()["error"], "message": "No robot with id 'acme-1'."}
            }
        # The e-stop of every robot stops only those the caller sees.
        await http.post("/api/robots/lab-1/reset", headers=bearer(ADMIN_KEY))
        stopped = await http.post("/api/estop", headers=bearer(token("viewer", tenant="acme")))
        assert stopped.json() == {"estopped": ["acme-1"]}
        states = {
            r["id"]: r["state"]
            for r in (await http.get("/api/robots", headers=bearer(ADMIN_KEY))).json()
        }
        assert states == {"lab-1": "idle", "lab-2": "idle"}  # the key is of tenant default
        metrics = (await http.get("/metrics", headers=bearer(ADMIN_KEY))).text
    assert 'arena_auth_refused_total{reason="role"}' in metrics
    assert 'arena_auth_refused_total{reason="scope"}' in metrics


async def test_websocket_matrix_of_roles_scope_and_tenants(
    start_server: StartServer, secret_file: Path
) -> None:
    server = await _tenanted_server(start_server, secret_file)
    paths = {"master": "/ws/master/{}", "slave": "/ws/slave/{}", "viewer": "/ws/robots/{}/state"}
    needs = {"master": Role.OPERATOR, "slave": Role.ADMIN, "viewer": Role.VIEWER}
    for role in Role:
        caller = token(str(role), robots=["lab-1"])
        for endpoint, path in paths.items():
            for robot_id in ("lab-1", "lab-2", "acme-1"):
                url = server.ws_url + path.format(robot_id) + f"?token={caller}"
                async with open_websocket_url(url) as ws:
                    first = json.loads(await ws.get_message())
                    if role < needs[endpoint]:
                        expected = ("error", "FORBIDDEN", 4403)
                    elif robot_id != "lab-1":
                        expected = ("error", "UNKNOWN_ROBOT", 4404)
                    else:
                        expected = ("accepted", None, None)
                    if first["type"] == "error":
                        got = ("error", first["data"]["code"], await closed_with(ws))
                    else:
                        got = ("accepted", None, None)
                        assert first["type"] in ("state", "execute_command", "heartbeat")
                    assert got == expected, (role, endpoint, robot_id)
        async with httpx.AsyncClient(base_url=server.url) as http:  # a slave left: reset
            await http.post("/api/robots/lab-1/reset", headers=bearer(ADMIN_KEY))


async def test_a_token_s_groups_reach_the_robots_in_those_groups(
    start_server: StartServer, secret_file: Path
) -> None:
    server = await _tenanted_server(start_server, secret_file)
    cell = token("operator", groups=["cell-*"])
    async with server.client() as http:
        made = await http.post(
            "/api/groups", json={"id": "cell-1", "members": ["lab-2"]}, headers=bearer(ADMIN_KEY)
        )
        assert made.status_code == 201
        listed = (await http.get("/api/robots", headers=bearer(cell))).json()
        assert [robot["id"] for robot in listed] == ["lab-2"]
        groups = (await http.get("/api/groups", headers=bearer(cell))).json()["groups"]
        assert [group["id"] for group in groups] == ["cell-1"]
        for robot_id, status in (("lab-2", 200), ("lab-1", 404), ("acme-1", 404)):
            reset = await http.post(f"/api/robots/{robot_id}/reset", headers=bearer(cell))
            assert reset.status_code == status, robot_id
        assert (await http.post("/api/groups/cell-1/estop", headers=bearer(cell))).is_success
    for robot_id, first in (("cell-1", "state"), ("lab-2", "state"), ("lab-1", "error")):
        async with open_websocket_url(f"{server.ws_url}/ws/master/{robot_id}?token={cell}") as ws:
            message = json.loads(await ws.get_message())
            assert message["type"] == first, (robot_id, message)
            if first == "error":
                assert (message["data"]["code"], await closed_with(ws)) == ("UNKNOWN_ROBOT", 4404)


async def test_what_another_tenant_has_is_as_if_it_did_not_exist(
    start_server: StartServer, secret_file: Path
) -> None:
    server = await _tenanted_server(start_server, secret_file)
    acme, ours = bearer(token("admin", tenant="acme")), bearer(ADMIN_KEY)
    scoped = token("operator", robots=["lab-1"])  # of our tenant, seeing lab-1 alone
    async with server.client() as http:
        for group_id in ("cell", "acme-cell"):
            made = await http.post(
                "/api/groups", json={"id": group_id, "members": ["acme-1"]}, headers=acme
            )
            assert made.status_code == 201
        made = await http.post("/api/groups", json={"id": "pair", "members": ["lab-1", "lab-2"]},
                               headers=ours)  # fmt: skip
        assert made.status_code == 201
        # Ids another tenant holds, a group's or a robot's, are free in ours.
        for group_id in ("cell", "acme-1"):
            made = await http.post(
                "/api/groups", json={"id": group_id, "members": ["lab-1"]}, headers=ours
            )
            assert (made.status_code, made.json().get("members")) == (201, ["lab-1"]), group_id
        listed = (await http.get("/api/groups", headers=ours)).json()["groups"]
        assert sorted(group["id"] for group in listed) == ["acme-1", "cell", "pair"]
        theirs = (await http.get("/api/groups/cell", headers=acme)).json()
        assert theirs["members"] == ["acme-1"]  # each tenant's own "cell"
        # A group the caller may not see, of another tenant or with a member out of its
        # scope, is a WebSocket to a robot that does not exist: 4404, as for no robot at all.
        for caller, group_id in ((token("operator"), "acme-cell"), (scoped, "pair")):
            answers = []
            for path in (group_id, "no-such-robot"):
                url = f"{server.ws_url}/ws/master/{path}?token={caller}"
                async with open_websocket_url(url) as ws:
                    error = await receive(ws, "error")
                    said = error["data"]["message"].replace(path, "ID")
                    answers.append((error["data"]["code"], said, await closed_with(ws)))
            assert answers[0] == answers[1] == ("UNKNOWN_ROBOT", "No robot with id 'ID'.", 4404)
        # Connections are counted to those who see their robots only.
        url = f"{server.ws_url}/ws/master/acme-1?token={token('operator', tenant='acme')}"
        async with open_websocket_url(url) as ws:
            await receive(ws, "state")
            for caller, masters in ((acme, 1), (ours, 0), (bearer(scoped), 0)):
                status = (await http.get("/", headers=caller)).json()
                assert status["connections"].get("master", 0) == masters, caller
                metrics = (await http.get("/metrics", headers=caller)).text
                assert f'arena_connections{{role="master"}} {masters}' in metrics, caller
            # Figures of the whole server go to its own callers, not to a tenant's.
            assert "arena_http_requests_total" in (await http.get("/metrics", headers=ours)).text
            assert (
                "arena_http_requests_total" not in (await http.get("/metrics", headers=acme)).text
            )


async def test_bad_tokens_over_http_and_websocket_say_why_and_are_counted(
    start_server: StartServer, secret_file: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="arena.server.auth")
    server = await start_server(
        jwt_secret_file=str(secret_file), jwt_issuer="lab-idp", jwt_audience="arena", demo=True
    )
    ours = {"issuer": "lab-idp", "audience": "arena"}
    good = token("admin", **ours)
    head, body, signature = good.split(".")
    claims = json.loads(base64.urlsafe_b64decode(body + "=="))
    grown = base64.urlsafe_b64encode(json.dumps({**claims, "sub": "root"}).encode())
    other_secret = b"another-secret-of-32-bytes-or-more!!"
    bad = {  # each refused token, and a word of what the refusal says
        "expired": (mint(SECRET, "bob", Role.ADMIN, 60, now=time.time() - 600, **ours), "expired"),
        "wrong issuer": (token("admin", issuer="elsewhere", audience="arena"), "lab-idp"),
        "wrong audience": (token("admin", issuer="lab-idp", audience="other"), "'arena'"),
        "badly signed": (jwt.encode(claims, other_secret, algorithm="HS256"), "signature"),
        "alg none": (jwt.encode(claims, None, algorithm="none"), "not accepted"),
        "tampered": (f"{head}.{grown.rstrip(b'=').decode()}.{signature}", "signature"),
        "junk": ("junk", "neither"),
    }
    async with server.client() as http:
        for what, (text, words) in bad.items():
            reply = await http.post("/api/robots/demo-arm/estop", headers=bearer(text))
            said = reply.json()["error"]
            assert (reply.status_code, said["code"]) == (401, "UNAUTHORIZED"), what
            assert words in said["message"], (what, said)
            assert (
                await http.get("/api/robots/demo-arm/status", headers=bearer(text))
            ).status_code == 401
            url = f"{server.ws_url}/ws/master/demo-arm?token={text}"
            async with open_websocket_url(url) as ws:
                error = await receive(ws, "error")
                assert (error["data"]["code"], await closed_with(ws)) == ("UNAUTHORIZED", 4401)
                assert words in error["data"]["message"], what
        assert (await http.get("/api/robots")).status_code == 401
        viewer = bearer(token("viewer", **ours))
        state = await http.get("/api/robots/demo-arm", headers=viewer)
        assert state.json()["state"] == "idle"  # nothing a refused caller sent was done
        metrics = (await http.get("/metrics", headers=viewer)).text
    assert 'arena_auth_refused_total{reason="expired"} 3' in metrics
    assert 'arena_auth_refused_total{reason="invalid"} 18' in metrics
    assert 'arena_auth_refused_total{reason="missing"} 1' in metrics
    # Each refusal logged by its reason; no token's text in the log or the metrics.
    refusals = [r.getMessage() for r in caplog.records if "refused a caller" in r.getMessage()]
    assert refusals.count("refused a caller: invalid") == 18 and len(refusals) == 22
    logged = "\n".join(r.getMessage() for r in caplog.records) + metrics
    assert not [what for what, (text, _) in bad.items() if text in logged and text != "junk"]
    assert "bob" not in logged and signature not in logged


def test_a_claim_of_the_wrong_type_makes_an_invalid_token() -> None:
    verifier = TokenVerifier(SECRET, issuer="lab-idp", audience="arena")
    later = int(time.time()) + 600
    good = {"sub": "eve", "exp": later, "iat": later - 600, "iss": "lab-idp", "aud": "arena"}
    assert verifier.verify(jwt.encode(good, SECRET, "HS256")).expires == later + 30
    wrong = {  # each claim Arena or PyJWT reads, of a type it is not
        "exp": str(later),  # a string PyJWT would read as a number: never expiring
        "nbf": str(later - 600),
        "iat": str(later - 600),
        "exp ": True,  # (key trimmed below) a boolean is no number of seconds
        "exp  ": float("inf"),
        "iss": 5,  # PyJWT raises a TypeError of its own on this one
        "aud": 5,
        "sub": 7,
        "role": ["admin"],
        "tenant": 3,
        "robots": "lab-*",
        "groups": [1],
        "jti": 9,
    }
    for key, value in wrong.items():
        claim = key.strip()  # signed as is (PyJWT's encode refuses some of these)
        text = jwt.PyJWS().encode(json.dumps({**good, claim: value}).encode(), SECRET, "HS256")
        assert f"'{claim}'" in _refusal(verifier, text), (claim, value)


async def test_a_token_whose_expiry_is_a_string_opens_no_websocket(
    start_server: StartServer, secret_file: Path
) -> None:
    server = await start_server(jwt_secret_file=str(secret_file), demo=True)
    claims = {"sub": "eve", "role": "viewer", "exp": str(int(time.time()) + 600)}
    text = jwt.encode(claims, SECRET, "HS256")
    async with open_websocket_url(f"{server.ws_url}/ws/robots/demo-arm/state?token={text}") as ws:
        error = await receive(ws, "error")
        assert (error["data"]["code"], await closed_with(ws)) == ("UNAUTHORIZED", 4401)
        assert "'exp'" in error["data"]["message"]
    async with server.client() as http:
        reply = await http.get("/api/robots", headers=bearer(text))
    assert (reply.status_code, reply.json()["error"]["code"]) == (401, "UNAUTHORIZED")


async def test_a_websocket_whose_token_expires_is_closed_with_4401(
    autojump_clock: trio.testing.MockClock, start_server: StartServer, secret_file: Path
) -> None:
    server = await start_server(jwt_secret_file=str(secret_file), demo=True)
    # Valid for an hour of wall-clock time, plus the 30 s leeway: the server takes the
    # deadline to trio's clock at connect, and this test's clock is virtual.
    hour = token("viewer", ttl=3600)
    async with open_websocket_url(f"{server.ws_url}/ws/robots/demo-arm/state?token={hour}") as ws:
        await receive(ws, "state")
        started = trio.current_time()
        messages = []
        with trio.fail_after(2 * 3600), pytest.raises(ConnectionClosed) as closed:
            while True:
                messages.append(json.loads(await ws.get_message()))
        lasted = trio.current_time() - started
    assert closed.value.reason.code == 4401
    assert messages[-1]["type"] == "error" and "expired" in messages[-1]["data"]["message"]
    assert 3600 + 30 - 60 < lasted <= 3600 + 30  # (less the real seconds since it was minted)
    assert sum(m["type"] == "heartbeat" for m in messages) >= 100  # it lived until then


# -- who did what, read back from the recording -----------------------------------------------


async def test_the_audit_trail_is_read_back_from_the_recording(
    start_server: StartServer,
    secret_file: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    recordings = tmp_path / "audit"
    server = await start_server(
        api_keys=(ADMIN_KEY,), jwt_secret_file=str(secret_file), recordings_dir=str(recordings)
    )
    alice = token("operator", sub="alice", robots=["arm"])
    async with server.client() as http:
        await http.post("/api/robots", json={"id": "arm"}, headers=bearer(ADMIN_KEY))
        slave = await http.post("/api/robots/arm/slaves", json={"type": "mock-slave"},
                                headers=bearer(ADMIN_KEY))  # fmt: skip
        assert slave.status_code == 201
        async with open_websocket_url(
            f"{server.ws_url}/ws/master/arm?id=alice-ui&token={alice}"
        ) as ws:
            await receive(ws, "state")
            assert (await command(ws, {"Rotation": 12}))["data"]["status"] == "accepted"
            await ws.send_message(json.dumps({"type": "estop"}))
            await receive(ws, "state")
            await ws.send_message(json.dumps({"type": "release"}))
            await receive(ws, "released")
        bob = bearer(token("viewer", sub="bob"))
        assert (await http.post("/api/robots/arm/reset", headers=bob)).status_code == 403
        assert (await http.post("/api/robots/arm/estop", headers=bob)).status_code == 200
        assert (await http.post("/api/robots/arm/reset", headers=bearer(alice))).status_code == 200
    server.stop.set()
    await server.done.wait()
    [path] = recordings.glob("*.mcap")
    recording = read_recording(path)
    trail = [
        (m.data["user"], m.data["action"], m.data["detail"])
        for m in recording.messages
        if m.kind == "audit"
    ]
    assert trail == [
        ("api-key-1", "POST /api/robots", "201"),
        ("api-key-1", "POST /api/robots/{robot_id}/slaves", "201"),
        ("alice", "connect master", "alice-ui"),
        ("alice", "estop over WebSocket", "alice-ui"),
        ("alice", "release over WebSocket", "alice-ui"),
        ("bob", "POST /api/robots/{robot_id}/estop", "200"),
        ("alice", "POST /api/robots/{robot_id}/reset", "200"),
    ]  # bob's refused reset changed nothing and is only counted
    lines = analysis.timeline(recording, "arm")
    assert any(
        "command" in line and "Rotation=12" in line and "(by alice)" in line for line in lines
    )
    assert any("bob: POST /api/robots/{robot_id}/estop (200)" in line for line in lines)
    summary = analysis.summarize(recording)
    assert summary["users"] == ["alice", "api-key-1", "bob"]
    assert SECRET.decode() not in path.read_bytes().decode("latin-1")
    assert alice not in path.read_bytes().decode("latin-1")
    # ... and as the command line shows it.
    capsys.readouterr()
    assert main(["inspect", str(path)]) == 0
    inspected = capsys.readouterr().out
    assert "users      alice, api-key-1, bob" in inspected
    assert "user=api-key-1 action=POST /api/robots detail=201" in inspected
    assert main(["timeline", str(path), "--robot", "arm"]) == 0
    shown = capsys.readouterr().out.splitlines()
    assert any("alice: release over WebSocket (alice-ui)" in line for line in shown), shown
    assert any("(by alice)" in line and "Rotation=12" in line for line in shown)


async def test_openapi_gives_each_operation_its_role(start_server: StartServer) -> None:
    server = await start_server()
    async with server.client() as http:
        document = (await http.get("/openapi.json")).json()
    roles = {
        (method.upper(), path): operation.get("x-arena-role")
        for path, operations in document["paths"].items()
        for method, operation in operations.items()
    }
    assert roles[("POST", "/api/robots/{robot_id}/estop")] == "viewer"
    assert roles[("PUT", "/api/robots/{robot_id}/joints")] == "operator"
    assert roles[("POST", "/api/robots")] == "admin"
    assert all(roles[route] == str(role) for route, role in ROLE_FOR.items() if route in roles)


def test_token_settings_come_from_flags_the_environment_and_the_file(tmp_path: Path) -> None:
    settings = tmp_path / "arena.toml"
    settings.write_text('jwt_issuer = "from-file"\njwt_audience = "arena"\n')
    environ = {"ARENA_JWT_SECRET_FILE": "/run/secrets/jwt", "ARENA_JWT_LEEWAY": "5"}
    config = load_config(str(settings), environ, jwt_issuer="from-flag")
    assert (config.jwt_secret_file, config.jwt_leeway) == ("/run/secrets/jwt", 5.0)
    assert (config.jwt_issuer, config.jwt_audience) == ("from-flag", "arena")
    assert config.auth_enabled and not load_config(None, {}).auth_enabled
    with pytest.raises(ArenaError, match="jwt_leeway"):
        load_config(None, {"ARENA_JWT_LEEWAY": "-1"}).check()
    # Tokens are enough to listen beyond loopback; a too-short secret is refused at start.
    load_config(None, environ, host="0.0.0.0").check()
    short = tmp_path / "short"
    short.write_text("tiny\n")
    with pytest.raises(ArenaError, match="32 bytes"):
        TokenVerifier.from_files(str(short), None)
