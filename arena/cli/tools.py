"""The project's tools: `schemas` (the wire messages' JSON Schemas) and `bench`."""

from __future__ import annotations

import argparse

from arena.cli.common import Commands

#: `arena bench`'s scenarios (arena/bench: SCENARIOS, then LONG_SCENARIOS), named here so that
#: reading the arguments does not import the benchmarks.
BENCH_SCENARIOS = (
    *("relay", "throughput", "fleet", "estop", "flood", "recording", "replay", "core"),
    *(
        "physics",
        "camera",
        "usb",
        "teleop",
        "soak",
        "versus",
        "nodes",
        "policy",
        "workers",
        "pause",
    ),
)


def add(commands: Commands) -> None:
    """Declare `schemas` and `bench`."""
    schemas = commands.add_parser("schemas", help="write the JSON Schemas of the wire messages")
    schemas.add_argument("--out", default="specs/schemas", help="folder to write them into")
    schemas.set_defaults(handler=schemas_command)
    bench = commands.add_parser("bench", help="run the benchmarks and print medians")
    bench.add_argument("--json", help="also write the results to this file")
    bench.add_argument(
        "scenarios",
        nargs="*",
        choices=BENCH_SCENARIOS,
        metavar="SCENARIO",
        help="which (default: all but the long ones): relay throughput fleet estop flood "
        "recording replay core physics camera usb teleop; only when named: soak versus "
        "nodes policy workers pause",
    )
    bench.add_argument("--repeats", type=int, default=3)
    bench.add_argument("--fleet-robots", type=int, default=100, help="robots in fleet and soak")
    bench.add_argument("--soak-seconds", type=float, default=600.0)
    bench.add_argument("--soak-rate", type=float, default=50.0, help="commands/s per robot")
    bench.add_argument(
        "--lerobot-python",
        metavar="PATH",
        help="teleop: LeRobot 0.6's Python with lerobot[feetech], for its loop beside Arena's "
        "(default: .compat/python, which `make compat` builds; without one it is skipped)",
    )
    bench.set_defaults(handler=bench_command)


def schemas_command(args: argparse.Namespace) -> int:
    """`arena schemas`: write every schema, print each file's path."""
    from pathlib import Path

    from arena.schemas import write_schemas

    for path in write_schemas(Path(args.out)):
        print(path)
    return 0


def bench_command(args: argparse.Namespace) -> int:
    """`arena bench`: run the scenarios named (default: all but the long ones)."""
    from arena.bench import run_benchmarks

    run_benchmarks(
        args.json,
        args.scenarios or None,
        args.repeats,
        args.fleet_robots,
        args.soak_seconds,
        args.soak_rate,
        args.lerobot_python,
    )
    return 0
