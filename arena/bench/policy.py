"""`arena bench policy`: a LeRobot ACT, then a diffusion policy, as a robot's master, on this
machine's CPU.

One robot on a server of its own (`arena serve`, recording on) with a mock slave and a
640x480 test-pattern camera at 30 fps. An ACT with LeRobot's default architecture (a ResNet-18
backbone, `dim_model` 512, chunks of 100 actions) and random weights (no pretrained backbone:
nothing is downloaded) is saved by `python -m arena.bench.act DIR` in a process of its own,
then attached over REST at 30 fps with LeRobot's async-inference defaults (50 actions a chunk,
an observation when half are left). It takes one 240x320 image, which the worker scales from
the camera's JPEG. Then the same with a diffusion policy of LeRobot's default architecture (10
denoising steps; `python -m arena.bench.act DIR --type diffusion`), its figures beside.

Measured:
- the server's CPU (its recording process included, the policy's worker not) over the same
  window with the camera and no policy, then with the policy driving: what a policy adds;
- the worker's CPU while it drives;
- observation to command, from the policy's own records in the recording
  (`/robots/{id}/policy`): the age of the camera frame when the observation left, plus the
  time from then to the first command decided after its chunk came back (`observation_to_
  command`). Also the round trip to the worker and the worker's own inference time.
"""

from __future__ import annotations

import asyncio
import contextlib
import sys
import tempfile
from collections.abc import AsyncIterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import httpx

from arena.bench.common import Server, create_bench_robot, percentile, process_cpu_seconds
from arena.recording.mcap_file import RecordedMessage, read_recording

ROBOT = "policy-arm"
CAMERA = {"name": "front", "source": "test-pattern", "fps": 30, "width": 640, "height": 480}
FPS = 30.0
ACTIONS_PER_CHUNK = 50  # LeRobot's RobotClient default


def observation_to_command(messages: Sequence[RecordedMessage], identity: str) -> list[float]:
    """Seconds from each observation's oldest camera frame to the first command of the policy
    decided once its chunk came back (trio times of the records, one clock). An inference
    with no command after it (the run ended) counts nothing."""
    commands = sorted(
        float(m.data["t"])
        for m in messages
        if m.kind == "command" and m.data["source"] == identity and m.data["accepted"]
    )
    found = []
    for record in (m for m in messages if m.kind == "policy" and m.data["policy"] == identity):
        back = float(record.data["t"])
        sent = back - float(record.data["latency"])
        after = next((t for t in commands if t >= back), None)
        if after is not None:
            found.append(after - sent + float(record.data["frame_age"] or 0.0))
    return found


def _worker_pid(server: Server) -> int | None:
    for pid in server.pids()[1:]:
        with contextlib.suppress(OSError):
            if b"arena.policy.worker" in Path(f"/proc/{pid}/cmdline").read_bytes():
                return pid
    return None


async def _cpu_over(server: Server, seconds: float, worker: int | None) -> tuple[float, float]:
    """(server without the worker, worker) CPU in percent of one core over `seconds`."""

    def sample() -> tuple[float, float]:
        both = server.cpu_seconds()
        alone = process_cpu_seconds(worker) if worker is not None else 0.0
        return both - alone, alone

    server_before, worker_before = sample()
    await asyncio.sleep(seconds)
    server_after, worker_after = sample()
    return (
        (server_after - server_before) / seconds * 100,
        (worker_after - worker_before) / seconds * 100,
    )


async def saved_policy(folder: Path, kind: str) -> Path:
    """The benchmark's policy of `kind` saved in `folder` by a process of its own."""
    made = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "arena.bench.act", str(folder), "--type", kind
    )
    if await made.wait() != 0:
        raise RuntimeError(f"the benchmark's {kind} policy could not be saved")
    return folder


async def attach_policy(http: httpx.AsyncClient, robot: str, folder: Path) -> str:
    """Attach the policy in `folder` as `robot`'s master at the benchmark's rate: its id."""
    body = {
        "type": "policy",
        "path": str(folder),
        "fps": FPS,
        "actions_per_chunk": ACTIONS_PER_CHUNK,
    }
    attached = await http.post(f"/api/robots/{robot}/master", json=body)
    attached.raise_for_status()
    return str(attached.json()["id"])


@dataclass
class PolicyRun:
    """A policy benchmark under way: its client, its saved policies by kind, and (once it is
    over) the messages of its recording."""

    http: httpx.AsyncClient
    folders: dict[str, Path]
    messages: list[RecordedMessage] = field(default_factory=list)


@contextlib.asynccontextmanager
async def policy_run(server: Server, robot: str, kinds: Sequence[str]) -> AsyncIterator[PolicyRun]:
    """The benchmark's policies of `kinds` saved in a scratch folder, and `robot` made on
    `server` with a mock slave and the camera; at the end the recording is stopped and read
    back into `messages`."""
    with tempfile.TemporaryDirectory() as scratch:
        folders = {kind: await saved_policy(Path(scratch) / kind, kind) for kind in kinds}
        async with httpx.AsyncClient(base_url=server.url, timeout=300) as http:
            await create_bench_robot(http, robot)
            base = f"/api/robots/{robot}"
            (await http.post(f"{base}/slaves", json={"type": "mock-slave"})).raise_for_status()
            (await http.post(f"{base}/cameras", json=CAMERA)).raise_for_status()
            run = PolicyRun(http, folders)
            yield run
            stopped = (await http.post("/api/recordings/current/stop")).json()["stopped"]
            data = (await http.get(f"/api/recordings/{stopped}/file")).content
        path = Path(scratch) / "run.mcap"
        path.write_bytes(data)
        run.messages = read_recording(path).messages


async def _drive(
    http: httpx.AsyncClient, server: Server, folder: Path, seconds: float, warmup: float
) -> tuple[str, float, float]:
    """Attach the policy in `folder`, let it warm up, then measure `seconds`: its identity,
    the server's CPU and the worker's (percent of one core); detached after."""
    identity = await attach_policy(http, ROBOT, folder)
    await asyncio.sleep(warmup)  # the first inferences warm the policy up
    busy, worker_cpu = await _cpu_over(server, seconds, _worker_pid(server))
    await http.delete(f"/api/robots/{ROBOT}/master")
    return identity, busy, worker_cpu


def _figures(
    messages: Sequence[RecordedMessage], identity: str, prefix: str, skip: int
) -> dict[str, float]:
    """Observation to command and the policy's own records, past its first `skip` inferences."""
    records = [m.data for m in messages if m.kind == "policy" and m.data["policy"] == identity]
    records = records[skip:]
    latencies = observation_to_command(messages, identity)[skip:]
    return {
        f"{prefix}_observation_to_command_p50_ms": percentile(latencies, 0.5) * 1000,
        f"{prefix}_observation_to_command_p99_ms": percentile(latencies, 0.99) * 1000,
        f"{prefix}_frame_age_p50_ms": percentile([r["frame_age"] for r in records], 0.5) * 1000,
        f"{prefix}_round_trip_p50_ms": percentile([r["latency"] for r in records], 0.5) * 1000,
        f"{prefix}_inference_p50_ms": percentile([r["inference"] for r in records], 0.5) * 1000,
        f"{prefix}_inferences": float(len(latencies)),
    }


async def policy(server: Server, seconds: float = 20.0, warmup: float = 5.0) -> dict[str, float]:
    """The figures above for an ACT (`policy_...`) and then a diffusion policy (`policy_
    diffusion_...`, 10 denoising steps: seconds an inference on a CPU, so it runs twice as
    long), each for `seconds` after its warm-up, on the same server."""
    async with policy_run(server, ROBOT, ("act", "diffusion")) as run:
        await asyncio.sleep(warmup)
        idle, _ = await _cpu_over(server, seconds, None)
        act_id, busy, worker_cpu = await _drive(
            run.http, server, run.folders["act"], seconds, warmup
        )
        slow = await _drive(run.http, server, run.folders["diffusion"], 2 * seconds, 2 * warmup)
    messages = run.messages
    return {
        "policy_server_cpu_percent": busy - idle,
        "policy_idle_server_cpu_percent": idle,
        "policy_worker_cpu_percent": worker_cpu,
        **_figures(messages, act_id, "policy", 2),
        "policy_diffusion_server_cpu_percent": slow[1] - idle,
        "policy_diffusion_worker_cpu_percent": slow[2],
        **_figures(messages, slow[0], "policy_diffusion", 1),
    }
