"""`arena bench`: benchmarks against a real server on loopback. Prints medians; asserts nothing.

The server runs as its own process (`arena serve`, recording on unless a scenario says
otherwise); relay, throughput, fleet and one robot's e-stop use the lean clients of
`bench_client` in this process (with its garbage collector kept out of the way), the relay and
e-stop again with `websockets` and httpx on asyncio, as do the e-stop of every robot and the
soak. The robots use a copy of the so-arm100 type whose rate limit is raised (the default 100
commands/s per master would be the only thing measured otherwise); every other check stays on.

Scenarios:
  relay       one master, one slave, commands one at a time: send -> slave's execute_command
              (a lean client, then again with the `websockets` library)
  throughput  commands as fast as one master can send: accepted/s, and what reached the slave
  fleet       N robots, each a master at 50 Hz (then 25 Hz) and a slave: latency p50/p99,
              server CPU and RSS (with its recording process); a lean selector-loop client
  estop       POST /api/robots/{id}/estop -> the slave's estop notice (and -> the HTTP answer,
              which comes after the notice); a master's estop message -> the notice;
              POST /api/estop -> the last robot's notice
  recording   throughput with recording on against off (ratio)
  replay      commands/s of a replay at maximum speed (in process)
  core        RobotCore.command calls/s (pure decision code)
  teleop      leader arm -> follower: a leader register change to the follower's goal write,
              two simulated buses at 1 Mbaud in this process, p50/p99 at 100 and 500 Hz
  usb         the USB slave's control loop on a simulated bus (`arena sim-bus --wire-time`, its
              own process) at 1 Mbaud: the highest cycle rate, and the CPU at 500 Hz
  soak        (only when named) the fleet held for 10 minutes: latency and memory of the first
              minute against the last, commands unacknowledged, recording messages dropped
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import gc
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any, TypeVar

import httpx

from arena.bench_client import BlockingHttp, BlockingWebSocket, masked_frame
from arena.robot.model import BUILTIN_TYPES_DIR, TYPES_PATH_ENV

BENCH_TYPE = "so-arm100-bench"

T = TypeVar("T")


def _without_client_gc(run: Callable[..., T], *args: Any) -> T:
    """Run a lean client with this process's objects frozen out of the garbage collector.

    A full collection here (httpx, asyncio, websockets and their imports) takes ~20 ms; it
    fell two seconds into every fleet run, at the same point, as a spike the server never saw.
    """
    gc.collect()
    gc.freeze()
    try:
        return run(*args)
    finally:
        gc.unfreeze()


def _percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))] if ordered else float("nan")


def _bench_types(folder: Path) -> Path:
    """A robot-type folder holding so-arm100 with the rate limit out of the way."""
    target = folder / BENCH_TYPE
    shutil.copytree(BUILTIN_TYPES_DIR / "so-arm100", target)
    config = target / "robot.toml"
    text = config.read_text()
    text = re.sub(r"command_rate = [\d.]+", "command_rate = 1000000.0", text)
    text = re.sub(r"command_burst = \d+", "command_burst = 1000000", text)
    config.write_text(text)
    return folder


@dataclasses.dataclass
class Server:
    """A server process and its base URL."""

    process: subprocess.Popen[bytes]
    url: str

    @property
    def ws(self) -> str:
        return "ws" + self.url[4:]

    def pids(self) -> list[int]:
        """The server process and its children (the recording writer)."""
        pid = self.process.pid
        children = [
            int(child)
            for task in Path(f"/proc/{pid}/task").glob("*/children")
            for child in task.read_text().split()
        ]
        return [pid, *children]

    def cpu_seconds(self) -> float:
        """User + system CPU time of the server and its children so far."""
        total = 0
        for pid in self.pids():
            with contextlib.suppress(OSError), open(f"/proc/{pid}/stat") as stat:
                fields = stat.read().rsplit(")", 1)[1].split()
                total += int(fields[11]) + int(fields[12])
        return total / os.sysconf("SC_CLK_TCK")

    def rss_mib(self) -> float:
        """Resident memory of the server and its children."""
        total = 0
        for pid in self.pids():
            with contextlib.suppress(OSError), open(f"/proc/{pid}/status") as status:
                rss = (int(line.split()[1]) for line in status if line.startswith("VmRSS:"))
                total += next(rss, 0)  # an exiting process has none
        return total / 1024


@asynccontextmanager
async def running_server(record: bool = True) -> AsyncIterator[Server]:
    """`arena serve` on 127.0.0.1 with a port the system chose, stopped on exit."""
    with tempfile.TemporaryDirectory() as scratch:
        folder = Path(scratch)
        env = {
            **os.environ,
            TYPES_PATH_ENV: str(_bench_types(folder / "types")),
            "LOG_LEVEL": "INFO",  # the "listening on" line is how we learn the port
        }
        args = [
            sys.executable,
            "-m",
            "arena.cli",
            "serve",
            "--port",
            "0",
            "--recordings-dir",
            str(folder / "recordings"),
        ]
        if not record:
            args.append("--no-record")
        process = subprocess.Popen(args, env=env, stderr=subprocess.PIPE)
        assert process.stderr is not None
        url = None
        deadline = time.monotonic() + 60
        while url is None and time.monotonic() < deadline:
            line = process.stderr.readline().decode()
            if not line:
                break
            found = re.search(r"listening on (http://\S+)", line)
            if found:
                url = found.group(1)
        if url is None:
            process.kill()
            raise RuntimeError("the server did not start")
        # Drain the log so the server never blocks on a full pipe.
        loop = asyncio.get_running_loop()
        drain = loop.run_in_executor(None, lambda: process.stderr.read() if process.stderr else b"")
        try:
            yield Server(process, url)
        finally:
            process.terminate()
            await drain
            process.wait(timeout=10)


async def _robot(http: httpx.AsyncClient, robot_id: str) -> None:
    response = await http.post("/api/robots", json={"robot_type": BENCH_TYPE, "id": robot_id})
    response.raise_for_status()


_EXECUTE = '"type":"execute_command"'
_ACK = '"type":"ack"'
_ESTOP = '"type":"estop"'
_RESET = '"type":"reset"'


def _command(i: int) -> str:
    # Tiny alternating steps: always inside the velocity budget, so each goes out at once.
    value = (i % 2) * 0.001
    return json.dumps(
        {
            "type": "command",
            "data": {
                "joints": [{"name": "Rotation", "value": value}, {"name": "Elbow", "value": -value}]
            },
        }
    )


async def relay(server: Server, count: int = 5000) -> dict[str, float]:
    """Master send -> slave receipt of execute_command, one command at a time (lean client)."""
    async with httpx.AsyncClient(base_url=server.url) as http:
        await _robot(http, "relay")
    return await asyncio.to_thread(_without_client_gc, _lean_relay, server.ws, count)


def _time_to(
    marker: str, receiver: BlockingWebSocket, sender: BlockingWebSocket, frame: bytes
) -> float:
    """Seconds from sending `frame` to `receiver`'s first message containing `marker`."""
    start = time.perf_counter()
    sender.send_raw(frame)
    while marker not in receiver.receive():
        pass
    return time.perf_counter() - start


def _lean_relay(ws: str, count: int) -> dict[str, float]:
    slave = BlockingWebSocket(ws + "/ws/slave/relay")
    master = BlockingWebSocket(ws + "/ws/master/relay")
    frames = [masked_frame(_command(i + 1)) for i in range(count + 100)]
    latencies = []
    try:
        for i, frame in enumerate(frames):
            latency = _time_to(_EXECUTE, slave, master, frame)
            if i >= 100:  # warm-up excluded
                latencies.append(latency)
            while _ACK not in master.receive():
                pass
    finally:
        master.close()
        slave.close()
    return {
        "relay_p50_us": _percentile(latencies, 0.5) * 1e6,
        "relay_p99_us": _percentile(latencies, 0.99) * 1e6,
        "relay_max_us": max(latencies) * 1e6,
    }


async def relay_with_websockets(server: Server, count: int = 5000) -> dict[str, float]:
    """The relay again with the `websockets` client library (what a Python user sees)."""
    import websockets

    async with httpx.AsyncClient(base_url=server.url) as http:
        await _robot(http, "relay-ws")
    async with (
        websockets.connect(compression=None, uri=server.ws + "/ws/slave/relay-ws") as slave,
        websockets.connect(compression=None, uri=server.ws + "/ws/master/relay-ws") as master,
    ):
        latencies = []
        for i in range(count + 100):
            sent = time.perf_counter()
            await master.send(_command(i + 1))
            while True:
                message = json.loads(await slave.recv())
                if message["type"] == "execute_command":
                    break
            if i >= 100:  # warm-up excluded
                latencies.append(time.perf_counter() - sent)
            while json.loads(await master.recv())["type"] != "ack":
                pass
    return {
        "relay_websockets_p50_us": _percentile(latencies, 0.5) * 1e6,
        "relay_websockets_p99_us": _percentile(latencies, 0.99) * 1e6,
    }


async def throughput(
    server: Server, count: int = 20_000, robot_id: str = "flood"
) -> dict[str, float]:
    """Commands as fast as one master can send them; acks counted as they come back.

    The frames are made before the clock starts and go out in one `sendall` from a thread,
    so the client costs as little as it can (lean client, see `bench_client`).
    """
    async with httpx.AsyncClient(base_url=server.url) as http:
        await _robot(http, robot_id)
    return await asyncio.to_thread(_without_client_gc, _lean_throughput, server.ws, robot_id, count)


def _lean_throughput(ws: str, robot_id: str, count: int) -> dict[str, float]:
    slave = BlockingWebSocket(ws + f"/ws/slave/{robot_id}")
    master = BlockingWebSocket(ws + f"/ws/master/{robot_id}")
    frames = b"".join(masked_frame(_command(i + 1)) for i in range(count))
    reached = 0

    def count_slave() -> None:
        nonlocal reached
        with contextlib.suppress(OSError):  # the socket closes under it at the end
            while True:
                if _EXECUTE in slave.receive():
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
            if _ACK in message:
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

    async with httpx.AsyncClient(base_url=server.url) as http:
        for n in range(robots):
            await _robot(http, f"fleet-{n}")
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
                    await slave.send('{"type": "heartbeat"}')

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
                await master.send(
                    json.dumps(
                        {
                            "type": "command",
                            "data": {"joints": [{"name": "Rotation", "value": value}]},
                        }
                    )
                )
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
    server: Server,
    robots: int = 100,
    rate: float = 50.0,
    seconds: float = 10.0,
    heartbeat_period: float = 5.0,
) -> dict[str, float]:
    """`robots` robots, each with a master at `rate` Hz and a slave, for `seconds` (lean
    client: one selector loop in a thread, its masters' schedules spread over the period and
    its slaves' heartbeats over `heartbeat_period`)."""
    async with httpx.AsyncClient(base_url=server.url) as http:
        for n in range(robots):
            await _robot(http, f"fleet-{n}")
    return await asyncio.to_thread(
        _without_client_gc, _lean_fleet, server, robots, rate, seconds, heartbeat_period
    )


def _lean_fleet(
    server: Server, robots: int, rate: float, seconds: float, heartbeat_period: float
) -> dict[str, float]:
    import heapq
    import selectors

    pairs = [
        (
            BlockingWebSocket(server.ws + f"/ws/slave/fleet-{n}"),
            BlockingWebSocket(server.ws + f"/ws/master/fleet-{n}"),
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
    frames = [
        tuple(
            masked_frame(
                json.dumps(
                    {"type": "command", "data": {"joints": [{"name": "Rotation", "value": v}]}}
                )
            )
            for v in pair
        )
        for pair in values
    ]
    heartbeat = masked_frame('{"type": "heartbeat"}')
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
    cpu_start = server.cpu_seconds()

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
        cpu_used = server.cpu_seconds() - cpu_start
        elapsed = time.perf_counter() - start
        settle = time.perf_counter() + 10  # the last acknowledgments: late is not lost
        while acked < sent and time.perf_counter() < settle:
            handle(0.05)
    finally:
        for slave, master in pairs:
            master.close()
            slave.close()
    return {
        "fleet_p50_us": _percentile(latencies, 0.5) * 1e6,
        "fleet_p99_us": _percentile(latencies, 0.99) * 1e6,
        "fleet_server_cpu_percent": 100 * cpu_used / elapsed,
        "fleet_server_rss_mib": server.rss_mib(),
        "fleet_commands_sent": sent,
        "fleet_commands_unacknowledged": sent - acked,
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
    async with httpx.AsyncClient(base_url=server.url) as http:
        recorder = (await http.get("/api/recordings")).json()["recorder"]
    return {
        "soak_robots": robots,
        "soak_rate_hz": rate,
        "soak_seconds": seconds,
        "soak_commands_per_s": run.sent / seconds,
        "soak_commands_sent": run.sent,
        "soak_commands_unacknowledged": run.sent - run.acked,
        "soak_commands_refused": run.refused,
        "soak_first_p50_us": _percentile(first, 0.5) * 1e6,
        "soak_first_p99_us": _percentile(first, 0.99) * 1e6,
        "soak_last_p50_us": _percentile(last, 0.5) * 1e6,
        "soak_last_p99_us": _percentile(last, 0.99) * 1e6,
        "soak_rss_warm_mib": warm[2],
        "soak_rss_end_mib": rss_end,
        "soak_server_cpu_percent": 100 * (cpu1 - cpu0) / (t1 - t0),
        "soak_recorded_messages": recorder["messages"],
        "soak_recording_dropped": recorder["dropped"],
    }


async def estop(server: Server, trials: int = 200, robots: int = 100) -> dict[str, float]:
    """REST e-stop to the slave's notice: one robot, then every robot at once.

    The clock runs from the request's start to the notice, which the robot sends before the
    HTTP answer is written; the time to the answer is reported beside it. One robot is timed
    with the lean client (raw HTTP on a keep-alive connection, a lean WebSocket slave), then
    again with httpx and `websockets` (what a Python user sees)."""
    import websockets

    async with httpx.AsyncClient(base_url=server.url) as http:
        await _robot(http, "stop-one")
        results = await asyncio.to_thread(_without_client_gc, _lean_estop_one, server, trials)
        await _robot(http, "stop-ws")
        results.update(
            await asyncio.to_thread(_without_client_gc, _lean_estop_over_websocket, server, trials)
        )
        await _robot(http, "stop-httpx")  # its own robot: a slave that leaves e-stops "stop-one"
        one, answered = [], []
        async with websockets.connect(
            compression=None, uri=server.ws + "/ws/slave/stop-httpx"
        ) as slave:
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
        results["estop_one_httpx_p50_ms"] = _percentile(one, 0.5) * 1e3
        results["estop_one_httpx_p99_ms"] = _percentile(one, 0.99) * 1e3
        results["estop_one_httpx_answered_p99_ms"] = _percentile(answered, 0.99) * 1e3
        for n in range(robots):
            await _robot(http, f"stop-{n}")
        slaves = [
            await websockets.connect(compression=None, uri=server.ws + f"/ws/slave/stop-{n}")
            for n in range(robots)
        ]
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


def _lean_estop_one(server: Server, trials: int, warm_up: int = 10) -> dict[str, float]:
    slave = BlockingWebSocket(server.ws + "/ws/slave/stop-one")
    http = BlockingHttp(server.url)
    stop = http.request_bytes("POST", "/api/robots/stop-one/estop")
    reset = http.request_bytes("POST", "/api/robots/stop-one/reset")
    noticed, answered = [], []
    try:
        for trial in range(warm_up + trials):
            start = time.perf_counter()
            http.send(stop)
            while _ESTOP not in slave.receive():
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
            while _RESET not in slave.receive():
                pass
    finally:
        http.close()
        slave.close()
    return {
        "estop_one_p50_ms": _percentile(noticed, 0.5) * 1e3,
        "estop_one_p99_ms": _percentile(noticed, 0.99) * 1e3,
        "estop_one_answered_p99_ms": _percentile(answered, 0.99) * 1e3,
    }


def _lean_estop_over_websocket(server: Server, trials: int, warm_up: int = 10) -> dict[str, float]:
    """A master's `estop` message to the slave's notice: the e-stop that skips HTTP."""
    slave = BlockingWebSocket(server.ws + "/ws/slave/stop-ws")
    master = BlockingWebSocket(server.ws + "/ws/master/stop-ws")
    stop = masked_frame('{"type": "estop", "data": {"reason": "bench"}}')
    reset = masked_frame('{"type": "reset"}')
    noticed = []
    try:
        for trial in range(warm_up + trials):
            notice = _time_to(_ESTOP, slave, master, stop)
            if trial >= warm_up:
                noticed.append(notice)
            _time_to(_RESET, slave, master, reset)
    finally:
        master.close()
        slave.close()
    return {
        "estop_one_websocket_p50_ms": _percentile(noticed, 0.5) * 1e3,
        "estop_one_websocket_p99_ms": _percentile(noticed, 0.99) * 1e3,
    }


async def _skip_until(ws: Any, kind: str) -> None:
    while json.loads(await ws.recv())["type"] != kind:
        pass


def replay_rate(commands: int = 20_000) -> dict[str, float]:
    """A replay at maximum speed, in process, everything on: a mock slave follows and the
    recorder writes MCAP. Commands per second issued and answered, on the real clock."""
    import trio

    from arena.drivers.mock_slave import MockSlave
    from arena.recording.recorder import Recorder
    from arena.recording.replay import ReplayMaster, TimedCommand
    from arena.robot.manager import open_manager
    from arena.robot.model import load_robot_model
    from arena.robot.motion import Command
    from arena.server.run import tune_garbage_collector

    model = load_robot_model("so-arm100")
    policy = dataclasses.replace(model.safety, command_rate=1e9, command_burst=10**9)
    # Recorded at 100 Hz; at the highest speed (1000x) the replay is always behind its
    # schedule, so what is measured is the work per command.
    timed = [
        TimedCommand(i * 0.01, Command.of({"Rotation": (i % 2) * 0.001})) for i in range(commands)
    ]

    async def run(folder: Path) -> dict[str, float]:
        recorder = Recorder(folder)
        async with trio.open_nursery() as recording:
            await recording.start(recorder.run)
            async with open_manager() as manager:
                manager.on_create.append(recorder.follow)
                robot = await manager.create_robot("so-arm100", robot_id="replay", policy=policy)
                slave = MockSlave()
                await robot.attach_slave(slave)
                master = ReplayMaster(timed, speed=1000.0)
                start = time.perf_counter()
                await robot.attach_master(master)
                while robot.snapshot().master is not None:
                    await trio.sleep(0.005)  # a snapshot costs ~10 us: not too often
                elapsed = time.perf_counter() - start
            recording.cancel_scope.cancel()
        return {
            "replay_commands_per_s": master.sent / elapsed,
            "replay_refused": float(master.refused),
            "replay_recorded_messages": float(recorder.writer.messages),
            "replay_recording_dropped": float(recorder.status()["dropped"]),
        }

    # The collector tuned as `arena serve` tunes it, and put back after (this process goes on
    # to run the benchmark's clients).
    thresholds = gc.get_threshold()
    tune_garbage_collector()
    try:
        with tempfile.TemporaryDirectory() as folder:
            return trio.run(run, Path(folder))
    finally:
        gc.unfreeze()
        gc.set_threshold(*thresholds)


def core_rate(count: int = 20_000) -> dict[str, float]:
    """Pure core: commands per second."""
    from arena.robot.core import RobotCore
    from arena.robot.model import load_robot_model
    from arena.robot.motion import Command

    model = load_robot_model("so-arm100")
    policy = dataclasses.replace(model.safety, command_rate=1e12, command_burst=10**9)
    core = RobotCore(model, 0.0, policy)
    commands = [Command.of({"Rotation": (i % 2) * 0.001}) for i in range(count)]
    start = time.perf_counter()
    for i, command in enumerate(commands):
        core.command(None, command, i * 0.01)
    return {"core_commands_per_s": count / (time.perf_counter() - start)}


def usb_control_rate(seconds: float = 3.0, rate: float = 500.0) -> dict[str, float]:
    """The bus worker (sync write goals + sync read positions of 6 servos per cycle) against a
    simulated bus with wire-time emulation in another process: cycles/s flat out, and the
    worker thread's CPU share when paced at `rate`."""
    from arena.feetech.bus import ServoBus
    from arena.feetech.health import ServoFault
    from arena.feetech.worker import BusWorker, Reading, WorkerEvent, WorkerSettings

    class Count:
        def __init__(self) -> None:
            self.readings = 0
            self.faults = 0

        def reading(self, reading: Reading) -> None:
            self.readings += 1

        def event(self, event: WorkerEvent) -> None:
            self.faults += isinstance(event, ServoFault)

    def run(worker_rate: float, link: Path) -> tuple[float, float, int]:
        listener = Count()
        ids = (1, 2, 3, 4, 5, 6)
        worker = BusWorker(
            lambda: ServoBus(str(link)), ids, listener, WorkerSettings(rate=worker_rate)
        )
        worker.start()
        worker.first_connect.result(timeout=10)
        goal = 0
        start = time.perf_counter()
        cycles0, cpu0 = worker.stats.cycles, worker.stats.thread_cpu
        while (elapsed := time.perf_counter() - start) < seconds:
            goal = (goal + 7) % 400
            worker.set_goals(dict.fromkeys(ids, 1848 + goal))
            time.sleep(0.002)
        cycles, cpu = worker.stats.cycles - cycles0, worker.stats.thread_cpu - cpu0
        worker.stop()
        return cycles / elapsed, cpu / elapsed, listener.faults

    with tempfile.TemporaryDirectory() as folder:
        link = Path(folder) / "ttySIM"
        sim = subprocess.Popen(
            [sys.executable, "-m", "arena.cli", "sim-bus", "--link", str(link), "--wire-time"],
            stdout=subprocess.PIPE,
            text=True,
        )
        try:
            assert sim.stdout is not None
            sim.stdout.readline()  # the banner: the port is there
            top_rate, top_cpu, faults_top = run(0.0, link)
            paced_rate, paced_cpu, faults_paced = run(rate, link)
        finally:
            sim.terminate()
            sim.wait(timeout=10)
    return {
        "usb_max_control_rate_hz": top_rate,
        "usb_max_rate_cpu_percent": 100 * top_cpu,
        f"usb_{rate:.0f}hz_achieved_hz": paced_rate,
        f"usb_{rate:.0f}hz_cpu_percent": 100 * paced_cpu,
        "usb_servo_faults": float(faults_top + faults_paced),
    }


def teleop_latency(moves: int = 200, rate: float = 100.0) -> dict[str, float]:
    """Leader register change -> follower Goal_Position write, through a robot (usb-master and
    usb-slave on two simulated buses with wire-time emulation, both loops at `rate`)."""
    import trio

    from arena.drivers.usb_master import UsbMaster
    from arena.drivers.usb_slave import UsbSlave
    from arena.feetech import registers as reg
    from arena.feetech.sim_pty import PtySimBus
    from arena.protocol.rest import UsbMasterBody, UsbSlaveBody
    from arena.robot.manager import open_manager
    from arena.robot.model import load_robot_model

    latencies: list[float] = []

    async def run(leader: PtySimBus, follower: PtySimBus) -> None:
        model = load_robot_model("so-arm100")
        log: list[tuple[float, int, int, bytes]] = []
        async with open_manager() as manager:
            robot = await manager.create_robot("so-arm100", robot_id="arm")
            await robot.attach_slave(
                UsbSlave(UsbSlaveBody(port=str(follower.link), rate=rate), model)
            )
            master = UsbMaster(UsbMasterBody(port=str(leader.link), rate=rate), model)
            await master.prepare()
            await robot.attach_master(master)
            await trio.sleep(0.3)
            with follower.paused() as bus:
                bus.write_log = log
            for i in range(moves):
                target = 2048 + (25 if i % 2 == 0 else -25)  # 2.2 degrees: one direct step
                with leader.paused() as bus:
                    bus.servo(1).move_by_hand(target)
                    moved_at = time.monotonic()
                want = reg.GOAL_POSITION.encode(target)
                deadline = moved_at + 1.0
                while time.monotonic() < deadline:
                    await trio.sleep(0.0005)
                    with follower.paused():
                        hit = [t for t, sid, a, d in log if sid == 1 and a == 42 and d == want]
                        log.clear()
                    if hit:
                        latencies.append(hit[0] - moved_at)
                        break
                await trio.sleep(0.03 + (i % 7) * 0.003)  # spaced: the rate limit never waits

    with (
        tempfile.TemporaryDirectory() as folder,
        PtySimBus(Path(folder) / "leader", wire_time=True) as leader,
        PtySimBus(Path(folder) / "follower", wire_time=True) as follower,
    ):
        trio.run(run, leader, follower)
    latencies.sort()
    tag = f"{rate:.0f}hz"
    return {
        f"teleop_{tag}_p50_ms": 1000 * _percentile(latencies, 0.5),
        f"teleop_{tag}_p99_ms": 1000 * _percentile(latencies, 0.99),
        f"teleop_{tag}_missed": float(moves - len(latencies)),
    }


async def _with_server(scenario: Callable[[Server], Any], record: bool = True) -> Any:
    async with running_server(record=record) as server:
        return await scenario(server)


SCENARIOS = (
    "relay",
    "throughput",
    "fleet",
    "estop",
    "recording",
    "replay",
    "core",
    "usb",
    "teleop",
)
#: Long scenarios, run only when named.
LONG_SCENARIOS = ("soak",)


def run_benchmarks(
    json_path: str | None = None,
    only: list[str] | None = None,
    repeats: int = 3,
    fleet_robots: int = 100,
    soak_seconds: float = 600.0,
    soak_rate: float = 50.0,
) -> dict[str, Any]:
    """Run the chosen scenarios (medians of `repeats` runs where cheap), print, write JSON."""
    chosen = only or list(SCENARIOS)
    unknown = sorted(set(chosen) - set(SCENARIOS) - set(LONG_SCENARIOS))
    if unknown:
        known = ", ".join((*SCENARIOS, *LONG_SCENARIOS))
        raise ValueError(f"unknown scenarios: {', '.join(unknown)} (known: {known})")
    results: dict[str, Any] = {}

    def median_of(runs: list[dict[str, float]]) -> dict[str, float]:
        return {key: statistics.median(run[key] for run in runs) for key in runs[0]}

    if "core" in chosen:
        results.update(median_of([core_rate() for _ in range(repeats)]))
    if "replay" in chosen:
        results.update(median_of([replay_rate() for _ in range(repeats)]))
    if "relay" in chosen:
        results.update(median_of([asyncio.run(_with_server(relay)) for _ in range(repeats)]))
        results.update(
            median_of([asyncio.run(_with_server(relay_with_websockets)) for _ in range(repeats)])
        )
    if "throughput" in chosen or "recording" in chosen:
        on = median_of([asyncio.run(_with_server(throughput)) for _ in range(repeats)])
        results.update(on)
        if "recording" in chosen:
            off = median_of(
                [asyncio.run(_with_server(throughput, record=False)) for _ in range(repeats)]
            )
            results["throughput_no_recording_per_s"] = off["throughput_accepted_per_s"]
            results["recording_cost_ratio"] = (
                on["throughput_accepted_per_s"] / off["throughput_accepted_per_s"]
            )
    if "estop" in chosen:
        results.update(asyncio.run(_with_server(estop)))
    if "fleet" in chosen:
        results.update(asyncio.run(_with_server(lambda server: fleet(server, robots=fleet_robots))))
        # Half the rate as well: where the latency stands before one core is full.
        half = asyncio.run(
            _with_server(lambda server: fleet(server, robots=fleet_robots, rate=25.0))
        )
        results.update({k.replace("fleet_", "fleet_25hz_", 1): v for k, v in half.items()})
    if "soak" in chosen:
        window = min(60.0, soak_seconds / 4)
        results.update(
            asyncio.run(
                _with_server(
                    lambda server: soak(
                        server,
                        robots=fleet_robots,
                        rate=soak_rate,
                        seconds=soak_seconds,
                        window=window,
                    )
                )
            )
        )
    if "usb" in chosen:
        results.update(median_of([usb_control_rate() for _ in range(repeats)]))
    if "teleop" in chosen:
        for rate in (100.0, 250.0, 500.0):
            results.update(median_of([teleop_latency(rate=rate) for _ in range(repeats)]))
    width = max(len(k) for k in results)
    print(f"{'scenario':<{width}}  value (medians of {repeats} runs where repeated)")
    for key, value in results.items():
        shown = f"{value:14.2f}" if isinstance(value, float) else f"{value!s:>14}"
        print(f"{key:<{width}}  {shown}")
    if json_path:
        Path(json_path).write_text(json.dumps(results, indent=2))
    return results
