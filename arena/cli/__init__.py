"""The `arena` command: serve robots, read and replay recordings, work the servo bus, test.

`arena serve` runs the server; `inspect`, `timeline`, `export`, `plot`, `recover`, `replay`,
`import-dataset` and `foxglove-layout` work on recordings; `calibrate` and `sim-bus` on the
servo bus; `estop-test` times every way a robot stops; `policy` runs a LeRobot policy as a
robot's master from this machine, `script` a Python script, `mcp` serves robots to
LLM agents as MCP tools; `learn` runs the whole learning loop in the physics
twin; `bench` measures; `schemas` writes the messages' JSON
Schemas; `token` mints a user's token; `demo` plays the demo sequences on a simulated arm in
this process.
A refusal is one line on stderr and exit status 2.
"""

# One module per command or small group of commands, each with `add(commands)`, which declares
# its subcommands and their handlers, and the handlers themselves (`handler(args) -> status`):
# demo, serve, recordings (inspect, timeline, export, recover, plot, replay), datasets (the
# LeRobot side of export, import-dataset), foxglove (foxglove-layout), bus (sim-bus,
# calibrate), estop (estop-test), policy (policy), script (script), mcp (mcp), learn (learn),
# tools (schemas, bench), users (token). A handler imports what it needs when it runs, so
# that `arena --help` stays quick.

from __future__ import annotations

import argparse
import logging
import os
import sys
from collections.abc import Callable

import arena
from arena.cli import (
    bus,
    demo,
    estop,
    foxglove,
    learn,
    mcp,
    policy,
    recordings,
    script,
    serve,
    tools,
    users,
)
from arena.cli.demo import format_joints, run_demo
from arena.cli.recordings import LISTED
from arena.cli.tools import BENCH_SCENARIOS

__all__ = [
    "BENCH_SCENARIOS",
    "BROKEN_PIPE_STATUS",
    "LISTED",
    "build_parser",
    "command_names",
    "format_joints",
    "main",
    "run_demo",
]

#: Exit status of a command whose reader went away (`arena inspect FILE | head`), as for a
#: program killed by SIGPIPE.
BROKEN_PIPE_STATUS = 128 + 13


def build_parser() -> argparse.ArgumentParser:
    """The `arena` command's arguments: one subcommand each."""
    parser = argparse.ArgumentParser(
        prog="arena",
        description=__doc__,
        epilog="`arena COMMAND --help` tells more; the README is the manual.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"arena {arena.__version__}")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    demo.add(commands)
    serve.add(commands)
    recordings.add(commands)
    bus.add(commands)
    foxglove.add(commands)
    estop.add(commands)
    policy.add(commands)
    script.add(commands)
    mcp.add(commands)
    learn.add(commands)
    tools.add(commands)
    users.add(commands)
    return parser


def command_names(parser: argparse.ArgumentParser) -> list[str]:
    """The subcommands of `parser`, in order."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return list(action.choices)
    return []


def main(argv: list[str] | None = None) -> int:
    """Entry point of the `arena` console script."""
    args = build_parser().parse_args(argv)  # argparse ignores a closed pipe itself
    default_level = "INFO" if args.command == "serve" else "WARNING"
    logging.basicConfig(
        level=os.environ.get("LOG_LEVEL", default_level).upper(),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    return reporting(args.command, args.handler, args)


def reporting(
    command: str, handler: Callable[[argparse.Namespace], int], args: argparse.Namespace
) -> int:
    """Run a command's handler. A refusal (`ArenaError`) is one line on stderr and exit 2; a
    reader that stops reading (`| head`) ends the command quietly; Ctrl-C exits 130."""
    from arena.protocol.errors import ArenaError

    try:
        result = handler(args)
        sys.stdout.flush()  # a closed pipe shows here, not at exit
    except ArenaError as error:
        print(f"arena {command}: {error.message}", file=sys.stderr)
        return 2
    except BrokenPipeError:
        _drop_stdout()
        return BROKEN_PIPE_STATUS
    except KeyboardInterrupt:
        return 130
    return result


def _drop_stdout() -> None:
    """Point stdout at /dev/null, so that the flush at exit finds no broken pipe to report."""
    try:
        descriptor = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):  # not a real file (a test's capture)
        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, descriptor)
    os.close(devnull)
