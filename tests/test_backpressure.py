"""Peers that stop reading: their commands still flow, memory stays bounded, and when they read
again they get the newest state and how much they missed.

Every test here runs in lock step (the next command goes out once the slave has the last one),
so none depends on how fast the machine is: on a server whose reading waits on writing, the
lock step stops once the non-reader's buffers fill, and the test fails on its deadline.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path
from typing import Any

import pytest
import trio
from trio_websocket import WebSocketConnection, open_websocket_url

from arena.bench import BENCH_TYPE, bench_types
from arena.protocol.errors import ArenaError, ErrorCode
from arena.robot.model import TYPES_PATH_ENV
from arena.server.config import ServerConfig
from tests.conftest import RunningServer
from tests.raw_websocket import OP_TEXT, RawWebSocket
from tests.test_faults import targets_in, whole_arm

StartServer = Callable[..., Awaitable[RunningServer]]
COMMANDS = 600


def value(i: int) -> float:
    """A distinct Rotation target for command `i`, a small step from the one before."""
    return round((i + 1) * 0.1, 1)


def in_order(seen: list[float]) -> bool:
    """Every command's target reached the slave, in the order sent (a move the motion limiter
    splits adds targets between them)."""
    expected = [value(i) for i in range(COMMANDS)]
    wanted = set(expected)
    return [v for v in seen if v in wanted] == expected


@pytest.fixture
async def fast_server(
    start_server: StartServer, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> RunningServer:
    """A server with robot `fast` (rate limit lifted, and acceleration and jerk limits so
    high that each small step is one target: what is measured here is the messages, not the
    trajectory) and small outbound buffers."""
    types = bench_types(tmp_path / "types")
    config = types / BENCH_TYPE / "robot.toml"
    config.write_text(
        config.read_text().replace(
            "[[joints]]", "[[joints]]\nmax_acceleration = 1e9\nmax_jerk = 1e15"
        )
    )
    monkeypatch.setenv(TYPES_PATH_ENV, str(types))
    server = await start_server(joint_states_interval=0.0)
    async with server.client() as http:
        created = await http.post("/api/robots", json={"robot_type": BENCH_TYPE, "id": "fast"})
        assert created.status_code == 201, created.text
    return server


class Slave:
    """A slave that reads everything and lets the test wait for a given Rotation target."""

    def __init__(self, ws: WebSocketConnection) -> None:
        self.ws = ws
        self.seen: list[float] = []
        self._changed = trio.Event()

    async def run(self) -> None:
        while True:
            found = targets_in((await self.ws.get_message()).encode())
            if found:
                self.seen.extend(found)
                self._changed.set()
                self._changed = trio.Event()

    async def wait_for(self, target: float) -> None:
        while not self.seen or self.seen[-1] != target:
            await self._changed.wait()


@pytest.fixture
async def slave(fast_server: RunningServer, nursery: trio.Nursery) -> AsyncIterator[Slave]:
    async with open_websocket_url(fast_server.ws_url + "/ws/slave/fast?id=reader") as ws:
        reader = Slave(ws)
        nursery.start_soon(reader.run)
        yield reader
        nursery.cancel_scope.cancel()


def queued_bytes(server: RunningServer) -> int:
    """What the server holds for its WebSocket peers, over every connection."""
    return sum(c.ws.queued_bytes for c in server.app.connections)


async def read_until_missed(peer: RawWebSocket) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """Read again: the `missed` message, then what follows it up to the newest joint_states
    (the one whose Rotation is the last command's)."""
    with trio.fail_after(30):
        while True:
            frame = await peer.receive_frame()
            assert frame is not None
            missed = json.loads(frame.payload)
            if missed["type"] == "missed":
                break
        after: list[dict[str, Any]] = []
        while not (
            after
            and after[-1]["type"] == "joint_states"
            and rotation(after[-1]) == value(COMMANDS - 1)
        ):
            frame = await peer.receive_frame()
            assert frame is not None
            after.append(json.loads(frame.payload))
    return missed, after


def rotation(joint_states: dict[str, Any]) -> float:
    return next(j["virtual_value"] for j in joint_states["data"] if j["name"] == "Rotation")


async def test_a_master_that_never_reads_has_every_command_delivered(
    fast_server: RunningServer, slave: Slave
) -> None:
    # A master with a 4 KiB receive buffer that never reads what Arena sends back.
    master = await RawWebSocket.connect(fast_server.url, "/ws/master/fast", receive_buffer=4096)
    highest = 0
    with trio.fail_after(30):
        for i in range(COMMANDS):
            await master.send_frame(OP_TEXT, whole_arm(value(i)).encode())
            await slave.wait_for(value(i))
            highest = max(highest, queued_bytes(fast_server))
    assert in_order(slave.seen)
    # What could not be delivered was bounded: the newest states, a count for the acks.
    assert highest < 64 * 1024, highest
    assert fast_server.app.metrics.dropped["ack"] > 0
    missed, after = await read_until_missed(master)
    assert missed["data"]["ack"] > 0
    newest = [m for m in after if m["type"] == "joint_states"]
    assert newest and rotation(newest[-1]) == value(COMMANDS - 1)
    assert [m["type"] for m in after].count("joint_states") <= 2
    # Reading again, it is answered as before.
    await master.send_frame(OP_TEXT, whole_arm(1.5).encode())
    with trio.fail_after(10):
        while (reply := json.loads((await master.receive_frame() or b"").payload))["type"] != "ack":
            pass
    assert reply["data"]["status"] in ("accepted", "clamped")
    await master.aclose()


async def test_a_viewer_that_never_reads_slows_no_one(
    fast_server: RunningServer, slave: Slave
) -> None:
    viewer = await RawWebSocket.connect(
        fast_server.url, "/ws/robots/fast/state", receive_buffer=4096
    )
    highest = 0
    async with open_websocket_url(fast_server.ws_url + "/ws/master/fast") as master:
        with trio.fail_after(30):
            for i in range(COMMANDS):
                await master.send_message(whole_arm(value(i)))
                await slave.wait_for(value(i))
                while json.loads(await master.get_message())["type"] != "ack":
                    pass
                highest = max(highest, queued_bytes(fast_server))
    assert highest < 64 * 1024, highest
    missed, after = await read_until_missed(viewer)
    assert missed["data"]["joint_states"] > 0
    newest = [m for m in after if m["type"] == "joint_states"]
    assert newest and rotation(newest[-1]) == value(COMMANDS - 1)
    await viewer.aclose()


async def test_a_fire_and_forget_master_asks_for_no_acks_or_joint_states(
    fast_server: RunningServer, slave: Slave
) -> None:
    master = await RawWebSocket.connect(
        fast_server.url, "/ws/master/fast?acks=false&joint_states=false"
    )
    with trio.fail_after(10):
        for i in range(20):
            await master.send_frame(OP_TEXT, whole_arm(value(i)).encode())
            await slave.wait_for(value(i))
        # A refusal is still told: a joint it does not know.
        bad = {"type": "command", "data": {"joints": [{"name": "Nope", "value": 1}]}}
        await master.send_frame(OP_TEXT, json.dumps(bad).encode())
        kinds: list[str] = []
        while True:
            frame = await master.receive_frame()
            assert frame is not None
            message = json.loads(frame.payload)
            kinds.append(message["type"])
            if message["type"] in ("ack", "error"):
                break
    # The state on connecting, then only the answer to the bad command.
    assert "joint_states" not in kinds and kinds.count("ack") <= 1, kinds
    assert kinds[-1] in ("ack", "error")
    if kinds[-1] == "ack":
        assert message["data"]["status"] == "refused"
    await master.aclose()


async def test_a_websockets_master_with_max_queue_1_that_never_reads(
    fast_server: RunningServer,
) -> None:
    # Python's `websockets`, as a teleoperation producer would use it: it reads nothing, and
    # with max_queue=1 the library stops reading its socket after one unread message.
    url = fast_server.ws_url

    async def scenario() -> list[float]:
        import websockets

        seen: list[float] = []
        arrived = asyncio.Condition()
        async with (
            websockets.connect(url + "/ws/slave/fast?id=asyncio") as slave,
            websockets.connect(url + "/ws/master/fast", max_queue=1) as master,
        ):

            async def read_slave() -> None:
                async for raw in slave:
                    found = targets_in(raw.encode() if isinstance(raw, str) else raw)
                    if found:
                        async with arrived:
                            seen.extend(found)
                            arrived.notify_all()

            reader = asyncio.create_task(read_slave())
            async with asyncio.timeout(120):  # only a server that stalls reaches it
                for i in range(COMMANDS):
                    await master.send(whole_arm(value(i)))
                    async with arrived:
                        await arrived.wait_for(lambda i=i: bool(seen) and seen[-1] == value(i))
            reader.cancel()
        return seen

    seen = await trio.to_thread.run_sync(asyncio.run, scenario())
    assert in_order(seen)


async def test_the_queue_limit_per_peer_comes_from_the_config(start_server: StartServer) -> None:
    server = await start_server(demo=True, ws_queue_bytes=4096)
    async with open_websocket_url(server.ws_url + "/ws/robots/demo-arm/state") as viewer:
        await viewer.get_message()
        (connection,) = server.app.connections
        assert connection.ws.high_water == 4096
    for bad in (0, 100, 1 << 40):
        with pytest.raises(ArenaError) as refused:
            ServerConfig(ws_queue_bytes=bad).check()
        assert refused.value.code is ErrorCode.INVALID_CONFIG
