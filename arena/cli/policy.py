"""`arena policy DIR --url ... --robot ID`: run a LeRobot policy on this machine as the master
of a robot on an Arena server (specs/policy.md)."""

from __future__ import annotations

import argparse
import math
import os
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
        "--environment-state",
        type=_numbers,
        default=(),
        metavar="X,Y,...",
        help="observation.environment_state, for a policy that takes one (the task's state)",
    )
    policy.add_argument(
        "--policy-python",
        metavar="PATH",
        help="the Python that runs the worker (one with LeRobot and torch, e.g. your LeRobot "
        "0.6 virtualenv's bin/python); default: this one",
    )
    policy.add_argument(
        "--takeover", action="store_true", help="displace the robot's master, if it has one"
    )
    policy.set_defaults(handler=policy_command)


def _numbers(text: str) -> tuple[float, ...]:
    """Comma-separated finite numbers."""
    try:
        values = tuple(float(part) for part in text.split(",") if part.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"not numbers separated by commas: {text!r}") from None
    if not all(math.isfinite(value) for value in values):
        raise argparse.ArgumentTypeError(f"not finite numbers: {text!r}")
    return values


def policy_command(args: argparse.Namespace) -> int:
    """Run until the robot stops the policy (e-stop, takeover) or its worker ends; 2 if the
    policy cannot run on that robot."""
    import trio

    from arena.client.errors import ArenaClientError
    from arena.extras import require
    from arena.policy.master import PolicySettings
    from arena.policy.remote import run_remote
    from arena.protocol.errors import ArenaError

    if args.policy_python is None:
        require("lerobot", "arena policy")
    elif not (os.path.isfile(args.policy_python) and os.access(args.policy_python, os.X_OK)):
        print(f"arena policy: {args.policy_python} is not a program that runs", file=sys.stderr)
        return 2
    settings = PolicySettings(
        path=Path(args.path),
        task=args.task,
        fps=args.fps,
        max_relative_target=args.max_relative_target or None,
        environment_state=args.environment_state,
        python=args.policy_python,
    )
    try:
        run = trio.run(run_remote, settings, args.url, args.robot, args.api_key, args.takeover)
    except (ArenaError, ArenaClientError) as error:
        print(f"arena policy: {error.code}: {error.message}", file=sys.stderr)
        return 2
    counters = run.master.counters
    print(
        f"{run.master.identity}: {counters.sent} commands, {counters.inferences} inferences "
        f"({run.unsent} not recorded: the link was down), {counters.clamped} targets clamped, "
        f"{counters.invalid} actions refused, {counters.stalls} stalls; "
        f"{run.frames} camera frames, {run.frame_bytes / 1e3:.0f} kB"
    )
    return 0
