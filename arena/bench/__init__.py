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
  recording   throughput with recording on against off, and with Foxglove's view in the
              recording against without (ratios); what the recording process can write, in
              events a second, with and without that view (in this process)
  replay      commands/s of a replay at maximum speed (in process)
  physics     the MuJoCo twin: steps a second flat out, and the CPU of the real-time slave at
              500 Hz (in process)
  camera      one 640x480 camera at 30 fps with one MJPEG stream client: the server's CPU
              with it against without, capture-to-client latency p50/p99, frames dropped
  core        RobotCore.command calls/s (pure decision code); the collision guard's cost per
              command in a teleoperation stream, p50 / p99 with and without it
  teleop      leader arm -> follower on two simulated buses at 1 Mbaud: a leader moved like a
              person (minimum-jerk sweeps, reversals, flicks) for Arena and for LeRobot's own
              teleoperation loop (60 fps, in LeRobot 0.6's Python, `make compat`; skipped
              without it), tracking lag p50/p99, first reaction, overshoot, ratios, one run
              (arena/bench/teleop.py); then a teleported leader's value to the follower's
              goal write, p50/p99 at 100, 250 and 500 Hz
  usb         the USB slave's control loop on a simulated bus (`arena sim-bus --wire-time`, its
              own process) at 1 Mbaud: the highest cycle rate, and the CPU at 500 Hz
  flood       one robot's REST e-stop alone and while a viewer floods the server with pings and
              never reads; the server's memory growth during the flood
  versus      (only when named) Arena against the floor relay with the `websockets` client,
              alternating rounds: relay p50/p99, burst throughput, server CPU a command, and
              a fleet (--fleet-robots at 50 Hz): p99, CPU, robots a core; ratios (needs
              ARENA_FLOOR_PYTHON; see arena/bench/versus.py)
  nodes       (only when named) a fleet of `arena serve --node` processes over Zenoh: relay
              across nodes against within one, a fleet e-stop of 3 nodes x 100 robots to the
              last slave's notice, 100 robots at 50 Hz on two nodes against one
  soak        (only when named) the fleet held for 10 minutes: latency and memory of the first
              minute against the last, commands unacknowledged, recording messages dropped
  policy      (only when named; needs lerobot) an ACT, then a diffusion policy, random weights,
              drive a robot at 30 fps: observation (camera frame age included) to command
              p50/p99, the server CPU each adds, the worker's (see arena/bench/policy.py)
  pause       (only when named; needs lerobot) a small ACT, then that ACT, paused and resumed
              20 times each: pause to hold and resume to first action p50/p99 (see
              arena/bench/pause.py)
"""

from __future__ import annotations

import asyncio
import json
import statistics
from collections.abc import Callable
from pathlib import Path
from typing import Any

from arena.bench.camera import camera
from arena.bench.common import BENCH_TYPE, Server, bench_types, running_server
from arena.bench.estop import estop, flood
from arena.bench.fleet import FleetRun, drive_fleet, fleet, soak
from arena.bench.hardware import teleop_latency, usb_control_rate
from arena.bench.inprocess import core_rate, guard_cost, physics_rate, replay_rate, writer_rate
from arena.bench.policy import policy
from arena.bench.relay import relay, relay_with_websockets, throughput
from arena.bench.versus import ordinary_relay, versus_floor


async def _with_server(
    scenario: Callable[[Server], Any], record: bool = True, *options: str
) -> Any:
    async with running_server(record, *options) as server:
        return await scenario(server)


SCENARIOS = (
    "relay",
    "throughput",
    "fleet",
    "estop",
    "flood",
    "recording",
    "replay",
    "core",
    "physics",
    "camera",
    "usb",
    "teleop",
)
#: Long scenarios, run only when named.
LONG_SCENARIOS = ("soak", "versus", "nodes", "policy", "workers", "pause")


def run_benchmarks(
    json_path: str | None = None,
    only: list[str] | None = None,
    repeats: int = 3,
    fleet_robots: int = 100,
    soak_seconds: float = 600.0,
    soak_rate: float = 50.0,
    lerobot_python: str | None = None,
) -> dict[str, Any]:
    """Run the chosen scenarios (medians of `repeats` runs where cheap), print, write JSON.
    `lerobot_python`: LeRobot 0.6's Python for teleop's comparison (default: `make compat`'s)."""
    chosen = only or list(SCENARIOS)
    unknown = sorted(set(chosen) - set(SCENARIOS) - set(LONG_SCENARIOS))
    if unknown:
        known = ", ".join((*SCENARIOS, *LONG_SCENARIOS))
        raise ValueError(f"unknown scenarios: {', '.join(unknown)} (known: {known})")
    from arena.extras import require

    if "physics" in chosen:
        require("physics", "arena bench physics")
    if "nodes" in chosen:
        require("fleet", "arena bench nodes")
    if "policy" in chosen or "workers" in chosen or "pause" in chosen:
        require("lerobot", "arena bench policy")
    results: dict[str, Any] = {}

    def median_of(runs: list[dict[str, float]]) -> dict[str, float]:
        return {key: statistics.median(run[key] for run in runs) for key in runs[0]}

    if "core" in chosen:
        results.update(median_of([core_rate() for _ in range(repeats)]))
        results.update(median_of([guard_cost() for _ in range(repeats)]))
    if "physics" in chosen:
        results.update(median_of([physics_rate() for _ in range(repeats)]))
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
            plain = median_of(
                [
                    asyncio.run(_with_server(throughput, True, "--no-record-foxglove"))
                    for _ in range(repeats)
                ]
            )
            results["throughput_no_foxglove_per_s"] = plain["throughput_accepted_per_s"]
            results["foxglove_cost_ratio"] = (
                on["throughput_accepted_per_s"] / plain["throughput_accepted_per_s"]
            )
            results.update(median_of([writer_rate() for _ in range(repeats)]))
    if "estop" in chosen:
        results.update(asyncio.run(_with_server(estop)))
    if "flood" in chosen:
        results.update(asyncio.run(_with_server(flood)))
    if "camera" in chosen:
        results.update(median_of([asyncio.run(_with_server(camera)) for _ in range(repeats)]))
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
    if "nodes" in chosen:
        from arena.bench.nodes import nodes_estop, nodes_fleet, nodes_relay  # needs zenoh

        results.update(median_of([asyncio.run(nodes_relay()) for _ in range(repeats)]))
        results.update(median_of([asyncio.run(nodes_estop()) for _ in range(repeats)]))
        results.update(asyncio.run(nodes_fleet(robots=fleet_robots)))
    if "versus" in chosen:
        results.update(asyncio.run(versus_floor(rounds=repeats, fleet_robots=fleet_robots)))
    if "policy" in chosen:
        results.update(asyncio.run(_with_server(policy)))
    if "pause" in chosen:
        from arena.bench.pause import pause

        results.update(asyncio.run(_with_server(pause)))
    if "workers" in chosen:
        import trio

        from arena.bench.workers import workers  # the policy worker on trio, no server

        results.update(trio.run(workers))
    if "usb" in chosen:
        results.update(median_of([usb_control_rate() for _ in range(repeats)]))
    if "teleop" in chosen:
        from arena.bench.teleop import teleop_versus

        results.update(teleop_versus(python=Path(lerobot_python) if lerobot_python else None))
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


__all__ = [
    "BENCH_TYPE",
    "LONG_SCENARIOS",
    "SCENARIOS",
    "FleetRun",
    "Server",
    "bench_types",
    "core_rate",
    "drive_fleet",
    "estop",
    "fleet",
    "flood",
    "ordinary_relay",
    "relay",
    "relay_with_websockets",
    "replay_rate",
    "run_benchmarks",
    "running_server",
    "soak",
    "teleop_latency",
    "throughput",
    "usb_control_rate",
    "versus_floor",
]
