"""A 30 Hz remote master across a slow link, as the robot sees its commands: the figures of
specs/remote-link.md.

    python -m arena.bench.remote_link            # before (command_max_age 0) and after (0.4 s)

A server in this process, a robot with a slave that notes what it is told, and the master
through `SlowLink` (200 ms round trip, +-25 ms each way, so 50 ms of round-trip jitter): 2 s
of commands, a 2 s stall, 2 s more, on the real clock. For each setting: the longest gap between
commands the robot ran, the most it ran within 50 ms (a burst), how many it dropped as stale or
refused otherwise, and how late (after its stamp) the oldest command run after the stall was.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import math
import sys
import time
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from tempfile import TemporaryDirectory
from typing import Any

import trio
from trio_websocket import ConnectionClosed, open_websocket_url
from wsproto.utilities import LocalProtocolError

from arena.bench.slow_link import SlowLink
from arena.robot.events import CommandHandled
from arena.robot.links import SlaveLink
from arena.server.config import ServerConfig
from arena.server.run import run_server

RATE = 30.0
BURST_WINDOW = 0.05


class QuietSlave:
    """A slave that takes every target and reports it back at once."""

    kind = "bench-slave"

    async def run(self, link: SlaveLink) -> None:
        async for message in link.messages():
            joints = getattr(message, "joints", None)
            if joints is not None:
                await link.report_joint_states(joints)


@dataclass
class Figures:
    """What the robot saw of one run."""

    sent: int
    ran: int
    stale: int
    refused_otherwise: int
    longest_gap_ms: float
    biggest_burst: int  # commands run within BURST_WINDOW
    oldest_run_ms: float  # the age (now - its stamp) of the oldest command the robot ran
    run_late: int  # commands run more than 0.4 s after their stamp
    median_age_ms: float


async def one_run(
    max_age: float, seconds: float = 6.0, stall: tuple[float, float] = (2.0, 4.0)
) -> Figures:
    """One run of the scenario with `command_max_age` = `max_age`."""
    with TemporaryDirectory() as folder:
        config = ServerConfig(port=0, record=False, command_max_age=max_age, recordings_dir=folder)
        stop = trio.Event()
        async with trio.open_nursery() as nursery:
            app, urls = await nursery.start(partial(run_server, config, stop=stop))
            robot = await app.manager.create_robot("so-arm100", robot_id="far")
            await robot.attach_slave(QuietSlave(), "arm")
            link = SlowLink("127.0.0.1", int(urls[0].rsplit(":", 1)[1]), random_seed=1)
            await nursery.start(link.serve)
            link.shape(delay=0.1, jitter=0.025)
            ran: list[tuple[float, float]] = []  # (robot's time, the command's stamp in s)
            refusals: dict[str, int] = {}
            with robot.subscribe(maxlen=100_000, kinds=[CommandHandled]) as events:
                stamps: dict[float, float] = {}  # a command's Rotation -> its stamp (s)
                sent = await _master(link, seconds, stall, stamps)
                await trio.sleep(1.0)  # the last ones arrive
                while len(events):
                    event = events.get_nowait()
                    assert isinstance(event, CommandHandled)
                    if event.result.accepted:
                        stamp = stamps.get(round(event.command.joints[0].value, 3), math.nan)
                        ran.append((event.wall_time, stamp))
                    else:
                        code = str(event.result.code)
                        refusals[code] = refusals.get(code, 0) + 1
            stale = app.metrics.stale_commands["far"]
            stop.set()
            nursery.cancel_scope.cancel()
    times = [t for t, _ in ran]
    gaps = [b - a for a, b in itertools.pairwise(times)]
    burst = max(
        (sum(1 for u in times[i:] if u - t <= BURST_WINDOW) for i, t in enumerate(times)),
        default=0,
    )
    ages = sorted(t - s for t, s in ran)
    return Figures(
        sent=sent,
        ran=len(ran),
        stale=stale,
        refused_otherwise=sum(refusals.values()),
        longest_gap_ms=round(max(gaps, default=0.0) * 1000),
        biggest_burst=burst,
        oldest_run_ms=round(max(ages, default=0.0) * 1000),
        run_late=sum(1 for age in ages if age > 0.4),
        median_age_ms=round(ages[len(ages) // 2] * 1000) if ages else 0.0,
    )


async def _master(
    link: SlowLink, seconds: float, stall: tuple[float, float], stamps: dict[float, float]
) -> int:
    """Send stamped commands at RATE for `seconds`, the link stalled during `stall`; each
    one's Rotation (a slow ramp, a millidegree apart) names it in `stamps`."""
    url = f"ws://127.0.0.1:{link.port}/ws/master/far?joint_states=false&acks=false"
    sent = [0]
    # trio-websocket fails when a ping comes while it closes (python-trio/trio-websocket#184):
    # the run is over by then.
    with contextlib.suppress(LocalProtocolError):
        await _send_all(url, link, seconds, stall, stamps, sent)
    return sent[0]


async def _send_all(
    url: str,
    link: SlowLink,
    seconds: float,
    stall: tuple[float, float],
    stamps: dict[float, float],
    sent: list[int],
) -> None:
    async with open_websocket_url(url) as ws, trio.open_nursery() as nursery:

        async def drain() -> None:
            try:
                while True:
                    await ws.get_message()
            except ConnectionClosed:
                return

        nursery.start_soon(drain)
        start = trio.current_time()
        while (elapsed := trio.current_time() - start) < seconds:
            if stall[0] <= elapsed < stall[1] and not link.stalled:
                link.stall()
            elif elapsed >= stall[1] and link.stalled:
                link.release()
            now = time.time()
            value = round(10 + sent[0] / 1000, 3)
            stamps[value] = now
            data = {"timestamp": now * 1000, "joints": [{"name": "Rotation", "value": value}]}
            await ws.send_message(json.dumps({"type": "command", "data": data}))
            sent[0] += 1
            await trio.sleep_until(start + sent[0] / RATE)
        link.release()
        await trio.sleep(1.0)
        nursery.cancel_scope.cancel()


def main() -> dict[str, Any]:
    """Before (no age bound, today's behaviour) and after, each in a trio run of its own."""
    results = {}
    for name, max_age in (("before", 0.0), ("after", 0.4)):
        results[f"{name} (command_max_age {max_age} s)"] = trio.run(one_run, max_age).__dict__
    return results


if __name__ == "__main__":
    figures = main()
    text = json.dumps(figures, indent=2)
    print(text)
    if len(sys.argv) > 1:
        Path(sys.argv[1]).write_text(text + "\n", encoding="utf-8")
