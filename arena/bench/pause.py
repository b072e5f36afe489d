"""`arena bench pause`: how fast a running policy holds when paused, and acts again when
resumed (specs/policy.md, "Figures: `arena bench pause`").

One robot on a server of its own (`arena serve`, recording on) with a mock slave and a 640x480
test-pattern camera at 30 fps; a small ACT (milliseconds an inference), then LeRobot's default
ACT, random weights (as `arena bench policy` saves it), drives it at 30 fps. After a warm-up,
`runs` times: `POST .../master/pause`, a second paused, `POST .../master/resume`, and once the
policy acts again a second and a half running. From the recording:

- pause to hold: from the moment the pause request left the client to the last change of the
  robot's targets before the resume (the robot holds from then on; none after the request:
  zero);
- resume to first action: from the moment the resume request left to the first command of the
  policy the robot accepted after it (a fresh observation, one inference, the next control
  step).

The client's wall clock against the records' log times (the server's wall clock, anchored
when its recording started): one machine, one clock. The same two again from the moment the
robot applied the pause or resume (its master's `paused` / `resumed` record), which leaves out
the HTTP request's way in. Resume to first action is mostly one inference: Arena's own parts
of it are taken apart (`resume_parts`).
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Sequence
from pathlib import Path

import httpx

from arena.bench.common import Server, percentile
from arena.bench.policy import attach_policy, policy_run
from arena.recording.mcap_file import RecordedMessage

ROBOT = "pause-arm"


def pause_latencies(
    messages: Sequence[RecordedMessage],
    identity: str,
    pauses: Sequence[float],
    resumes: Sequence[float],
) -> tuple[list[float], list[float]]:
    """(pause to hold, resume to first action) in seconds for each pause at `pauses[i]` and
    resume at `resumes[i]` (wall-clock seconds), from the robot's recorded targets and the
    policy's accepted commands."""
    targets = [(m.log_time / 1e9, m.data["joints"]) for m in messages if m.kind == "targets"]
    commands = sorted(
        m.log_time / 1e9
        for m in messages
        if m.kind == "command" and m.data["source"] == identity and m.data["accepted"]
    )
    holds, firsts = [], []
    for paused, resumed in zip(pauses, resumes, strict=True):
        last_change = paused
        previous = None
        for at, joints in targets:
            if at >= resumed:
                break
            if at >= paused and previous is not None and joints != previous:
                last_change = at
            previous = joints
        holds.append(last_change - paused)
        first = next((at for at in commands if at >= resumed), None)
        if first is not None:
            firsts.append(first - resumed)
    return holds, firsts


def resume_parts(
    messages: Sequence[RecordedMessage], identity: str, resumes: Sequence[float]
) -> tuple[list[float], list[float]]:
    """Arena's own parts of each resume at `resumes[i]` (the log time, seconds, the robot
    applied it): to the fresh observation leaving for the worker (the first inference
    recorded after it, less its round trip: an inference in flight at the pause is waited
    out first), and from its chunk back to the first command of the policy accepted."""
    inferences = sorted(
        (m.log_time / 1e9, float(m.data["latency"]))
        for m in messages
        if m.kind == "policy" and m.data["policy"] == identity
    )
    commands = sorted(
        m.log_time / 1e9
        for m in messages
        if m.kind == "command" and m.data["source"] == identity and m.data["accepted"]
    )
    observed, commanded = [], []
    for resumed in resumes:
        fresh = next(((t, lat) for t, lat in inferences if t - lat >= resumed), None)
        if fresh is None:
            continue
        back, latency = fresh
        observed.append(back - latency - resumed)
        first = next((at for at in commands if at >= back), None)
        if first is not None:
            commanded.append(first - back)
    return observed, commanded


async def _sent(http: httpx.AsyncClient) -> float:
    """Commands of the robot's policy master the robot accepted so far (its figures)."""
    master = (await http.get(f"/api/robots/{ROBOT}")).json()["master"]
    return float(master["figures"]["sent"])


async def _runs(
    http: httpx.AsyncClient,
    folder: Path,
    runs: int,
    warmup: float,
    paused: float,
    running: float,
) -> tuple[str, list[float], list[float]]:
    """Attach the policy in `folder`, pause and resume it `runs` times, detach it: its
    identity and the wall-clock times each pause and resume request left."""
    base = f"/api/robots/{ROBOT}"
    identity = await attach_policy(http, ROBOT, folder)
    await asyncio.sleep(warmup)
    pauses, resumes = [], []
    for _ in range(runs):
        pauses.append(time.time())
        (await http.post(f"{base}/master/pause")).raise_for_status()
        await asyncio.sleep(paused)
        sent = await _sent(http)
        resumes.append(time.time())
        (await http.post(f"{base}/master/resume")).raise_for_status()
        # Until the policy acts again (on a busy CPU an inference may take longer than any
        # fixed wait, and a chunk that comes back after the next pause is dropped), then on.
        deadline = time.monotonic() + 120
        while await _sent(http) == sent and time.monotonic() < deadline:
            await asyncio.sleep(0.05)
        await asyncio.sleep(running)
    await http.delete(f"{base}/master")
    return identity, pauses, resumes


def _figures(
    messages: Sequence[RecordedMessage],
    identity: str,
    pauses: list[float],
    resumes: list[float],
    prefix: str,
) -> dict[str, float]:
    holds, firsts = pause_latencies(messages, identity, pauses, resumes)
    # The same from when the robot applied each (its master's `paused` / `resumed` record):
    # what the robot and the policy take, without the HTTP request's way in.
    applied = {
        change: [
            m.log_time / 1e9
            for m in messages
            if m.kind == "peer" and m.data["peer_id"] == identity and m.data["change"] == change
        ]
        for change in ("paused", "resumed")
    }
    held, acted = pause_latencies(messages, identity, applied["paused"], applied["resumed"])
    observed, commanded = resume_parts(messages, identity, applied["resumed"])
    inferences = [
        float(m.data["latency"])
        for m in messages
        if m.kind == "policy" and m.data["policy"] == identity
    ]
    found = {
        "to_hold": holds,
        "applied_to_hold": held,
        "to_first_action": firsts,
        "applied_to_first_action": acted,
        "applied_to_observation": observed,
        "chunk_to_action": commanded,
        "inference_round_trip": inferences,
    }
    figures = {f"{prefix}_runs": float(len(holds))}
    for name, values in found.items():
        figures[f"{prefix}_{name}_p50_ms"] = percentile(values, 0.5) * 1000
        figures[f"{prefix}_{name}_p99_ms"] = percentile(values, 0.99) * 1000
    return figures


async def pause(
    server: Server, runs: int = 20, warmup: float = 5.0, paused: float = 1.0, running: float = 1.5
) -> dict[str, float]:
    """The figures above over `runs` pauses and resumes of a small ACT (`pause_small_...`:
    milliseconds an inference, so Arena's own part shows) and of LeRobot's default ACT
    (`pause_act_...`), one after the other on the same server."""
    async with policy_run(server, ROBOT, ("small", "act")) as run:
        first = await _runs(run.http, run.folders["small"], runs, warmup, paused, running)
        second = await _runs(run.http, run.folders["act"], runs, warmup, paused, running)
    messages = run.messages
    return {
        **_figures(messages, *first, "pause_small"),
        **_figures(messages, *second, "pause_act"),
    }
