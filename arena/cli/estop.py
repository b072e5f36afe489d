"""`arena estop-test`: stop a robot every way it can be stopped, and time each stop."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from arena.cli.common import Commands

if TYPE_CHECKING:
    from arena.estop_test.analysis import Trial


def add(commands: Commands) -> None:
    """Declare `estop-test`."""
    stop = commands.add_parser(
        "estop-test", help="stop a robot every way it can be stopped, and time each stop"
    )
    stop.add_argument("--url", help="the server, e.g. http://127.0.0.1:8080")
    stop.add_argument("--robot", help="the robot to stop (it must have a slave that moves)")
    stop.add_argument("--trials", type=int, default=5, help="trials per stop path (5)")
    stop.add_argument(
        "--paths",
        help="comma-separated stop paths (default: all; heartbeat only if the server drops a "
        "silent master within 10 s, global, which stops every robot of the server, only if the "
        "robot is its only one): rest, global, master-message, master-cut, heartbeat, "
        "slave-error, group",
    )
    stop.add_argument("--api-key", help="an API key, if the server has keys")
    stop.add_argument("--joint", help="the joint to sweep (default: the robot's first)")
    stop.add_argument(
        "--settle", type=float, default=3.0, help="seconds at most for the arm to come to rest"
    )
    stop.add_argument(
        "--threshold", type=float, default=0.5, help="degrees within which a joint is at rest"
    )
    stop.add_argument("--json", help="write every figure and trial to this file")
    stop.add_argument(
        "--plot", help="draw position against time around each stop (needs matplotlib)"
    )
    stop.add_argument("--limits", help="a TOML file of limits; a breach exits with 1")
    stop.add_argument(
        "--offline", metavar="FILE", help="check a recording's e-stops instead of a server"
    )
    stop.set_defaults(handler=estop_test_command)


def estop_test_command(args: argparse.Namespace) -> int:
    """`arena estop-test`: the trials (live or from a recording), their table, the breaches
    of `--limits` (exit 1), and the JSON and plot asked for; 2 if it cannot run."""
    from arena.estop_test import report
    from arena.estop_test.analysis import load_limits

    try:
        limits = load_limits(Path(args.limits)) if args.limits else {}
    except (OSError, ValueError) as exc:
        print(f"arena estop-test: limits {args.limits}: {exc}", file=sys.stderr)
        return 2
    if args.plot:  # before the test, not after it
        from arena.extras import require

        require("plot", "arena estop-test --plot")
    found = _offline_trials(args) if args.offline else _live_trials(args)
    if found is None:
        return 2
    results, notes = found
    print(report.table(results))
    breaches = report.check(results, limits)
    for breach in breaches:
        print(f"BREACH {breach}")
    if args.json:
        report.write_json(Path(args.json), report.as_json(results, breaches, notes))
    if args.plot and results:
        print(report.plot(results, Path(args.plot)))
    return 1 if breaches else 0


Found = tuple[dict[str, list["Trial"]], list[str]]


def _offline_trials(args: argparse.Namespace) -> Found | None:
    """The e-stops of the recording `--offline` as trials (None: reported, cannot run)."""
    from arena.estop_test.analysis import recorded_stops
    from arena.protocol.errors import ArenaError
    from arena.recording.mcap_file import read_recording

    try:
        recording = read_recording(args.offline)
    except ArenaError as error:
        print(f"arena estop-test: {error.message}", file=sys.stderr)
        return None
    found = recorded_stops(
        recording.messages, threshold=args.threshold, window=max(args.settle, 0.5)
    )
    results = {trial.path: [trial] for trials in found.values() for trial in trials}
    if not results:
        print(f"arena estop-test: no e-stop in {args.offline}")
    return results, []


def _live_trials(args: argparse.Namespace) -> Found | None:
    """The trials of a test against the server `--url` (None: reported, cannot run)."""
    import httpx

    from arena.estop_test.live import EStopTestError, Settings, run

    if not args.url or not args.robot:
        print("arena estop-test: give --url and --robot (or --offline FILE)", file=sys.stderr)
        return None
    settings = Settings(
        url=args.url,
        robot=args.robot,
        trials=args.trials,
        paths=tuple(p.strip() for p in (args.paths or "").split(",") if p.strip()),
        api_key=args.api_key,
        settle=args.settle,
        threshold=args.threshold,
        joint=args.joint,
    )
    try:
        results, notes = run(settings)
    except EStopTestError as exc:
        print(f"arena estop-test: {exc}", file=sys.stderr)
        return None
    except (OSError, httpx.TransportError) as exc:
        print(f"arena estop-test: cannot reach --url {args.url}: {exc}", file=sys.stderr)
        return None
    except httpx.HTTPError as exc:
        print(f"arena estop-test: {exc}", file=sys.stderr)
        return None
    for note in notes:
        print(f"note: {note}")
    return results, notes
