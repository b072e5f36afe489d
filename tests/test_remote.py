"""Remote operation across Arena servers in one process: the websocket-slave and the
remote-server master, chained through a relay; links dropped and recovered."""

from __future__ import annotations

import itertools
import random
from collections.abc import Awaitable, Callable

import pytest
import trio

from arena.client import AsyncArena, Backoff, MasterSession, Refused, Session
from tests.conftest import RunningServer, eventually

StartServer = Callable[..., Awaitable[RunningServer]]
FAST = {"reconnectInitial": 0.05, "reconnectMax": 0.2}


async def relay_chain(
    start_server: StartServer,
) -> tuple[RunningServer, RunningServer, RunningServer]:
    """Operator server A (robot `avatar`), relay R (`relay-arm`), arm server B (`physical`
    with a simulated arm): A's websocket-slave masters R's robot, B's remote-server master
    takes R's targets."""
    a, r, b = [await start_server() for _ in range(3)]
    async with AsyncArena(r.url) as relay:
        await relay.create_robot("relay-arm")
    async with AsyncArena(b.url) as arm:
        await arm.create_robot("physical")
        await arm.attach_slave("physical", {"type": "mock-slave"})
        await arm.attach_master(
            "physical", {"type": "remote-server", "url": r.ws_url, "robotId": "relay-arm", **FAST}
        )
    async with AsyncArena(a.url) as operator:
        await operator.create_robot("avatar")
        await operator.attach_slave(
            "avatar", {"type": "websocket-slave", "url": r.url, "robotId": "relay-arm", **FAST}
        )
    return a, r, b


def real(server: RunningServer, robot_id: str, joint: str) -> float | None:
    return server.app.manager.get(robot_id).snapshot().joint(joint).real_value


async def test_an_operator_drives_an_arm_on_another_server_through_a_relay(
    start_server: StartServer,
) -> None:
    a, r, b = await relay_chain(start_server)
    async with MasterSession.open(a.url, "avatar") as operator:
        ack = await operator.command({"Rotation": 12, "Elbow": -8})
        assert ack["data"]["status"] in ("accepted", "clamped"), ack
        # B's simulated arm gets there, and the operator sees B's real values on A.
        physical = b.app.manager.get("physical")
        await eventually(lambda: physical.snapshot().joint("Rotation").goal == 12)
        await eventually(lambda: abs((real(a, "avatar", "Rotation") or 0) - 12) < 0.01)
        await operator.wait_for(lambda m: abs((m.real("Elbow") or 0) + 8) < 0.01)
    # Each server shows who holds what.
    relay_robot = r.app.manager.get("relay-arm").snapshot()
    assert relay_robot.master is not None and relay_robot.master.kind == "websocket"
    assert [s.peer_id for s in relay_robot.slaves] == ["remote-physical"]


async def test_estop_travels_down_the_chain_and_reset_brings_it_back(
    start_server: StartServer,
) -> None:
    a, r, b = await relay_chain(start_server)
    async with MasterSession.open(a.url, "avatar") as operator, AsyncArena(a.url) as rest_a:
        await operator.command({"Rotation": 5})
        await eventually(lambda: real(b, "physical", "Rotation") == 5)
        await rest_a.estop("avatar", "operator pressed stop")
        await eventually(lambda: str(b.app.manager.get("physical").snapshot().mode) == "estopped")
        assert str(r.app.manager.get("relay-arm").snapshot().mode) == "estopped"
        with pytest.raises(Refused) as refused:
            await operator.command({"Rotation": 9})
        assert refused.value.code == "ESTOPPED"
        await rest_a.reset("avatar")
        # The reset travels too, because the e-stops below were raised by the chain itself.
        await eventually(lambda: str(b.app.manager.get("physical").snapshot().mode) != "estopped")
        await eventually(lambda: str(r.app.manager.get("relay-arm").snapshot().mode) != "estopped")
        assert (await operator.command({"Rotation": 9}))["data"]["status"] == "accepted"
        await eventually(lambda: real(b, "physical", "Rotation") == 9)


async def test_the_relay_stops_and_restarts_mid_motion(start_server: StartServer) -> None:
    a, r, b = await relay_chain(start_server)
    port = int(r.url.rsplit(":", 1)[1])
    async with MasterSession.open(a.url, "avatar") as operator:
        await operator.command({"Rotation": 3})
        await eventually(lambda: real(b, "physical", "Rotation") == 3)
        await operator.command({"Rotation": 25})  # a long move: the relay goes mid-way
        r.stop.set()
        with trio.fail_after(10):
            await r.done.wait()
        # Both ends apply their own loss policy at once: e-stop.
        await eventually(lambda: str(a.app.manager.get("avatar").snapshot().mode) == "estopped")
        await eventually(lambda: str(b.app.manager.get("physical").snapshot().mode) == "estopped")
        frozen = b.app.manager.get("physical").snapshot().joint("Rotation").goal
        avatar = a.app.manager.get("avatar").snapshot()
        assert not avatar.slaves[0].connected  # shown as disconnected, still attached
        # The relay comes back on the same port; both links find it by themselves.
        r2 = await start_server(port=port)
        async with AsyncArena(r2.url) as relay:
            await relay.create_robot("relay-arm")
        # Both links attached to the new relay robot: an attempt that came before the robot
        # existed (refused with 4404, one more e-stop) is over before the resets below.
        await eventually(lambda: a.app.manager.get("avatar").snapshot().slaves[0].connected)
        await eventually(lambda: len(r2.app.manager.get("relay-arm").snapshot().slaves) == 1)
        await eventually(lambda: r2.app.manager.get("relay-arm").snapshot().master is not None)
        await trio.sleep(0.3)
        # Nothing queued during the outage ran: B has not moved since it stopped.
        assert b.app.manager.get("physical").snapshot().joint("Rotation").goal == frozen
        async with AsyncArena(a.url) as rest_a, AsyncArena(b.url) as rest_b:
            await rest_b.reset("physical")  # an e-stop from a lost link is reset by a person
            await rest_a.reset("avatar")
        assert (await operator.command({"Rotation": 7}))["data"]["status"] in (
            "accepted",
            "clamped",
        )
        await eventually(lambda: real(b, "physical", "Rotation") == 7)


async def test_attaching_to_a_wrong_remote_is_refused_at_once(
    start_server: StartServer,
) -> None:
    a = await start_server()
    r = await start_server(api_keys=("relay-key",))
    async with AsyncArena(r.url, api_key="relay-key") as relay:
        await relay.create_robot("relay-arm")
    async with a.client() as http:
        await http.post("/api/robots", json={"id": "avatar"})
        cases = [
            ({"url": r.url, "robotId": "relay-arm"}, 502, "REMOTE_REFUSED"),  # no key
            ({"url": r.url, "robotId": "nope", "apiKey": "relay-key"}, 502, "REMOTE_REFUSED"),
            ({"url": "http://127.0.0.1:9", "robotId": "relay-arm"}, 502, "REMOTE_UNREACHABLE"),
            ({"url": "ftp://example", "robotId": "relay-arm"}, 422, "INVALID_BODY"),
        ]
        for config, status, code in cases:
            answer = await http.post(
                "/api/robots/avatar/slaves", json={"type": "websocket-slave", **config}
            )
            assert (answer.status_code, answer.json()["error"]["code"]) == (status, code), config
            assert "relay-key" not in answer.text
        good = {
            "type": "websocket-slave",
            "url": r.url,
            "robotId": "relay-arm",
            "apiKey": "relay-key",
        }
        assert (await http.post("/api/robots/avatar/slaves", json=good)).status_code == 201
    await eventually(lambda: r.app.manager.get("relay-arm").snapshot().master is not None)


@pytest.mark.parametrize("seed", [1, 2])
async def test_reconnection_backoff_grows_with_jitter_and_is_bounded(
    autojump_clock: trio.testing.MockClock, seed: int
) -> None:
    attempts: list[float] = []

    class Unreachable(Session):
        async def _connect_once(self) -> str:
            attempts.append(trio.current_time())
            return "cannot connect: refused"

    backoff = Backoff(initial=0.5, maximum=4.0, factor=2.0, jitter=0.2)
    session = Unreachable("ws://127.0.0.1:9/x", backoff=backoff, rng=random.Random(seed))
    with trio.move_on_after(60):
        await session.run()
    gaps = [later - earlier for earlier, later in itertools.pairwise(attempts)]
    expected = backoff.delays(random.Random(seed))
    assert gaps == pytest.approx([next(expected) for _ in gaps])
    bases = [0.5, 1.0, 2.0, 4.0, 4.0, 4.0]
    for gap, base in zip(gaps, bases, strict=False):
        assert base * 0.8 <= gap <= base * 1.2
    assert max(gaps) <= 4.0 * 1.2
    assert len(set(gaps)) == len(gaps)  # jittered: no two waits alike


async def test_detaching_the_websocket_slave_releases_the_robot_over_there(
    start_server: StartServer,
) -> None:
    a, r, b = await relay_chain(start_server)
    relay = r.app.manager.get("relay-arm")
    async with MasterSession.open(a.url, "avatar") as operator:
        await operator.command({"Rotation": 6})
        await eventually(lambda: real(b, "physical", "Rotation") == 6)
    async with AsyncArena(a.url) as rest_a:
        (slave,) = (await rest_a.robot("avatar"))["slaves"]
        await rest_a._call("DELETE", f"/api/robots/avatar/slaves/{slave['id']}")
    # A normal end: the relay's robot is handed back, holding, not lost (e-stopped).
    await eventually(lambda: relay.snapshot().master is None)
    assert str(relay.snapshot().mode) == "idle" and relay.estop_count == 0
    # A barrier instead of a pause: a later command through the relay follows, on the same
    # connection, whatever the release sent over there; once it has arrived, so has that.
    physical = b.app.manager.get("physical")
    async with MasterSession.open(r.url, "relay-arm") as later:
        await later.command({"Rotation": 7})
        await eventually(lambda: physical.snapshot().joint("Rotation").goal == 7)
    assert str(physical.snapshot().mode) != "estopped"
