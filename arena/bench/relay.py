"""Relay and throughput: one master and one slave, commands one at a time and as fast as they go."""

from __future__ import annotations

import asyncio
import contextlib
import json
import threading
import time

import httpx

from arena.bench.client import BlockingWebSocket, masked_frame
from arena.bench.common import (
    ACK_MARK,
    EXECUTE_MARK,
    REST_TIMEOUT,
    Server,
    attached_slave,
    command_text,
    create_bench_robot,
    percentile,
    time_to,
    wait_for_slaves,
    without_client_gc,
)


async def relay(server: Server, count: int = 5000) -> dict[str, float]:
    """Master send -> slave receipt of execute_command, one command at a time (lean client)."""
    async with httpx.AsyncClient(base_url=server.url, timeout=REST_TIMEOUT) as http:
        await create_bench_robot(http, "relay")
        await create_bench_robot(http, "relay-deaf")
    results = await asyncio.to_thread(without_client_gc, lean_relay, server.ws, count)
    # The same with a master that never reads what it is sent (a teleoperation producer
    # whose library stopped reading): its commands must flow as a reading master's do.
    results.update(await asyncio.to_thread(without_client_gc, lean_relay, server.ws, count, True))
    return results


def lean_relay(
    ws: str,
    count: int,
    deaf: bool = False,
    master_ws: str | None = None,
    robot_id: str | None = None,
) -> dict[str, float]:
    """Relay latency over the lean blocking client (`bench.client`), blocking in a thread:
    `count` commands one at a time, each timed from its send to the slave's execute_command
    (warm-up excluded); `deaf` uses a master that never reads. `master_ws` puts the master on
    another server, `robot_id` names the robot (`bench nodes`: a node of the fleet)."""
    robot, name = ("relay-deaf", "relay_deaf") if deaf else ("relay", "relay")
    robot = robot_id or robot
    slave = attached_slave(ws, robot)
    master = BlockingWebSocket(
        (master_ws or ws) + f"/ws/master/{robot}", receive_buffer=4096 if deaf else None
    )
    frames = [masked_frame(command_text(i + 1)) for i in range(count + 100)]
    latencies = []
    try:
        for i, frame in enumerate(frames):
            latency = time_to(EXECUTE_MARK, slave, master, frame)
            if i >= 100:  # warm-up excluded
                latencies.append(latency)
            while not deaf and ACK_MARK not in master.receive():
                pass
    finally:
        master.close()
        slave.close()
    return {
        f"{name}_p50_us": percentile(latencies, 0.5) * 1e6,
        f"{name}_p99_us": percentile(latencies, 0.99) * 1e6,
        f"{name}_max_us": max(latencies) * 1e6,
    }


async def relay_with_websockets(server: Server, count: int = 5000) -> dict[str, float]:
    """The relay again with the `websockets` client library (what a Python user sees)."""
    import websockets

    async with httpx.AsyncClient(base_url=server.url, timeout=REST_TIMEOUT) as http:
        await create_bench_robot(http, "relay-ws")
    async with (
        websockets.connect(compression=None, uri=server.ws + "/ws/slave/relay-ws") as slave,
        websockets.connect(compression=None, uri=server.ws + "/ws/master/relay-ws") as master,
    ):
        await asyncio.to_thread(wait_for_slaves, server.url, ["relay-ws"])
        latencies = []
        for i in range(count + 100):
            sent = time.perf_counter()
            await master.send(command_text(i + 1))
            while True:
                message = json.loads(await slave.recv())
                if message["type"] == "execute_command":
                    break
            if i >= 100:  # warm-up excluded
                latencies.append(time.perf_counter() - sent)
            while json.loads(await master.recv())["type"] != "ack":
                pass
    return {
        "relay_websockets_p50_us": percentile(latencies, 0.5) * 1e6,
        "relay_websockets_p99_us": percentile(latencies, 0.99) * 1e6,
    }


async def throughput(
    server: Server, count: int = 20_000, robot_id: str = "flood"
) -> dict[str, float]:
    """Commands as fast as one master can send them; acks counted as they come back.

    The frames are made before the clock starts and go out in one `sendall` from a thread,
    so the client costs as little as it can (lean client, see `bench_client`).
    """
    async with httpx.AsyncClient(base_url=server.url, timeout=REST_TIMEOUT) as http:
        await create_bench_robot(http, robot_id)
    return await asyncio.to_thread(without_client_gc, _lean_throughput, server.ws, robot_id, count)


def _lean_throughput(ws: str, robot_id: str, count: int) -> dict[str, float]:
    slave = attached_slave(ws, robot_id)
    master = BlockingWebSocket(ws + f"/ws/master/{robot_id}")
    frames = b"".join(masked_frame(command_text(i + 1)) for i in range(count))
    reached = 0

    def count_slave() -> None:
        nonlocal reached
        with contextlib.suppress(OSError):  # the socket closes under it at the end
            while True:
                if EXECUTE_MARK in slave.receive():
                    reached += 1

    counter = threading.Thread(target=count_slave, daemon=True)
    counter.start()
    accepted = refused = 0
    start = time.perf_counter()
    sender = threading.Thread(target=master.send_raw, args=(frames,), daemon=True)
    sender.start()
    try:
        while accepted + refused < count:
            message = master.receive()
            if ACK_MARK in message:
                if '"refused"' in message:
                    refused += 1
                else:
                    accepted += 1
        elapsed = time.perf_counter() - start
        sender.join()
        time.sleep(0.2)  # the last targets on their way to the slave
    finally:
        master.close()
        slave.close()
    counter.join(timeout=5)
    return {
        "throughput_accepted_per_s": accepted / elapsed,
        "throughput_refused": refused,
        "throughput_reached_slave": reached,
    }
