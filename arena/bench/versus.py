"""Arena against another server, as ordinary clients see them: the relay subset of the contract
(`POST /api/robots`, `/ws/master/{id}`, `/ws/slave/{id}`) driven by Python's `websockets`.

Each round runs 2,000 commands one at a time (master send -> the slave's `execute_command`),
then 10,000 as fast as the master sends them (until the slave has the last one: a small step
of a joint at rest, which no server holds back). When the bench started the server itself,
its CPU (the whole process tree) over both phases and the half second after them (for the
work the commands left behind) is divided by the 12,000 commands, and given by phase too.
Then a fleet (`fleet_robots` robots, each a master at 50 Hz and a slave, the lean client of
`arena bench fleet`) runs on each server for 10 s: its p99 and the server's CPU, and from them
the robots one core would hold at that rate (robots / the share of a core they took; a figure
that holds only while the p99 stays inside 5 ms, which `fleet_within_5ms` says). Rounds
alternate between the servers; the figures are medians, and the ratios to the floor come from
one run.

The floor is `shared/bench/floor_relay.py` (aiohttp on uvloop with orjson: parse and forward,
nothing else), run with a Python that has those packages: `ARENA_FLOOR_PYTHON=PATH` (and
`ARENA_FLOOR_SCRIPT=PATH` if the script is not at `../shared/bench/floor_relay.py`).

Beside them runs the *contract floor*: `arena/bench/trio_floor.py --acks`, the floor written on
trio that also acknowledges every command as Arena does (a read and two writes a command, the
least the contract's messages cost on the loop Arena is built on). Its figures are
`versus_contract_*`, and Arena's ratios to it `versus_ratio_contract_*`: what is left above it
is Arena's own work (the safety machine, limits, the guard, joint states, the recording).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import socket
import statistics
import subprocess
import sys
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path

import httpx

from arena.bench.common import (
    BENCH_TYPE,
    REST_TIMEOUT,
    Server,
    percentile,
    running_server,
    wait_for_slaves,
)
from arena.bench.fleet import fleet

FLOOR_PYTHON_ENV = "ARENA_FLOOR_PYTHON"
FLOOR_SCRIPT_ENV = "ARENA_FLOOR_SCRIPT"
_DEFAULT_FLOOR = Path(__file__).resolve().parents[3] / "shared" / "bench" / "floor_relay.py"


def _command(i: int) -> str:
    # Never the value before: a command that changes nothing sends the slave no target.
    joints = [{"name": "Rotation", "value": round((i % 200 + 1) * 0.1, 1)}]
    return json.dumps({"type": "command", "data": {"joints": joints}})


# The burst ends with a joint at rest taking a small step, which any server relays at once:
# the end is when the slave has it. (The burst's own joint trails its goals at the arm's
# velocity limit; ending on a far value of that joint timed the arm's travel to it, up to
# ~0.1 s, as if it were the relay's.)
_LAST = json.dumps({"type": "command", "data": {"joints": [{"name": "Pitch", "value": 0.77}]}})
_LAST_SEEN = '"name":"Pitch","value":0.77'
#: Seconds after the burst before the server's CPU is read (a recording batch is 0.05 s, a
#: flush 0.25 s; the arm's travel on to its last goal ~0.1 s).
_SETTLE = 0.5


async def ordinary_relay(
    server: Server, robot_id: str, one_at_a_time: int = 2000, burst: int = 10_000
) -> dict[str, float]:
    """Relay latency, burst throughput and (for a server the bench started) CPU a command."""
    import websockets

    async with httpx.AsyncClient(base_url=server.url, timeout=REST_TIMEOUT) as http:
        created = await http.post("/api/robots", json={"robot_type": BENCH_TYPE, "id": robot_id})
        created.raise_for_status()
    arrived: asyncio.Queue[str] = asyncio.Queue()
    async with (
        websockets.connect(compression=None, uri=f"{server.ws}/ws/slave/{robot_id}") as slave,
        websockets.connect(compression=None, uri=f"{server.ws}/ws/master/{robot_id}") as master,
    ):
        if server.arena:
            await asyncio.to_thread(wait_for_slaves, server.url, [robot_id])

        async def read_slave() -> None:
            async for raw in slave:
                text = raw if isinstance(raw, str) else raw.decode()
                if '"execute_command"' in text:
                    arrived.put_nowait(text)

        async def drain_master() -> None:  # acks and joint states, read as a client would
            async for _ in master:
                pass

        readers = [asyncio.create_task(read_slave()), asyncio.create_task(drain_master())]
        cpu_before = server.cpu_seconds()
        latencies = []
        for i in range(one_at_a_time):
            sent = time.perf_counter()
            await master.send(_command(i))
            await arrived.get()
            latencies.append(time.perf_counter() - sent)
        cpu_one = server.cpu_seconds() - cpu_before
        started = time.perf_counter()
        for i in range(burst - 1):
            await master.send(_command(i))
        await master.send(_LAST)
        while _LAST_SEEN not in (await arrived.get()).replace(" ", ""):
            pass
        seconds = time.perf_counter() - started
        # CPU counts the work the commands left behind too (the last recording batch, the
        # arm's travel on to its last goal): read once the server has had time for it.
        await asyncio.sleep(_SETTLE)
        cpu = server.cpu_seconds() - cpu_before
        for reader in readers:
            reader.cancel()
    return {
        "p50_us": percentile(latencies, 0.5) * 1e6,
        "p99_us": percentile(latencies, 0.99) * 1e6,
        "throughput_per_s": burst / seconds,
        "cpu_us_per_command": cpu / (one_at_a_time + burst) * 1e6,
        # The same split by phase: one at a time, where every command is a wake-up, and the
        # burst with what it left behind.
        "cpu_one_at_a_time_us_per_command": cpu_one / one_at_a_time * 1e6,
        "cpu_burst_us_per_command": (cpu - cpu_one) / burst * 1e6,
    }


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


#: The contract floor: the trio floor that acknowledges every command.
CONTRACT_FLOOR = Path(__file__).with_name("trio_floor.py")


@asynccontextmanager
async def running_floor(python: str, script: Path, *options: str) -> AsyncIterator[Server]:
    """The floor relay (given `options` after its port) on 127.0.0.1, stopped on exit."""
    port = _free_port()
    command = [python, str(script), str(port), *options]
    process = subprocess.Popen(command, stderr=subprocess.DEVNULL)
    url = f"http://127.0.0.1:{port}"
    try:
        async with httpx.AsyncClient(base_url=url, timeout=REST_TIMEOUT) as http:
            for _ in range(200):
                with contextlib.suppress(httpx.TransportError):
                    if (await http.get("/")).status_code == 200:
                        break
                await asyncio.sleep(0.05)
            else:
                raise RuntimeError("the floor relay did not start")
        yield Server(process, url, arena=False)
    finally:
        process.terminate()
        process.wait(timeout=10)


#: The fleet's tail bound: a robots-a-core figure counts only while the p99 stays inside it.
FLEET_P99_BOUND_US = 5000.0


async def fleet_per_core(server: Server, robots: int, acks: bool) -> dict[str, float]:
    """A fleet of `robots` at 50 Hz for 10 s: p99, the server's CPU, and robots a core."""
    run = await fleet(server, robots=robots, rate=50.0, seconds=10.0, acks=acks)
    share = run["fleet_server_cpu_percent"] / 100
    return {
        "fleet_p99_us": run["fleet_p99_us"],
        "fleet_cpu_percent": run["fleet_server_cpu_percent"],
        "fleet_robots_per_core": robots / share if share > 0 else 0.0,
        "fleet_within_5ms": float(run["fleet_p99_us"] <= FLEET_P99_BOUND_US),
    }


async def versus_floor(rounds: int = 3, fleet_robots: int = 100, **sizes: int) -> dict[str, float]:
    """Arena and the floor in alternating rounds: medians, and Arena's ratios to the floor."""
    python = os.environ.get(FLOOR_PYTHON_ENV)
    script = Path(os.environ.get(FLOOR_SCRIPT_ENV, str(_DEFAULT_FLOOR)))
    if not python or not script.exists():
        raise RuntimeError(
            f"versus needs {FLOOR_PYTHON_ENV} (a Python with aiohttp, uvloop and orjson) and the "
            f"floor script ({FLOOR_SCRIPT_ENV}, default {_DEFAULT_FLOOR})"
        )
    runs: dict[str, list[dict[str, float]]] = {"arena": [], "floor": [], "contract": []}
    for n in range(rounds):
        async with running_server() as arena:
            measured = await ordinary_relay(arena, f"versus-{n}", **sizes)
        async with running_server() as arena:
            measured.update(await fleet_per_core(arena, fleet_robots, acks=True))
        runs["arena"].append(measured)
        async with running_floor(python, script) as floor:
            measured = await ordinary_relay(floor, f"versus-{n}", **sizes)
            # The floor keeps one slave per robot id, so one process serves both parts.
            measured.update(await fleet_per_core(floor, fleet_robots, acks=False))
        runs["floor"].append(measured)
        async with running_floor(sys.executable, CONTRACT_FLOOR, "--acks") as contract:
            measured = await ordinary_relay(contract, f"versus-{n}", **sizes)
            measured.update(await fleet_per_core(contract, fleet_robots, acks=True))
        runs["contract"].append(measured)
    results: dict[str, float] = {}
    for name, rounds_of in runs.items():
        for key in rounds_of[0]:
            results[f"versus_{name}_{key}"] = statistics.median(m[key] for m in rounds_of)
    for key in runs["arena"][0]:
        if key == "fleet_within_5ms":
            continue
        ours = results[f"versus_arena_{key}"]
        results[f"versus_ratio_{key}"] = ours / results[f"versus_floor_{key}"]
        results[f"versus_ratio_contract_{key}"] = ours / results[f"versus_contract_{key}"]
    return results
