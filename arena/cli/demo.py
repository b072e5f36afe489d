"""`arena demo`: the demo sequences on a simulated arm, in this process."""

from __future__ import annotations

import argparse

import trio

from arena.cli.common import Commands
from arena.drivers.mock_slave import MockSlave, MockSlaveConfig
from arena.drivers.sequence_master import SequenceMaster
from arena.drivers.sequences import demo_sequences, get_sequence
from arena.robot.manager import open_manager
from arena.robot.snapshot import RobotSnapshot


def add(commands: Commands) -> None:
    """Declare `demo`."""
    demo = commands.add_parser("demo", help="play the demo sequences on a simulated arm")
    demo.add_argument(
        "--sequence",
        action="append",
        choices=sorted(demo_sequences()),
        help="sequence to play (repeatable; default: all three)",
    )
    demo.add_argument("--loop", action="store_true", help="repeat until Ctrl-C")
    demo.add_argument("--interval", type=float, default=0.5, help="seconds between printouts")
    demo.set_defaults(handler=demo_command)


def demo_command(args: argparse.Namespace) -> int:
    """`arena demo`."""
    trio.run(run_demo, args.sequence or list(demo_sequences()), args.loop, args.interval)
    return 0


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
