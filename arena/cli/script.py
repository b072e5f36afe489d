"""`arena script FILE --url ... --robot ID`: run a Python script on this machine as the master of
a robot on an Arena server (specs/scripts.md)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from arena.cli.common import Commands


def add(commands: Commands) -> None:
    """Declare `script`."""
    script = commands.add_parser(
        "script", help="run a Python script here as the master of a robot on a server"
    )
    script.add_argument("file", help="the script (it drives the robot with arena.script's calls)")
    script.add_argument("--url", required=True, help="the server, e.g. http://robot-pc:8080")
    script.add_argument("--robot", required=True, help="the robot to drive")
    script.add_argument("--api-key", help="an API key, if the server has keys")
    script.add_argument(
        "--takeover", action="store_true", help="displace the robot's master, if it has one"
    )
    script.set_defaults(handler=script_command)


def script_command(args: argparse.Namespace) -> int:
    """Run the script until it ends or the robot ends it; 0 if it finished, 1 if it failed
    (its file and line printed) or the robot let it go, 2 if it could not start."""
    import trio

    from arena.client.errors import ArenaClientError
    from arena.protocol.errors import ArenaError
    from arena.script.master import ScriptSettings
    from arena.script.remote import run_remote

    path = Path(args.file)
    if not path.is_file():
        print(f"arena script: no file {args.file}", file=sys.stderr)
        return 2
    try:
        master, _ = trio.run(
            run_remote,
            ScriptSettings(path.resolve()),
            args.url,
            args.robot,
            args.api_key,
            args.takeover,
        )
    except (ArenaError, ArenaClientError) as error:
        print(f"arena script: {error.code}: {error.message}", file=sys.stderr)
        return 2
    for line in master.lines:
        print(line)
    counters = master.counters
    print(
        f"{master.identity}: {counters.requests} requests, {counters.commands} commands "
        f"accepted, {counters.refused} refused"
    )
    if master.outcome:
        print(f"arena script: {master.outcome}", file=sys.stderr)
        return 1
    return 0
