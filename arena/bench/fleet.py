"""The fleet and the soak: many robots, each with a master and a slave, at a steady rate."""

from __future__ import annotations

import asyncio
import dataclasses
import json
import time

import httpx

from arena.bench.client import BlockingWebSocket, masked_frame
from arena.bench.common import (
    HEARTBEAT_TEXT,
    REST_TIMEOUT,
    Server,
    create_bench_robot,
    joints_text,
    percentile,
    without_client_gc,
)


@dataclasses.dataclass
class FleetRun:
    """What a fleet run saw: latencies stamped with their send time, counts, server samples."""

    started: float
    latencies: list[tuple[float, float]] = dataclasses.field(default_factory=list)
    sent: int = 0
    acked: int = 0
    refused: int = 0
    # (seconds since start, server CPU seconds, server RSS MiB), every `sample_every` seconds
    samples: list[tuple[float, float, float]] = dataclasses.field(default_factory=list)

    def window(self, start: float, end: float) -> list[float]:
        """Latencies of commands sent between `start` and `end` seconds into the run."""
        return [lat for at, lat in self.latencies if start <= at - self.started < end]


async def drive_fleet(
    server: Server, robots: int, rate: float, seconds: float, sample_every: float = 1.0
) -> FleetRun:
    """`robots` robots, each with a WebSocket master at `rate` Hz and a WebSocket slave.

    Latency is the master's send to the slave's `execute_command` for that value.
    """
    import websockets

    async with httpx.AsyncClient(base_url=server.url, timeout=REST_TIMEOUT) as http:
        for n in range(robots):
            await create_bench_robot(http, f"fleet-{n}")
    run = FleetRun(started=time.perf_counter())
    end = run.started + seconds

    async def sample() -> None:
        while True:
            now = time.perf_counter()
            run.samples.append((now - run.started, server.cpu_seconds(), server.rss_mib()))
            await asyncio.sleep(sample_every)

    async def pair(n: int) -> None:
        async with (
            # No client pings: latency is measured here, and a busy load generator must not
            # drop its own connections for a late pong.
            websockets.connect(
                server.ws + f"/ws/slave/fleet-{n}", compression=None, ping_interval=None
            ) as slave,
            websockets.connect(
                server.ws + f"/ws/master/fleet-{n}", compression=None, ping_interval=None
            ) as master,
        ):
            sent_at: dict[float, float] = {}
            counts = {"sent": 0, "acked": 0}

            async def count_acks() -> None:
                async for raw in master:  # a prefix test: json.loads here would cap the load
                    if isinstance(raw, str) and raw.startswith('{"type":"ack"'):
                        counts["acked"] += 1
                        run.refused += '"status":"refused"' in raw

            async def receive() -> None:
                async for raw in slave:
                    if not (isinstance(raw, str) and raw.startswith('{"type":"execute_command"')):
                        continue
                    message = json.loads(raw)
                    if message["type"] == "execute_command":
                        value = message["data"]["joints"][0]["value"]
                        started = sent_at.pop(value, None)
                        if started is not None:
                            arrived = time.perf_counter()
                            run.latencies.append((started, arrived - started))

            async def heartbeats() -> None:  # a silent slave is dropped (and e-stops)
                while True:
                    await asyncio.sleep(10)
                    await slave.send(HEARTBEAT_TEXT)

            tasks = [
                asyncio.create_task(count_acks()),
                asyncio.create_task(receive()),
                asyncio.create_task(heartbeats()),
            ]
            i = 0
            next_at = time.perf_counter()
            while time.perf_counter() < end:
                i += 1
                value = round((i % 2) * 0.001 + n * 1e-6, 9)
                sent_at[value] = time.perf_counter()
                counts["sent"] += 1
                await master.send(joints_text({"Rotation": value}))
                # A fixed schedule (no drift); a late generator skips, it never bursts.
                next_at = max(next_at + 1 / rate, time.perf_counter())
                await asyncio.sleep(next_at - time.perf_counter())
            deadline = time.perf_counter() + 10  # the last acknowledgments: late is not lost
            while counts["acked"] < counts["sent"] and time.perf_counter() < deadline:
                await asyncio.sleep(0.05)
            await asyncio.sleep(0.2)
            for task in tasks:
                task.cancel()
            run.sent += counts["sent"]
            run.acked += counts["acked"]

    sampler = asyncio.create_task(sample())
    await asyncio.gather(*(pair(n) for n in range(robots)))
    sampler.cancel()
    now = time.perf_counter()
    run.samples.append((now - run.started, server.cpu_seconds(), server.rss_mib()))
    return run


async def fleet(
    server: Server | list[Server],
    robots: int = 100,
    rate: float = 50.0,
    seconds: float = 10.0,
    heartbeat_period: float = 5.0,
    acks: bool = True,
) -> dict[str, float]:
    """`robots` robots, each with a master at `rate` Hz and a slave, for `seconds` (lean
    client: one selector loop in a thread, its masters' schedules spread over the period and
    its slaves' heartbeats over `heartbeat_period`). Given several servers (the nodes of a
    fleet), robot n lives on server n mod k and its clients go to that node directly; CPU and
    memory are the sum of them all. `acks=False` for a server that acknowledges nothing (the
    floor relay): the run then ends without waiting for acknowledgments."""
    servers = server if isinstance(server, list) else [server]
    for n in range(robots):
        server = servers[n % len(servers)]
        async with httpx.AsyncClient(base_url=server.url, timeout=REST_TIMEOUT) as http:
            await create_bench_robot(http, f"fleet-{n}")
    return await asyncio.to_thread(
        without_client_gc, _lean_fleet, servers, robots, rate, seconds, heartbeat_period, acks
    )


def _lean_fleet(
    servers: list[Server],
    robots: int,
    rate: float,
    seconds: float,
    heartbeat_period: float,
    acks: bool,
) -> dict[str, float]:
    import heapq
    import selectors

    pairs = [
        (
            BlockingWebSocket(servers[n % len(servers)].ws + f"/ws/slave/fleet-{n}"),
            BlockingWebSocket(servers[n % len(servers)].ws + f"/ws/master/fleet-{n}"),
        )
        for n in range(robots)
    ]
    selector = selectors.DefaultSelector()
    for n, (slave, master) in enumerate(pairs):
        for ws, is_slave in ((slave, True), (master, False)):
            ws.sock.setblocking(False)
            selector.register(ws.sock, selectors.EVENT_READ, (n, ws, is_slave))
    # Two alternating values per robot, unique across robots: the slave's value names the send.
    values = [(round(n * 1e-6, 9), round(0.001 + n * 1e-6, 9)) for n in range(robots)]
    frames = [tuple(masked_frame(joints_text({"Rotation": v})) for v in pair) for pair in values]
    heartbeat = masked_frame(HEARTBEAT_TEXT)
    heartbeats = 0
    sent_at: list[dict[float, float]] = [{} for _ in range(robots)]
    latencies: list[float] = []
    sent = acked = refused = 0
    period = 1.0 / rate
    start = time.perf_counter()
    end = start + seconds
    # Independent robots do not tick in step: their first sends are spread over one period.
    schedule = [(start + period * n / robots, n, 0) for n in range(robots)]
    heapq.heapify(schedule)
    # Each slave says it is alive every period, and they too are spread: one every 50 ms for
    # 100 robots and 5 s.
    heartbeat_spacing = heartbeat_period / robots
    next_heartbeat = start + heartbeat_spacing
    cpu_start = sum(server.cpu_seconds() for server in servers)

    def handle(timeout: float) -> None:
        nonlocal acked, refused
        for key, _ in selector.select(timeout):
            n, ws, is_slave = key.data
            for message in ws.receive_ready():
                if is_slave:
                    if message.startswith('{"type":"execute_command"'):
                        value = json.loads(message)["data"]["joints"][0]["value"]
                        began = sent_at[n].pop(value, None)
                        if began is not None:
                            latencies.append(time.perf_counter() - began)
                elif message.startswith('{"type":"ack"'):
                    acked += 1
                    refused += '"status":"refused"' in message

    try:
        while (now := time.perf_counter()) < end:
            due, n, i = schedule[0]
            if due > now:
                handle(due - now)
                continue
            sent_at[n][values[n][i % 2]] = now
            pairs[n][1].send_raw(frames[n][i % 2])
            sent += 1
            # A fixed schedule (no drift); a late client skips a beat, it never bursts.
            heapq.heapreplace(schedule, (max(due + period, now), n, i + 1))
            if now >= next_heartbeat:  # a silent slave is dropped (and e-stops)
                pairs[heartbeats % robots][0].send_raw(heartbeat)
                heartbeats += 1
                next_heartbeat = start + heartbeat_spacing * (heartbeats + 1)
        cpu_used = sum(server.cpu_seconds() for server in servers) - cpu_start
        elapsed = time.perf_counter() - start
        settle = time.perf_counter() + 10  # the last acknowledgments: late is not lost
        while acks and acked < sent and time.perf_counter() < settle:
            handle(0.05)
    finally:
        for slave, master in pairs:
            master.close()
            slave.close()
    return {
        "fleet_p50_us": percentile(latencies, 0.5) * 1e6,
        "fleet_p99_us": percentile(latencies, 0.99) * 1e6,
        "fleet_server_cpu_percent": 100 * cpu_used / elapsed,
        "fleet_server_rss_mib": sum(server.rss_mib() for server in servers),
        "fleet_commands_sent": sent,
        "fleet_commands_unacknowledged": sent - acked if acks else 0,
        "fleet_commands_refused": refused,
        "fleet_messages": len(latencies),
        "fleet_heartbeats_sent": heartbeats,
    }


async def soak(
    server: Server,
    robots: int = 100,
    rate: float = 50.0,
    seconds: float = 600.0,
    window: float = 60.0,
) -> dict[str, float]:
    """The fleet held for `seconds`: the first `window` against the last, and what was lost.

    Memory is read after the first window (caches and buffers warmed) and at the end; lost
    commands are those sent without an acknowledgment; the recorder reports what it wrote.
    """
    run = await drive_fleet(server, robots, rate, seconds, sample_every=window / 6)
    first, last = run.window(0, window), run.window(seconds - window, seconds)
    warm = next(s for s in run.samples if s[0] >= window)
    (t0, cpu0, _), (t1, cpu1, rss_end) = run.samples[0], run.samples[-1]
    async with httpx.AsyncClient(base_url=server.url, timeout=REST_TIMEOUT) as http:
        recorder = (await http.get("/api/recordings")).json()["recorder"]
    return {
        "soak_robots": robots,
        "soak_rate_hz": rate,
        "soak_seconds": seconds,
        "soak_commands_per_s": run.sent / seconds,
        "soak_commands_sent": run.sent,
        "soak_commands_unacknowledged": run.sent - run.acked,
        "soak_commands_refused": run.refused,
        "soak_first_p50_us": percentile(first, 0.5) * 1e6,
        "soak_first_p99_us": percentile(first, 0.99) * 1e6,
        "soak_last_p50_us": percentile(last, 0.5) * 1e6,
        "soak_last_p99_us": percentile(last, 0.99) * 1e6,
        "soak_rss_warm_mib": warm[2],
        "soak_rss_end_mib": rss_end,
        "soak_server_cpu_percent": 100 * (cpu1 - cpu0) / (t1 - t0),
        "soak_recorded_messages": recorder["messages"],
        "soak_recording_dropped": recorder["dropped"],
    }
