"""`arena bench`: in-process benchmarks of the robot core. Prints medians; asserts nothing.

Scenarios (each run several times, the median reported):
- core: `RobotCore.command` calls per second (pure decision code: safety, limits, motion).
- actor: commands per second through a robot actor with one slave attached, awaiting each answer,
  and the per-command round-trip time (p50, p99).
- relay: time from a master's command to a slave taking the target (p50, p99).
"""

from __future__ import annotations

import dataclasses
import json
import statistics
import time
from collections.abc import Callable
from typing import Any

import trio

from arena.robot.actor import SlaveLink
from arena.robot.core import RobotCore
from arena.robot.events import SlaveTarget
from arena.robot.manager import open_manager
from arena.robot.model import load_robot_model
from arena.robot.motion import Command

REPEATS = 5
COMMANDS = 20_000


def _commands(count: int) -> list[Command]:
    # Tiny alternating steps that stay inside the velocity budget even at tens of thousands of
    # commands per second, so every command produces a target.
    return [
        Command.of({"Rotation": (i % 2) * 0.001, "Elbow": -(i % 2) * 0.001}) for i in range(count)
    ]


def bench_core() -> float:
    """Pure core: commands per second."""
    model = load_robot_model("so-arm100")
    policy = dataclasses.replace(model.safety, command_rate=1e12, command_burst=10**9)
    core = RobotCore(model, 0.0, policy)
    commands = _commands(COMMANDS)
    start = time.perf_counter()
    for i, command in enumerate(commands):
        core.command(None, command, i * 0.01)
    return COMMANDS / (time.perf_counter() - start)


async def _actor_round_trips() -> tuple[float, list[float], list[float]]:
    model = load_robot_model("so-arm100")
    policy = dataclasses.replace(model.safety, command_rate=1e12, command_burst=10**9)
    received: list[float] = []

    async def slave(link: SlaveLink) -> None:
        while True:
            message = await link.receive()
            if isinstance(message, SlaveTarget):
                received.append(time.perf_counter())

    async with open_manager() as manager:
        robot = await manager.create_robot("so-arm100", robot_id="bench", policy=policy)
        link = await robot.connect_slave("bench-slave")
        async with trio.open_nursery() as nursery:
            nursery.start_soon(slave, link)
            master = await robot.connect_master("bench-master")
            round_trips: list[float] = []
            relays: list[float] = []
            commands = _commands(COMMANDS // 4)
            start = time.perf_counter()
            for command in commands:
                sent = time.perf_counter()
                await master.command(command)
                round_trips.append(time.perf_counter() - sent)
                count = len(received)
                for _ in range(100):  # let the slave take the target
                    if len(received) > count:
                        relays.append(received[-1] - sent)
                        break
                    await trio.sleep(0)
            elapsed = time.perf_counter() - start
            nursery.cancel_scope.cancel()
    return len(commands) / elapsed, round_trips, relays


def _median_of(runs: int, fn: Callable[[], float]) -> float:
    return statistics.median(fn() for _ in range(runs))


def _percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


def run_benchmarks(json_path: str | None = None) -> dict[str, Any]:
    """Run every scenario, print a table, optionally write JSON."""
    results: dict[str, Any] = {}
    results["core_commands_per_s"] = _median_of(REPEATS, bench_core)
    actor_runs = [trio.run(_actor_round_trips) for _ in range(REPEATS)]
    results["actor_commands_per_s"] = statistics.median(r[0] for r in actor_runs)
    trips = [t for r in actor_runs for t in r[1]]
    relays = [t for r in actor_runs for t in r[2]]
    results["actor_round_trip_us_p50"] = _percentile(trips, 0.5) * 1e6
    results["actor_round_trip_us_p99"] = _percentile(trips, 0.99) * 1e6
    results["relay_us_p50"] = _percentile(relays, 0.5) * 1e6
    results["relay_us_p99"] = _percentile(relays, 0.99) * 1e6
    width = max(len(k) for k in results)
    print(f"{'scenario':<{width}}  median of {REPEATS} runs")
    for key, value in results.items():
        print(f"{key:<{width}}  {value:12.1f}")
    if json_path:
        with open(json_path, "w", encoding="utf-8") as handle:
            json.dump(results, handle, indent=2)
    return results
