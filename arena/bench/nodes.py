"""`arena bench nodes`: a fleet of `arena serve --node` processes on 127.0.0.1 (Zenoh on ports
they choose, explicit endpoints).

  nodes_relay       master on node 1, robot and slave on node 0: send -> `execute_command`,
                    against master and slave both on node 0, in the same run (lean client)
  nodes_estop       3 nodes x 100 robots, a slave each: POST /api/fleet/estop on node 0 to
                    the last slave's e-stop notice, and each node's acknowledgment time
  nodes_fleet       100 robots at 50 Hz over two nodes (each client on its robot's node)
                    against the same on one node: p50/p99 and CPU of all the servers
"""

from __future__ import annotations

import asyncio
import contextlib
import selectors
import statistics
import time
from collections.abc import AsyncIterator
from typing import Any

import httpx

from arena.bench.client import BlockingWebSocket
from arena.bench.common import (
    REST_TIMEOUT,
    Server,
    create_bench_robot,
    running_server,
    wait_for_slaves,
    without_client_gc,
)
from arena.bench.fleet import fleet
from arena.bench.relay import lean_relay

_LISTEN = ("--fleet-listen", "tcp/127.0.0.1:0")


async def _wait_for(check: Any, limit: float = 60.0) -> None:
    deadline = time.monotonic() + limit
    while not await check():
        if time.monotonic() > deadline:
            raise RuntimeError("the fleet did not form")
        await asyncio.sleep(0.1)


@contextlib.asynccontextmanager
async def running_fleet(count: int, record: bool = True) -> AsyncIterator[list[Server]]:
    """`count` nodes: node n0 listens, the others connect to it (and find each other)."""
    async with contextlib.AsyncExitStack() as stack:
        first = await stack.enter_async_context(running_server(record, "--node", "n0", *_LISTEN))
        async with httpx.AsyncClient(base_url=first.url, timeout=REST_TIMEOUT) as http:
            nodes = (await http.get("/api/fleet/nodes")).json()["nodes"]
        locator = next(n for n in nodes if n["name"] == "n0")["locators"][0]
        servers = [first]
        for n in range(1, count):
            options = ("--node", f"n{n}", *_LISTEN, "--fleet-connect", locator)
            servers.append(await stack.enter_async_context(running_server(record, *options)))

        async def formed() -> bool:
            for server in servers:
                async with httpx.AsyncClient(base_url=server.url, timeout=REST_TIMEOUT) as http:
                    listed = (await http.get("/api/fleet/nodes")).json()["nodes"]
                if sum(node["alive"] for node in listed) < count:
                    return False
            return True

        await _wait_for(formed)
        yield servers


async def _known_everywhere(servers: list[Server], robot_ids: set[str]) -> None:
    async def known() -> bool:
        for server in servers:
            async with httpx.AsyncClient(base_url=server.url, timeout=REST_TIMEOUT) as http:
                listed = (await http.get("/api/fleet/robots")).json()["robots"]
            if not robot_ids <= {robot["id"] for robot in listed}:
                return False
        return True

    await _wait_for(known)


async def nodes_relay(count: int = 2000) -> dict[str, float]:
    """Cross-node relay against same-node relay, one run."""
    async with running_fleet(2) as (home, away):
        async with httpx.AsyncClient(base_url=home.url, timeout=REST_TIMEOUT) as http:
            await create_bench_robot(http, "relay")
            await create_bench_robot(http, "relay-far")
        await _known_everywhere([away], {"relay-far"})
        same = await asyncio.to_thread(without_client_gc, lean_relay, home.ws, count)
        cross = await asyncio.to_thread(
            without_client_gc, lean_relay, home.ws, count, False, away.ws, "relay-far"
        )
    return {
        "nodes_relay_same_p50_us": same["relay_p50_us"],
        "nodes_relay_same_p99_us": same["relay_p99_us"],
        "nodes_relay_cross_p50_us": cross["relay_p50_us"],
        "nodes_relay_cross_p99_us": cross["relay_p99_us"],
        "nodes_relay_cross_ratio_p50": cross["relay_p50_us"] / same["relay_p50_us"],
    }


async def nodes_estop(nodes: int = 3, robots: int = 100, trials: int = 5) -> dict[str, float]:
    """A fleet e-stop from node 0 to the last slave's notice, over `nodes` x `robots`; the
    median of `trials` (every robot reset between them)."""
    async with running_fleet(nodes) as servers:
        ids: list[tuple[Server, str]] = []
        for index, server in enumerate(servers):
            async with httpx.AsyncClient(base_url=server.url, timeout=REST_TIMEOUT) as http:
                for n in range(robots):
                    robot_id = f"stop-{index}-{n}"
                    await create_bench_robot(http, robot_id)
                    ids.append((server, robot_id))
        await _known_everywhere(servers[:1], {robot_id for _, robot_id in ids})
        slaves = [BlockingWebSocket(server.ws + f"/ws/slave/{rid}") for server, rid in ids]
        runs = []
        try:
            for server in servers:
                mine = [rid for where, rid in ids if where is server]
                await asyncio.to_thread(wait_for_slaves, server.url, mine)
            for _ in range(trials):
                runs.append(await asyncio.to_thread(_estop_and_wait, servers[0], slaves))
                await asyncio.to_thread(_reset_all, ids)
        finally:
            for slave in slaves:
                slave.close()

    def median(key: str) -> float:
        return statistics.median(run[key] for run in runs)

    return {
        "nodes_estop_last_notice_ms": median("last"),
        "nodes_estop_last_notice_max_ms": max(run["last"] for run in runs),
        "nodes_estop_answer_ms": median("answer"),
        "nodes_estop_slowest_ack_ms": median("slowest_ack"),
        "nodes_estop_missing_nodes": max(run["missing"] for run in runs),
        "nodes_estop_robots": float(len(ids)),
    }


def _reset_all(ids: list[tuple[Server, str]]) -> None:
    clients: dict[str, httpx.Client] = {}
    try:
        for server, robot_id in ids:
            client = clients.setdefault(server.url, httpx.Client(base_url=server.url))
            client.post(f"/api/robots/{robot_id}/reset").raise_for_status()
    finally:
        for client in clients.values():
            client.close()


def _estop_and_wait(server: Server, slaves: list[BlockingWebSocket]) -> dict[str, float]:
    selector = selectors.DefaultSelector()
    for slave in slaves:
        slave.sock.setblocking(False)
        selector.register(slave.sock, selectors.EVENT_READ, slave)
    for _ in range(3):  # what the slaves were sent on attaching
        for key, _ in selector.select(0.2):
            key.data.receive_ready()
    for _ in range(3):  # and the reset of the trial before
        for key, _ in selector.select(0.05):
            key.data.receive_ready()
    waiting = set(slaves)
    with httpx.Client(base_url=server.url, timeout=10) as http:  # made before the clock runs
        http.get("/")  # and connected
        start = time.perf_counter()
        answer = http.post("/api/fleet/estop", json={"reason": "bench"}).json()
        answered = time.perf_counter()
    last = start
    deadline = start + 10
    while waiting and time.perf_counter() < deadline:
        for key, _ in selector.select(0.05):
            slave = key.data
            if any('"type":"estop"' in m for m in slave.receive_ready()) and slave in waiting:
                waiting.discard(slave)
                last = time.perf_counter()
    for slave in slaves:
        selector.unregister(slave.sock)
        slave.sock.setblocking(True)
    if waiting:
        raise RuntimeError(f"{len(waiting)} slaves never heard the fleet e-stop")
    return {
        "last": (last - start) * 1000,
        "answer": (answered - start) * 1000,
        "slowest_ack": max(ack["ms"] for ack in answer["acks"]),
        "missing": float(len(answer["missing"])),
    }


async def nodes_fleet(
    robots: int = 100, rate: float = 50.0, seconds: float = 10.0
) -> dict[str, float]:
    """The fleet scenario on two nodes against one node, in the same run."""
    async with running_server() as single:
        one = await fleet(single, robots=robots, rate=rate, seconds=seconds)
    async with running_fleet(2) as servers:
        two = await fleet(servers, robots=robots, rate=rate, seconds=seconds)
    return {
        "nodes_fleet_one_p50_us": one["fleet_p50_us"],
        "nodes_fleet_one_p99_us": one["fleet_p99_us"],
        "nodes_fleet_one_cpu_percent": one["fleet_server_cpu_percent"],
        "nodes_fleet_two_p50_us": two["fleet_p50_us"],
        "nodes_fleet_two_p99_us": two["fleet_p99_us"],
        "nodes_fleet_two_cpu_percent": two["fleet_server_cpu_percent"],
        "nodes_fleet_two_unacknowledged": two["fleet_commands_unacknowledged"],
    }
