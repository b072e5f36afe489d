"""E-stops: one robot over REST and over its master socket, and every robot at once."""

from __future__ import annotations

import asyncio
import json
import math
import statistics
import subprocess
import sys
import time
from typing import Any

import httpx

from arena.bench.client import BlockingHttp, BlockingWebSocket, masked_frame
from arena.bench.common import (
    ESTOP_MARK,
    ESTOP_TEXT,
    RESET_MARK,
    RESET_TEXT,
    REST_TIMEOUT,
    Server,
    attached_slave,
    create_bench_robot,
    percentile,
    time_to,
    wait_for_slaves,
    without_client_gc,
)


async def estop(server: Server, trials: int = 200, robots: int = 100) -> dict[str, float]:
    """REST e-stop to the slave's notice: one robot, then every robot at once.

    The clock runs from the request's start to the notice, which the robot sends before the
    HTTP answer is written; the time to the answer is reported beside it. One robot is timed
    with the lean client (raw HTTP on a keep-alive connection, a lean WebSocket slave), then
    again with httpx and `websockets` (what a Python user sees)."""
    import websockets

    async with httpx.AsyncClient(base_url=server.url, timeout=REST_TIMEOUT) as http:
        await create_bench_robot(http, "stop-one")
        results = await asyncio.to_thread(without_client_gc, _lean_estop_one, server, trials)
        await create_bench_robot(http, "stop-ws")
        results.update(
            await asyncio.to_thread(without_client_gc, _lean_estop_over_websocket, server, trials)
        )
        await create_bench_robot(
            http, "stop-httpx"
        )  # its own robot: a slave that leaves e-stops "stop-one"
        one, answered = [], []
        async with websockets.connect(
            compression=None, uri=server.ws + "/ws/slave/stop-httpx"
        ) as slave:
            await asyncio.to_thread(wait_for_slaves, server.url, ["stop-httpx"])
            for _ in range(trials):
                start = time.perf_counter()
                request = asyncio.create_task(http.post("/api/robots/stop-httpx/estop"))
                while json.loads(await slave.recv())["type"] != "estop":
                    pass
                one.append(time.perf_counter() - start)
                response = await request
                answered.append(time.perf_counter() - start)
                response.raise_for_status()
                await http.post("/api/robots/stop-httpx/reset")
                while json.loads(await slave.recv())["type"] != "reset":
                    pass
        results["estop_one_httpx_p50_ms"] = percentile(one, 0.5) * 1e3
        results["estop_one_httpx_p99_ms"] = percentile(one, 0.99) * 1e3
        results["estop_one_httpx_answered_p99_ms"] = percentile(answered, 0.99) * 1e3
        for n in range(robots):
            await create_bench_robot(http, f"stop-{n}")
        slaves = [
            await websockets.connect(compression=None, uri=server.ws + f"/ws/slave/stop-{n}")
            for n in range(robots)
        ]
        await asyncio.to_thread(wait_for_slaves, server.url, [f"stop-{n}" for n in range(robots)])
        everyone = []
        try:
            for _ in range(5):
                start = time.perf_counter()
                request = asyncio.create_task(http.post("/api/estop"))

                async def notice(ws: Any) -> float:
                    while json.loads(await ws.recv())["type"] != "estop":
                        pass
                    return time.perf_counter()

                done = await asyncio.gather(*(notice(ws) for ws in slaves))
                everyone.append(max(done) - start)
                (await request).raise_for_status()
                for n in range(robots):
                    await http.post(f"/api/robots/stop-{n}/reset")
                await asyncio.gather(*(_skip_until(ws, "reset") for ws in slaves))
        finally:
            for ws in slaves:
                await ws.close()
    results["estop_all_median_ms"] = statistics.median(everyone) * 1e3
    return results


def _lean_estop_one(
    server: Server, trials: int, warm_up: int = 10, robot_id: str = "stop-one"
) -> dict[str, float]:
    slave = attached_slave(server.ws, robot_id)
    http = BlockingHttp(server.url)
    stop = http.request_bytes("POST", f"/api/robots/{robot_id}/estop")
    reset = http.request_bytes("POST", f"/api/robots/{robot_id}/reset")
    noticed, answered = [], []
    try:
        for trial in range(warm_up + trials):
            start = time.perf_counter()
            http.send(stop)
            while ESTOP_MARK not in slave.receive():
                pass
            notice = time.perf_counter() - start
            status, body = http.answer()
            if status != 200:
                raise RuntimeError(f"e-stop answered {status}: {body!r}")
            if trial >= warm_up:
                noticed.append(notice)
                answered.append(time.perf_counter() - start)
            http.send(reset)
            status, body = http.answer()
            if status != 200:
                raise RuntimeError(f"reset answered {status}: {body!r}")
            while RESET_MARK not in slave.receive():
                pass
    finally:
        http.close()
        slave.close()
    return {
        "estop_one_p50_ms": percentile(noticed, 0.5) * 1e3,
        "estop_one_p99_ms": percentile(noticed, 0.99) * 1e3,
        "estop_one_answered_p99_ms": percentile(answered, 0.99) * 1e3,
    }


def _lean_estop_over_websocket(server: Server, trials: int, warm_up: int = 10) -> dict[str, float]:
    """A master's `estop` message to the slave's notice: the e-stop that skips HTTP."""
    slave = attached_slave(server.ws, "stop-ws")
    master = BlockingWebSocket(server.ws + "/ws/master/stop-ws")
    stop = masked_frame(ESTOP_TEXT)
    reset = masked_frame(RESET_TEXT)
    noticed = []
    try:
        for trial in range(warm_up + trials):
            notice = time_to(ESTOP_MARK, slave, master, stop)
            if trial >= warm_up:
                noticed.append(notice)
            time_to(RESET_MARK, slave, master, reset)
    finally:
        master.close()
        slave.close()
    return {
        "estop_one_websocket_p50_ms": percentile(noticed, 0.5) * 1e3,
        "estop_one_websocket_p99_ms": percentile(noticed, 0.99) * 1e3,
    }


async def _skip_until(ws: Any, kind: str) -> None:
    while json.loads(await ws.recv())["type"] != kind:
        pass


async def flood(server: Server, trials: int = 300) -> dict[str, float]:
    """One robot's REST e-stop (lean client), alone and while a viewer floods the server with
    pings it never reads the pongs of; the server's memory before and after the flood."""
    async with httpx.AsyncClient(base_url=server.url, timeout=REST_TIMEOUT) as http:
        for robot_id in ("stop-quiet", "stop-flooded", "flood-target"):
            await create_bench_robot(http, robot_id)
    quiet = await asyncio.to_thread(
        without_client_gc, _lean_estop_one, server, trials, 10, "stop-quiet"
    )
    rss_before = server.rss_mib()
    host, port = server.url.split("//")[1].rsplit(":", 1)
    flooder = subprocess.Popen(
        [sys.executable, "-m", "arena.bench.flooder", host, port, "flood-target"]
    )
    try:
        await asyncio.sleep(1.0)  # the flood under way
        try:
            flooded = await asyncio.to_thread(
                without_client_gc, _lean_estop_one, server, trials, 10, "stop-flooded"
            )
        except (TimeoutError, OSError):  # a server the flood froze: no answer in 30 s
            flooded = dict.fromkeys(
                ("estop_one_p50_ms", "estop_one_p99_ms", "estop_one_answered_p99_ms"), math.inf
            )
        rss_during = server.rss_mib()
    finally:
        flooder.kill()
        flooder.wait()
    return {
        "flood_estop_quiet_p50_ms": quiet["estop_one_p50_ms"],
        "flood_estop_quiet_p99_ms": quiet["estop_one_p99_ms"],
        "flood_estop_p50_ms": flooded["estop_one_p50_ms"],
        "flood_estop_p99_ms": flooded["estop_one_p99_ms"],
        "flood_estop_answered_p99_ms": flooded["estop_one_answered_p99_ms"],
        "flood_server_rss_growth_mib": rss_during - rss_before,
    }
