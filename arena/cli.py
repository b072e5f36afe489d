"""The `arena` command: `arena demo` (in-process demo) and `arena bench` (benchmarks)."""

from __future__ import annotations

import argparse
import logging
import os
import sys
from functools import partial

import trio

from arena.drivers.mock_slave import MockSlave, MockSlaveConfig
from arena.drivers.sequence_master import SequenceMaster
from arena.drivers.sequences import demo_sequences, get_sequence
from arena.robot.manager import open_manager
from arena.robot.snapshot import RobotSnapshot


def format_joints(snapshot: RobotSnapshot) -> str:
    """One line: every joint's virtual/real value in degrees."""
    parts = []
    for joint in snapshot.joints:
        real = "  -  " if joint.real_value is None else f"{joint.real_value:6.1f}"
        parts.append(f"{joint.name}={joint.virtual_value:6.1f}/{real}")
    return f"[{snapshot.mode:>8}] " + " ".join(parts)


async def run_demo(sequence_ids: list[str], loop: bool, interval: float) -> None:
    """Create `demo-arm` with a mock slave, play sequences, print joint states as they go."""
    sequences = [get_sequence(s) for s in sequence_ids]
    async with open_manager() as manager:
        robot = await manager.create_robot("so-arm100", "Demo arm", "demo-arm")
        await robot.attach_slave(MockSlave(MockSlaveConfig(simulate_latency=20, response_delay=10)))
        master = SequenceMaster(sequences, loop=loop)
        await robot.attach_master(master)
        print(f"robot demo-arm: playing {', '.join(sequence_ids)} (virtual/real degrees)")
        while robot.snapshot().owner is not None:
            print(format_joints(robot.snapshot()), flush=True)
            await trio.sleep(interval)
        print(format_joints(robot.snapshot()))
        print("done")


def main(argv: list[str] | None = None) -> int:
    """Entry point of the `arena` console script."""
    parser = argparse.ArgumentParser(prog="arena", description=__doc__)
    commands = parser.add_subparsers(dest="command", required=True)
    demo = commands.add_parser("demo", help="play the demo sequences on a simulated arm")
    demo.add_argument(
        "--sequence",
        action="append",
        choices=sorted(demo_sequences()),
        help="sequence to play (repeatable; default: all three)",
    )
    demo.add_argument("--loop", action="store_true", help="repeat until Ctrl-C")
    demo.add_argument("--interval", type=float, default=0.5, help="seconds between printouts")
    serve = commands.add_parser("serve", help="run the HTTP and WebSocket server")
    serve.add_argument("--host", default=None, help="address to bind (default 127.0.0.1)")
    serve.add_argument("--port", type=int, default=None, help="port (default 8080; 0: any)")
    serve.add_argument(
        "--demo",
        action="store_true",
        default=None,
        help="create robot demo-arm (so-arm100) with a mock slave",
    )
    serve.add_argument("--config", help="a TOML file of server settings")
    serve.add_argument(
        "--api-key",
        action="append",
        default=[],
        dest="api_keys",
        help="an API key clients must present (repeatable)",
    )
    serve.add_argument(
        "--insecure",
        action="store_true",
        default=None,
        help="allow binding beyond loopback without API keys",
    )
    serve.add_argument("--certfile", help="TLS certificate (PEM)")
    serve.add_argument("--keyfile", help="TLS private key (PEM)")
    schemas = commands.add_parser("schemas", help="write the JSON Schemas of the wire messages")
    schemas.add_argument("--out", default="specs/schemas", help="folder to write them into")
    bench = commands.add_parser("bench", help="run the benchmarks and print medians")
    bench.add_argument("--json", help="also write the results to this file")
    args = parser.parse_args(argv)
    default_level = "INFO" if args.command == "serve" else "WARNING"
    logging.basicConfig(
        level=os.environ.get("LOG_LEVEL", default_level).upper(),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    try:
        if args.command == "serve":
            return _serve(args)
        if args.command == "schemas":
            from pathlib import Path

            from arena.protocol.schemas import write_schemas

            for path in write_schemas(Path(args.out)):
                print(path)
            return 0
        if args.command == "demo":
            trio.run(run_demo, args.sequence or list(demo_sequences()), args.loop, args.interval)
        elif args.command == "bench":
            from arena.bench import run_benchmarks

            run_benchmarks(args.json)
    except KeyboardInterrupt:
        return 130
    return 0


def _serve(args: argparse.Namespace) -> int:
    from arena.protocol.errors import ArenaError
    from arena.server.config import load_config
    from arena.server.run import run_server

    try:
        config = load_config(
            args.config,
            host=args.host,
            port=args.port,
            demo=args.demo,
            api_keys=tuple(args.api_keys),
            insecure=args.insecure,
            certfile=args.certfile,
            keyfile=args.keyfile,
        )
        config.check()
    except ArenaError as error:
        print(f"arena serve: {error.message}", file=sys.stderr)
        return 2
    trio.run(partial(run_server, config, handle_signals=True))
    return 0


if __name__ == "__main__":
    sys.exit(main())
