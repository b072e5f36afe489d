"""The `arena` command: serve robots, read and replay recordings, work the servo bus, test.

`arena serve` runs the server; `inspect`, `timeline`, `export`, `plot`, `recover`, `replay`,
`import-dataset` and `foxglove-layout` work on recordings; `calibrate` and `sim-bus` on the
servo bus; `estop-test` times every way a robot stops; `bench` measures; `schemas` writes the
messages' JSON Schemas; `demo` plays the demo sequences on a simulated arm in this process.
A refusal is one line on stderr and exit status 2.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from functools import partial
from typing import Any

import trio

import arena
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


#: `arena bench`'s scenarios (arena/bench: SCENARIOS, then LONG_SCENARIOS), named here so that
#: reading the arguments does not import the benchmarks.
BENCH_SCENARIOS = (
    *("relay", "throughput", "fleet", "estop", "flood", "recording", "replay", "core"),
    *("physics", "camera", "usb", "teleop", "soak", "versus", "nodes"),
)


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
    serve.add_argument("--api-key-file", help="API keys, one a line (kept out of `ps`)")
    serve.add_argument(
        "--viewer-key",
        action="append",
        default=[],
        dest="viewer_keys",
        help="a read-only key: GET requests and the state WebSocket only (repeatable)",
    )
    serve.add_argument(
        "--insecure",
        action="store_true",
        default=None,
        help="allow binding beyond loopback without API keys",
    )
    serve.add_argument(
        "--allow-origin",
        action="append",
        default=[],
        dest="allowed_origins",
        metavar="ORIGIN",
        help="a web page origin (scheme://host:port) that may change things (repeatable)",
    )
    serve.add_argument(
        "--allow-host",
        action="append",
        default=[],
        dest="allowed_hosts",
        metavar="NAME",
        help="a host name a loopback server answers to besides localhost (repeatable)",
    )
    serve.add_argument("--certfile", help="TLS certificate (PEM)")
    serve.add_argument("--keyfile", help="TLS private key (PEM)")
    serve.add_argument(
        "--no-record",
        action="store_false",
        dest="record",
        default=None,
        help="do not record to MCAP (recording can be started over REST)",
    )
    serve.add_argument("--recordings-dir", help="where recordings go (default recordings/)")
    serve.add_argument(
        "--no-record-foxglove",
        action="store_false",
        dest="record_foxglove",
        default=None,
        help="leave Foxglove's view (transforms, 3D model, log) out of recordings",
    )
    serve.add_argument(
        "--foxglove-port",
        type=int,
        default=None,
        metavar="PORT",
        help="serve every robot live to Foxglove on ws://HOST:PORT (0: any port)",
    )
    fleet = serve.add_argument_group("fleet (specs/fleet.md)")
    fleet.add_argument("--node", help="this server's name in a fleet (joins it over Zenoh)")
    fleet.add_argument("--fleet", help="the fleet's name (default: default)")
    fleet.add_argument(
        "--fleet-listen",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="Zenoh endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeatable)",
    )
    fleet.add_argument(
        "--fleet-connect",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="a node or router to connect to, e.g. tcp/10.0.0.2:7447 (repeatable)",
    )
    fleet.add_argument(
        "--fleet-scout", action="store_true", default=None, help="find nodes by multicast"
    )
    fleet.add_argument(
        "--fleet-zenoh-config",
        metavar="FILE",
        help="a Zenoh configuration (JSON5) to start from: TLS, access control",
    )
    inspect = commands.add_parser("inspect", help="summarize a recording")
    inspect.add_argument("file")
    inspect.add_argument("--json", action="store_true", help="print the summary as JSON")
    timeline = commands.add_parser("timeline", help="a recording's events in order")
    timeline.add_argument("file")
    timeline.add_argument("--robot")
    timeline.add_argument("--from", dest="start", type=float, help="seconds from the start")
    timeline.add_argument("--to", dest="end", type=float, help="seconds from the start")
    export = commands.add_parser(
        "export", help="a recording as CSV or JSON lines, or recordings as a LeRobot dataset"
    )
    export.add_argument("file", nargs="+", help="one file (csv, jsonl); one or more (lerobot)")
    export.add_argument("--format", choices=["csv", "jsonl", "lerobot"], default="jsonl")
    export.add_argument("--topic", help="csv, jsonl: only this topic")
    export.add_argument("--robot", help="lerobot: the recorded robot (default: the only one)")
    export.add_argument("-o", "--output", help="lerobot: the dataset's folder (new or empty)")
    export.add_argument("--fps", type=int, default=30, help="lerobot: frames a second")
    export.add_argument("--repo-id", help="lerobot: the dataset's name (default arena/ROBOT)")
    export.add_argument("--slave", help="lerobot: whose joint states are the observation")
    export.add_argument(
        "--task", default="teleoperation", help="lerobot: the task of a file with no episodes"
    )
    import_dataset = commands.add_parser(
        "import-dataset", help="a LeRobot dataset episode as a recording to replay"
    )
    import_dataset.add_argument("folder", help="the dataset's folder (holding meta/info.json)")
    import_dataset.add_argument("--episode", type=int, default=0)
    import_dataset.add_argument("-o", "--output", required=True, help="the MCAP file to write")
    import_dataset.add_argument("--repo-id", help="the dataset's name (default local/FOLDER)")
    import_dataset.add_argument("--robot", default="dataset-arm", help="robot id in the file")
    recover = commands.add_parser("recover", help="rewrite a truncated recording completely")
    recover.add_argument("file")
    recover.add_argument("-o", "--output", help="default: FILE with .recovered.mcap")
    plot = commands.add_parser("plot", help="plot a robot's joints from a recording")
    plot.add_argument("file")
    plot.add_argument("--robot", help="the recorded robot (default: the only one)")
    plot.add_argument("-o", "--output", required=True, help="image file (.png, .svg, .pdf)")
    replay = commands.add_parser("replay", help="replay a recording into a server's robot")
    replay.add_argument("file")
    replay.add_argument("--robot", help="the recorded robot whose commands to replay")
    replay.add_argument(
        "--to", required=True, help="master WebSocket URL, e.g. ws://127.0.0.1:8080/ws/master/arm"
    )
    replay.add_argument("--speed", type=float, default=1.0)
    replay.add_argument("--loop", action="store_true")
    replay.add_argument("--from", dest="start", type=float, help="seconds into the commands")
    replay.add_argument("--until", dest="end", type=float, help="seconds into the commands")
    sim_bus = commands.add_parser("sim-bus", help="a simulated STS3215 servo bus on a pty")
    sim_bus.add_argument(
        "--link", default="/tmp/arena-sim-bus", help="path of the port (a symlink to the pty)"
    )
    sim_bus.add_argument(
        "--ids", type=_servo_ids, default="1,2,3,4,5,6", help="servo ids, comma-separated"
    )
    sim_bus.add_argument(
        "--wire-time", action="store_true", help="answer as slowly as a real wire at --baud"
    )
    sim_bus.add_argument("--baud", type=int, default=1_000_000)
    calibrate = commands.add_parser("calibrate", help="calibrate an arm on a servo bus")
    calibrate.add_argument("--port", help="serial port (default: find the adapter by USB id)")
    calibrate.add_argument("--baud", type=int, default=1_000_000)
    calibrate.add_argument("--robot-type", default="so-arm100")
    calibrate.add_argument(
        "--out", default="calibration/robot.json", help="calibration file to write"
    )
    calibrate.add_argument(
        "--write-homing", action="store_true", help="also store the offsets in the servos"
    )
    layout = commands.add_parser(
        "foxglove-layout", help="a Foxglove layout: the 3D twins, a plot per joint, the log"
    )
    layout.add_argument("-o", "--output", required=True, help="layout file to write (- : stdout)")
    layout.add_argument(
        "--robot",
        action="append",
        default=[],
        dest="robots",
        help="a robot id to show (repeatable; default: those of --recording, else demo-arm)",
    )
    layout.add_argument("--recording", help="show the robots of this recording")
    layout.add_argument("--robot-type", default=None, help="whose joints to plot (so-arm100)")
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
    schemas = commands.add_parser("schemas", help="write the JSON Schemas of the wire messages")
    schemas.add_argument("--out", default="specs/schemas", help="folder to write them into")
    bench = commands.add_parser("bench", help="run the benchmarks and print medians")
    bench.add_argument("--json", help="also write the results to this file")
    bench.add_argument(
        "scenarios",
        nargs="*",
        choices=BENCH_SCENARIOS,
        metavar="SCENARIO",
        help="which (default: all but the long ones): relay throughput fleet estop flood "
        "recording replay core physics camera usb teleop; long, only when named: soak versus "
        "nodes",
    )
    bench.add_argument("--repeats", type=int, default=3)
    bench.add_argument("--fleet-robots", type=int, default=100, help="robots in fleet and soak")
    bench.add_argument("--soak-seconds", type=float, default=600.0)
    bench.add_argument("--soak-rate", type=float, default=50.0, help="commands/s per robot")
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
    handlers = {
        "serve": _serve,
        "sim-bus": _bus_command,
        "calibrate": _bus_command,
        "import-dataset": _import_dataset,
        "foxglove-layout": _foxglove_layout,
        "estop-test": _estop_test,
        "schemas": _schemas,
        "demo": _demo,
        "bench": _bench,
        **dict.fromkeys(
            ("inspect", "timeline", "export", "recover", "replay", "plot"), _recording_tool
        ),
    }
    return _reporting(args.command, handlers[args.command], args)


#: Exit status of a command whose reader went away (`arena inspect FILE | head`), as for a
#: program killed by SIGPIPE.
BROKEN_PIPE_STATUS = 128 + 13


def _reporting(command: str, handler: Any, args: argparse.Namespace) -> int:
    """Run a command's handler. A refusal (`ArenaError`) is one line on stderr and exit 2; a
    reader that stops reading (`| head`) ends the command quietly; Ctrl-C exits 130."""
    from arena.protocol.errors import ArenaError

    try:
        result: int = handler(args)
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


def _schemas(args: argparse.Namespace) -> int:
    from pathlib import Path

    from arena.schemas import write_schemas

    for path in write_schemas(Path(args.out)):
        print(path)
    return 0


def _demo(args: argparse.Namespace) -> int:
    trio.run(run_demo, args.sequence or list(demo_sequences()), args.loop, args.interval)
    return 0


def _bench(args: argparse.Namespace) -> int:
    from arena.bench import run_benchmarks

    run_benchmarks(
        args.json,
        args.scenarios or None,
        args.repeats,
        args.fleet_robots,
        args.soak_seconds,
        args.soak_rate,
    )
    return 0


def _recording_tool(args: argparse.Namespace) -> int:
    from arena.protocol.errors import ArenaError, ErrorCode

    if args.command == "export" and args.format == "lerobot":
        return _export_lerobot(args)
    if args.command == "export":
        if len(args.file) > 1:
            raise ArenaError(ErrorCode.INVALID_VALUE, "csv and jsonl take one file.")
        args.file = args.file[0]
    return _recording_command(args)


def _export_lerobot(args: argparse.Namespace) -> int:
    from pathlib import Path

    from arena.protocol.errors import ArenaError, ErrorCode
    from arena.recording.dataset import export_lerobot
    from arena.recording.mcap_file import read_recording
    from arena.recording.replay import pick_robot

    if not args.output:
        raise ArenaError(ErrorCode.INVALID_VALUE, "Say where the dataset goes: -o DIR.")
    paths = [Path(name) for name in args.file]
    robot = args.robot or pick_robot(read_recording(paths[0]), None)
    report = export_lerobot(
        paths,
        robot,
        Path(args.output),
        fps=args.fps,
        repo_id=args.repo_id,
        slave=args.slave,
        task=args.task,
    )
    frames = sum(count for _, _, count in report.episodes)
    cameras = ", ".join(report.cameras) or "none"
    print(
        f"{report.root}: {report.repo_id}, {len(report.episodes)} episodes, {frames} frames "
        f"at {report.fps} fps, cameras: {cameras}"
    )
    for index, task, count in report.episodes:
        print(f"  episode {index}: {count} frames, task {task!r}")
    return 0


def _import_dataset(args: argparse.Namespace) -> int:
    from pathlib import Path

    from arena.recording.dataset import import_lerobot

    frames = import_lerobot(
        Path(args.folder),
        args.episode,
        Path(args.output),
        repo_id=args.repo_id,
        robot_id=args.robot,
    )
    print(f"{args.output}: episode {args.episode}, {frames} commands of robot {args.robot!r}")
    return 0


def _estop_test(args: argparse.Namespace) -> int:
    from pathlib import Path

    from arena.estop_test import report
    from arena.estop_test.analysis import Trial, load_limits, recorded_stops

    try:
        limits = load_limits(Path(args.limits)) if args.limits else {}
    except (OSError, ValueError) as exc:
        print(f"arena estop-test: limits {args.limits}: {exc}", file=sys.stderr)
        return 2
    if args.plot:  # before the test, not after it
        from arena.extras import require

        require("plot", "arena estop-test --plot")
    results: dict[str, list[Trial]]
    notes: list[str] = []
    if args.offline:
        from arena.protocol.errors import ArenaError
        from arena.recording.mcap_file import read_recording

        try:
            recording = read_recording(args.offline)
        except ArenaError as error:
            print(f"arena estop-test: {error.message}", file=sys.stderr)
            return 2
        found = recorded_stops(
            recording.messages, threshold=args.threshold, window=max(args.settle, 0.5)
        )
        results = {trial.path: [trial] for trials in found.values() for trial in trials}
        if not results:
            print(f"arena estop-test: no e-stop in {args.offline}")
    else:
        import httpx

        from arena.estop_test.live import EStopTestError, Settings, run

        if not args.url or not args.robot:
            print("arena estop-test: give --url and --robot (or --offline FILE)", file=sys.stderr)
            return 2
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
            return 2
        except (OSError, httpx.TransportError) as exc:
            print(f"arena estop-test: cannot reach --url {args.url}: {exc}", file=sys.stderr)
            return 2
        except httpx.HTTPError as exc:
            print(f"arena estop-test: {exc}", file=sys.stderr)
            return 2
        for note in notes:
            print(f"note: {note}")
    print(report.table(results))
    breaches = report.check(results, limits)
    for breach in breaches:
        print(f"BREACH {breach}")
    if args.json:
        report.write_json(Path(args.json), report.as_json(results, breaches, notes))
    if args.plot and results:
        print(report.plot(results, Path(args.plot)))
    return 1 if breaches else 0


def _foxglove_layout(args: argparse.Namespace) -> int:
    from pathlib import Path

    from arena.recording.foxglove import layout
    from arena.robot.model import load_robot_model

    robots: list[str] = list(args.robots)
    robot_type = args.robot_type
    if args.recording:
        from arena.recording.mcap_file import read_recording

        recording = read_recording(args.recording)
        recorded = {
            name.removeprefix("robot/"): meta
            for name, meta in recording.metadata.items()
            if name.startswith("robot/")
        }
        robots = robots or sorted(recorded)
        robot_type = robot_type or next(
            (meta.get("robot_type") for meta in recorded.values()), None
        )
    model = load_robot_model(robot_type or "so-arm100")
    text = layout(robots or ["demo-arm"], model.joint_names)
    if args.output == "-":
        print(text)
    else:
        Path(args.output).write_text(text + "\n", encoding="utf-8")
        print(args.output)
    return 0


def _servo_ids(text: str) -> tuple[int, ...]:
    """`--ids 1,2,3`: servo ids 0-253."""
    try:
        ids = tuple(int(part) for part in text.split(",") if part.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not servo ids such as 1,2,3") from None
    if not ids or not all(0 <= i <= 253 for i in ids):
        raise argparse.ArgumentTypeError(f"{text!r}: servo ids are 0 to 253")
    return ids


def _bus_command(args: argparse.Namespace) -> int:
    from pathlib import Path

    from arena.feetech import terminal
    from arena.feetech.bus import ServoBus, find_adapter
    from arena.protocol.errors import ArenaError
    from arena.robot.model import load_robot_model

    if args.command == "sim-bus":
        terminal.serve_sim_bus(Path(args.link), args.ids, args.wire_time, args.baud)
        return 0
    model = load_robot_model(args.robot_type)
    try:
        port = args.port or find_adapter()
    except ArenaError as error:
        raise ArenaError(error.code, f"{error.message} (--port PATH)") from None
    bus = ServoBus(port, args.baud)
    bus.open()
    try:
        terminal.calibrate_interactively(
            bus,
            {joint.name: joint.servo_id for joint in model.joints},
            Path(args.out),
            robot_type=args.robot_type,
            write_homing=args.write_homing,
        )
    finally:
        bus.close()
    return 0


def _recording_command(args: argparse.Namespace) -> int:
    import json
    from pathlib import Path

    from arena.recording import analysis
    from arena.recording.mcap_file import read_recording, write_recording

    recording = read_recording(args.file)
    if not recording.messages and recording.foreign_topics:
        from arena.protocol.errors import ArenaError, ErrorCode

        raise ArenaError(
            ErrorCode.INVALID_RECORDING,
            f"{args.file} holds no Arena topics (only other MCAP data).",
        )
    if recording.in_progress:
        print(
            f"note: {Path(args.file).name} is in progress (still being written): "
            "read up to its last complete record",
            file=sys.stderr,
        )
    elif recording.truncated:
        print(
            f"note: {Path(args.file).name} is truncated (its writer stopped before the end): "
            "read every complete record; `arena recover` rewrites it whole",
            file=sys.stderr,
        )
    if args.command == "inspect":
        summary = analysis.summarize(recording)
        print(json.dumps(summary, indent=2) if args.json else _format_summary(summary))
    elif args.command == "timeline":
        from arena.recording.replay import pick_robot

        robot = None if args.robot is None else pick_robot(recording, args.robot)
        print("\n".join(analysis.timeline(recording, robot, args.start, args.end)))
    elif args.command == "export":
        topics = {m.topic for m in recording.messages}
        if args.topic is not None and args.topic not in topics:
            from arena.protocol.errors import ArenaError, ErrorCode

            raise ArenaError(
                ErrorCode.INVALID_VALUE,
                f"{Path(args.file).name} has no topic {args.topic!r} (--topic); "
                f"it has {sorted(topics)}.",
            )
        sys.stdout.write(analysis.export(recording, args.format, args.topic))
    elif args.command == "plot":
        from arena.recording.plot import plot_recording
        from arena.recording.replay import pick_robot

        print(plot_recording(recording, pick_robot(recording, args.robot), Path(args.output)))
    elif args.command == "recover":
        output = Path(args.output or str(Path(args.file).with_suffix("")) + ".recovered.mcap")
        count = write_recording(recording, output)
        print(
            f"wrote {count} messages to {output} ({len(recording.messages)} Arena records, "
            f"{len(recording.views)} of Foxglove's view)"
        )
    else:
        from trio_websocket import HandshakeError

        from arena.protocol.errors import ArenaError, ErrorCode
        from arena.recording.client_replay import replay_to_server
        from arena.recording.replay import pick_robot, recorded_commands

        source = pick_robot(recording, args.robot)
        commands = recorded_commands(recording, source, args.start, args.end)
        try:
            sent, refused = trio.run(
                partial(replay_to_server, args.to, commands, speed=args.speed, loop=args.loop)
            )
        except (OSError, HandshakeError) as exc:
            reason = str(exc.__cause__ or exc) or type(exc).__name__
            raise ArenaError(
                ErrorCode.REMOTE_UNREACHABLE, f"cannot reach --to {args.to}: {reason}"
            ) from None
        print(f"sent {sent} commands, {refused} refused")
    return 0


#: Entries of a kind `arena inspect` lists before it only counts the rest (`--json`: all).
LISTED = 5


def _format_summary(summary: dict[str, Any]) -> str:
    from arena.recording.analysis import GAP_MEANING

    state = (
        "  (in progress: still being written)"
        if summary["in_progress"]
        else "  (truncated: its writer stopped before the end)"
        if summary["truncated"]
        else ""
    )
    lines = [
        f"file       {summary['file']}{state}",
        f"messages   {summary['messages']} ({summary['arena_messages']} Arena records, "
        f"{summary['view_messages']} of Foxglove's view)",
        f"duration   {summary.get('duration_s', 0)} s",
    ]
    robots = summary["robots"]
    assert isinstance(robots, dict)
    for robot_id, info in robots.items():
        lines.append(f"robot      {robot_id} ({info['robot_type']})")
        for joint, error in info["tracking_error_deg"].items():
            lines.append(f"  max tracking error {joint:<12} {error:8.3f} deg")
    topics = summary.get("topics", {})
    assert isinstance(topics, dict)
    for name, info in topics.items():
        lines.append(f"topic      {name:<36} {info['count']:>8} msgs  {info['rate_hz']} Hz")
    if "gaps" in summary:
        lines.append(f"gaps       {len(summary['gaps'])} ({GAP_MEANING})")
    for key in ("gaps", "estops", "faults"):
        entries: list[dict[str, Any]] = summary.get(key, [])
        if key != "gaps" and entries:
            lines.append(f"{key:<10} {len(entries)}")
        for entry in entries[:LISTED]:
            lines.append(f"  {key[:-1]:<8} " + " ".join(f"{k}={v}" for k, v in entry.items()))
        if len(entries) > LISTED:
            lines.append(f"  ... and {len(entries) - LISTED} more (--json lists every one)")
    return "\n".join(lines)


def _serve(args: argparse.Namespace) -> int:
    from arena.server.config import load_config
    from arena.server.run import run_server

    config = load_config(
        args.config,
        api_key_file=args.api_key_file,
        record=args.record,
        recordings_dir=args.recordings_dir,
        record_foxglove=args.record_foxglove,
        foxglove_port=args.foxglove_port,
        host=args.host,
        port=args.port,
        demo=args.demo,
        api_keys=tuple(args.api_keys),
        viewer_keys=tuple(args.viewer_keys) or None,
        insecure=args.insecure,
        certfile=args.certfile,
        keyfile=args.keyfile,
        allowed_origins=tuple(args.allowed_origins),
        allowed_hosts=tuple(args.allowed_hosts),
        node=args.node,
        fleet=args.fleet,
        fleet_listen=tuple(args.fleet_listen) or None,
        fleet_connect=tuple(args.fleet_connect) or None,
        fleet_scout=args.fleet_scout,
        fleet_zenoh_config=args.fleet_zenoh_config,
    )
    config.check()
    trio.run(partial(run_server, config, handle_signals=True, freeze_startup_objects=True))
    return 0


if __name__ == "__main__":
    sys.exit(main())
