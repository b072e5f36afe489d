"""`arena policy DIR --url ... --robot ID`: run a LeRobot policy on this machine as the master
of a robot on an Arena server (specs/policy.md)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from arena.cli.common import Commands


def add(commands: Commands) -> None:
    """Declare `policy`."""
    policy = commands.add_parser(
        "policy", help="run a LeRobot policy here as the master of a robot on a server"
    )
    policy.add_argument("path", help="the policy's directory (saved by LeRobot 0.4)")
    policy.add_argument("--url", required=True, help="the server, e.g. http://robot-pc:8080")
    policy.add_argument("--robot", required=True, help="the robot to drive")
    policy.add_argument("--api-key", help="an API key, if the server has keys")
    policy.add_argument("--task", default="", help="the task, for policies that take one")
    policy.add_argument("--fps", type=float, default=30.0, help="control steps a second (30)")
    policy.add_argument(
        "--max-relative-target",
        type=float,
        default=10.0,
        help="the step limit: degrees from the measured position (10; 0: off)",
    )
    policy.add_argument(
        "--takeover", action="store_true", help="displace the robot's master, if it has one"
    )
    policy.set_defaults(handler=policy_command)


def policy_command(args: argparse.Namespace) -> int:
    """Run until the robot stops the policy (e-stop, takeover) or its worker ends; 2 if the
    policy cannot run on that robot."""
    import trio

    from arena.client.errors import ArenaClientError
    from arena.extras import require
    from arena.policy.master import PolicySettings
    from arena.policy.remote import run_remote
    from arena.protocol.errors import ArenaError

    require("lerobot", "arena policy")
    settings = PolicySettings(
        path=Path(args.path),
        task=args.task,
        fps=args.fps,
        max_relative_target=args.max_relative_target or None,
    )
    try:
        master = trio.run(run_remote, settings, args.url, args.robot, args.api_key, args.takeover)
    except (ArenaError, ArenaClientError) as error:
        print(f"arena policy: {error.code}: {error.message}", file=sys.stderr)
        return 2
    counters = master.counters
    print(
        f"{master.identity}: {counters.sent} commands, {counters.inferences} inferences, "
        f"{counters.clamped} targets clamped, {counters.invalid} actions refused, "
        f"{counters.stalls} stalls"
    )
    return 0
