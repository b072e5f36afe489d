"""What every scenario shares: the benchmark robot type, the server process, helpers."""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import gc
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any, TypeVar

import httpx

from arena.bench.client import BlockingHttp, BlockingWebSocket
from arena.protocol.messages import (
    CommandData,
    CommandMessage,
    EStopMessage,
    HeartbeatMessage,
    JointValue,
    ReasonData,
    ResetMessage,
    encode,
)
from arena.robot.model import BUILTIN_TYPES_DIR, TYPES_PATH_ENV

BENCH_TYPE = "so-arm100-bench"
#: Seconds a benchmark's own REST calls (making robots, attaching drivers) may take: they are
#: set-up, never measured, and a loaded machine may take seconds to answer them.
REST_TIMEOUT = 60.0

T = TypeVar("T")


def without_client_gc(run: Callable[..., T], *args: Any) -> T:
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


def percentile(values: list[float], q: float) -> float:
    """The `q` quantile (0-1) of `values` by rank, no interpolation; NaN for no values."""
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))] if ordered else float("nan")


def bench_types(folder: Path) -> Path:
    """A robot-type folder holding so-arm100 with the rate limit out of the way."""
    target = folder / BENCH_TYPE
    shutil.copytree(BUILTIN_TYPES_DIR / "so-arm100", target)
    config = target / "robot.toml"
    text = config.read_text()
    text = re.sub(r"command_rate = [\d.]+", "command_rate = 1000000.0", text)
    text = re.sub(r"command_burst = \d+", "command_burst = 1000000", text)
    config.write_text(text)
    return folder


def process_cpu_seconds(pid: int) -> float:
    """CPU time of a live process (all its threads) to the nanosecond, from its CPU-time
    clock; 0.0 once it is gone.

    /proc's figures count whole clock ticks of 10 ms: a benchmark phase that costs a server
    0.15 s read as 15 or 17 ticks from one run to the next, a swing of 13 %. Linux names
    the clock of process `pid` `(~pid << 3) | 2` (the process-wide scheduler clock); /proc's
    ticks remain the fallback where that is refused.
    """
    with contextlib.suppress(OSError):
        return time.clock_gettime((~pid << 3) | 2)
    with contextlib.suppress(OSError), open(f"/proc/{pid}/stat") as stat:
        fields = stat.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    return 0.0


@dataclasses.dataclass
class Server:
    """A server process and its base URL."""

    process: subprocess.Popen[bytes]
    url: str
    #: Arena (a floor relay is not: it has no robots to ask about, `wait_for_slaves`)
    arena: bool = True

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
        return sum(process_cpu_seconds(pid) for pid in self.pids())

    def rss_mib(self) -> float:
        """Resident memory of the server and its children."""
        total = 0
        for pid in self.pids():
            with contextlib.suppress(OSError), open(f"/proc/{pid}/status") as status:
                rss = (int(line.split()[1]) for line in status if line.startswith("VmRSS:"))
                total += next(rss, 0)  # an exiting process has none
        return total / 1024


@asynccontextmanager
async def running_server(record: bool = True, *options: str) -> AsyncIterator[Server]:
    """`arena serve` on 127.0.0.1 with a port the system chose (and any more `options`),
    stopped on exit."""
    with tempfile.TemporaryDirectory() as scratch:
        folder = Path(scratch)
        env = {
            **os.environ,
            TYPES_PATH_ENV: str(bench_types(folder / "types")),
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
        args.extend(options)
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


def wait_for_slaves(url: str, robot_ids: list[str], timeout: float = REST_TIMEOUT) -> None:
    """Block until each robot of `robot_ids` on the Arena server at `url` (http:// or ws://:
    its host and port are what count) has a slave, all within `timeout` seconds.

    A slave's socket is open before its robot has it (the handshake is answered first): a
    command sent in between reaches no slave, and a slave that never reports gets targets
    from the next command on (specs/api.md), so a benchmark timing its first command to the
    slave would wait for ever (a candidate for a relay bench's hang once seen in CI)."""
    http = BlockingHttp(url, timeout=min(timeout, 30.0))
    deadline = time.monotonic() + timeout
    try:
        for robot_id in robot_ids:
            request = http.request_bytes("GET", f"/api/robots/{robot_id}")
            while True:
                http.send(request)
                status, body = http.answer()
                if status == 200 and json.loads(body)["slaves"]:
                    break
                if time.monotonic() > deadline:
                    raise RuntimeError(f"robot {robot_id!r} has no slave after {timeout:g} s")
                time.sleep(0.005)  # (a poll: the server says nothing when a slave attaches)
    finally:
        http.close()


def attached_slave(ws: str, robot_id: str) -> BlockingWebSocket:
    """A lean slave socket on robot `robot_id` at `ws`, once the robot has it
    (`wait_for_slaves`; closed if it never does)."""
    slave = BlockingWebSocket(ws + f"/ws/slave/{robot_id}")
    try:
        wait_for_slaves(ws, [robot_id])
    except BaseException:
        slave.close()
        raise
    return slave


async def create_bench_robot(http: httpx.AsyncClient, robot_id: str) -> None:
    """Create robot `robot_id` of the benchmark type (BENCH_TYPE) over REST."""
    response = await http.post("/api/robots", json={"robot_type": BENCH_TYPE, "id": robot_id})
    response.raise_for_status()


#: What identifies a message of each type in the server's compact JSON: the lean client
#: looks for these in the text instead of parsing every message it times.
EXECUTE_MARK = '"type":"execute_command"'
ACK_MARK = '"type":"ack"'
ESTOP_MARK = '"type":"estop"'
RESET_MARK = '"type":"reset"'


# The messages the benchmarks send, made with the protocol's structs and encoder (as every
# client's are) and without a timestamp, which the server does not need: made before a clock
# starts, they cost the measurement nothing.


def joints_text(joints: dict[str, float]) -> str:
    """A master's `command` moving `joints` (degrees), as JSON text."""
    entries = [JointValue(name, value) for name, value in joints.items()]
    return encode(CommandMessage(data=CommandData(joints=entries)))


def command_text(i: int) -> str:
    """The `i`th command of a relay: tiny alternating steps of two joints, each a nanodegree
    off every earlier command's goal, so that none asks for where the arm already is (a
    command that moves nothing sends its slave nothing: a relay timing each command to its
    slave's `execute_command` waited for ever)."""
    value = (i % 2) * 0.001 + i * 1e-9
    return joints_text({"Rotation": value, "Elbow": -value})


HEARTBEAT_TEXT = encode(HeartbeatMessage())
RESET_TEXT = encode(ResetMessage())
ESTOP_TEXT = encode(EStopMessage(data=ReasonData(reason="bench")))


def time_to(
    marker: str, receiver: BlockingWebSocket, sender: BlockingWebSocket, frame: bytes
) -> float:
    """Seconds from sending `frame` to `receiver`'s first message containing `marker` (what
    it had received before is dropped first: a motion tick's `execute_command` that came
    after the last one timed is not this frame's answer)."""
    receiver.drop_received()
    start = time.perf_counter()
    sender.send_raw(frame)
    while marker not in receiver.receive():
        pass
    return time.perf_counter() - start
