"""The commands on recordings: `inspect`, `timeline`, `export`, `import-dataset`, `recover`,
`plot`, `replay` (the LeRobot ones in `arena.cli.datasets`)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from arena.cli import datasets
from arena.cli.common import Commands

if TYPE_CHECKING:
    from arena.recording.mcap_file import Recording

#: Entries of a kind `arena inspect` lists before it only counts the rest (`--json`: all).
LISTED = 5


def add(commands: Commands) -> None:
    """Declare the commands on recordings."""
    inspect = commands.add_parser("inspect", help="summarize a recording")
    inspect.add_argument("file")
    inspect.add_argument("--json", action="store_true", help="print the summary as JSON")
    inspect.set_defaults(handler=inspect_command)
    timeline = commands.add_parser("timeline", help="a recording's events in order")
    timeline.add_argument("file")
    timeline.add_argument("--robot")
    timeline.add_argument("--from", dest="start", type=float, help="seconds from the start")
    timeline.add_argument("--to", dest="end", type=float, help="seconds from the start")
    timeline.set_defaults(handler=timeline_command)
    export = commands.add_parser(
        "export",
        help="a recording as CSV, JSON lines or a ROS 2 bag, or recordings as a LeRobot dataset",
    )
    export.add_argument("file", nargs="+", help="one file (csv, jsonl); one or more (lerobot)")
    export.add_argument("--format", choices=["csv", "jsonl", "lerobot", "ros2"], default="jsonl")
    export.add_argument("--topic", help="csv, jsonl: only this topic")
    export.add_argument("--robot", help="lerobot: the recorded robot (default: the only one)")
    export.add_argument(
        "-o", "--output", help="lerobot: the dataset's folder (new or empty); ros2: a new .mcap"
    )
    export.add_argument("--fps", type=int, default=30, help="lerobot: frames a second")
    export.add_argument("--repo-id", help="lerobot: the dataset's name (default arena/ROBOT)")
    export.add_argument("--slave", help="lerobot: whose joint states are the observation")
    export.add_argument(
        "--corrections-only",
        action="store_true",
        help="lerobot: each intervention's correction as an episode of its own, nothing else",
    )
    export.add_argument(
        "--task", default="teleoperation", help="lerobot: the task of a file with no episodes"
    )
    export.set_defaults(handler=export_command)
    datasets.add_import(commands)
    recover = commands.add_parser("recover", help="rewrite a truncated recording completely")
    recover.add_argument("file")
    recover.add_argument("-o", "--output", help="default: FILE with .recovered.mcap")
    recover.set_defaults(handler=recover_command)
    plot = commands.add_parser("plot", help="plot a robot's joints from a recording")
    plot.add_argument("file")
    plot.add_argument("--robot", help="the recorded robot (default: the only one)")
    plot.add_argument("-o", "--output", required=True, help="image file (.png, .svg, .pdf)")
    plot.set_defaults(handler=plot_command)
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
    replay.add_argument(
        "--takeover", action="store_true", help="replace the robot's master if it has one"
    )
    replay.set_defaults(handler=replay_command)


def open_recording(file: str) -> Recording:
    """Read `file` for a command: refused if it holds no Arena topics; a note on stderr if it
    is still being written or was cut short."""
    from arena.protocol.errors import ArenaError, ErrorCode
    from arena.recording.mcap_file import read_recording

    recording = read_recording(file)
    if not recording.messages and recording.foreign_topics:
        raise ArenaError(
            ErrorCode.INVALID_RECORDING,
            f"{file} holds no Arena topics (only other MCAP data).",
        )
    if recording.in_progress:
        print(
            f"note: {Path(file).name} is in progress (still being written): "
            "read up to its last complete record",
            file=sys.stderr,
        )
    elif recording.truncated:
        print(
            f"note: {Path(file).name} is truncated (its writer stopped before the end): "
            "read every complete record; `arena recover` rewrites it whole",
            file=sys.stderr,
        )
    return recording


def inspect_command(args: argparse.Namespace) -> int:
    """`arena inspect`: a summary, as text or JSON."""
    import json

    from arena.recording import analysis

    summary = analysis.summarize(open_recording(args.file))
    print(json.dumps(summary, indent=2) if args.json else format_summary(summary))
    return 0


def timeline_command(args: argparse.Namespace) -> int:
    """`arena timeline`: the events in order, of one robot or all."""
    from arena.recording import analysis
    from arena.recording.replay import pick_robot

    recording = open_recording(args.file)
    robot = None if args.robot is None else pick_robot(recording, args.robot)
    lines = analysis.timeline(recording, robot, args.start, args.end)
    if lines:
        print("\n".join(lines))
    elif recording.messages:  # (an empty window printed nothing, as if the file were empty)
        origin = min(m.log_time for m in recording.messages)
        times = [
            (m.log_time - origin) / 1e9 for m in recording.messages if robot in (None, m.robot_id)
        ]
        whose = "any robot" if robot is None else f"robot {robot!r}"
        window = f"from {args.start or 0:g} s to " + (
            "the end" if args.end is None else f"{args.end:g} s"
        )
        span = f"{min(times):.3f}-{max(times):.3f} s" if times else "nothing"
        print(f"note: no record of {whose} {window}; its records span {span}", file=sys.stderr)
    return 0


def export_command(args: argparse.Namespace) -> int:
    """`arena export`: one file as CSV or JSON lines, or files as a LeRobot dataset."""
    from arena.protocol.errors import ArenaError, ErrorCode
    from arena.recording import analysis

    if args.format == "lerobot":
        return datasets.export_lerobot(args)
    if len(args.file) > 1:
        raise ArenaError(ErrorCode.INVALID_VALUE, "csv, jsonl and ros2 take one file.")
    file = args.file[0]
    if args.format == "ros2":
        return export_ros2(file, args.output)
    recording = open_recording(file)
    topics = {m.topic for m in recording.messages}
    if args.topic is not None and args.topic not in topics:
        raise ArenaError(
            ErrorCode.INVALID_VALUE,
            f"{Path(file).name} has no topic {args.topic!r} (--topic); it has {sorted(topics)}.",
        )
    sys.stdout.write(analysis.export(recording, args.format, args.topic))
    return 0


def export_ros2(file: str, output: str | None) -> int:
    """`arena export FILE --format ros2 -o OUT.mcap`: the recording as a ROS 2 bag."""
    from arena.extras import require
    from arena.protocol.errors import ArenaError, ErrorCode

    if output is None:
        raise ArenaError(ErrorCode.INVALID_VALUE, "--format ros2 needs -o OUT.mcap.")
    require("ros2", "A ROS 2 bag (--format ros2)")
    from arena.ros2.bag import export_bag

    counts = export_bag(open_recording(file), Path(output))
    for topic, count in counts.items():
        print(f"{topic}: {count}")
    return 0


def recover_command(args: argparse.Namespace) -> int:
    """`arena recover`: every complete record of a cut-short file, written whole."""
    from arena.recording.mcap_file import write_recording

    recording = open_recording(args.file)
    output = Path(args.output or str(Path(args.file).with_suffix("")) + ".recovered.mcap")
    count = write_recording(recording, output)
    print(
        f"wrote {count} messages to {output} ({len(recording.messages)} Arena records, "
        f"{len(recording.views)} of Foxglove's view)"
    )
    return 0


def plot_command(args: argparse.Namespace) -> int:
    """`arena plot`: a robot's joints drawn to an image file."""
    from arena.recording.plot import plot_recording
    from arena.recording.replay import pick_robot

    recording = open_recording(args.file)
    print(plot_recording(recording, pick_robot(recording, args.robot), Path(args.output)))
    return 0


def replay_command(args: argparse.Namespace) -> int:
    """`arena replay`: a robot's recorded commands sent to a server's master WebSocket."""
    from functools import partial

    import trio
    from trio_websocket import HandshakeError

    from arena.protocol.errors import ArenaError, ErrorCode
    from arena.recording.client_replay import replay_to_server
    from arena.recording.replay import pick_robot, recorded_commands

    recording = open_recording(args.file)
    source = pick_robot(recording, args.robot)
    commands = recorded_commands(recording, source, args.start, args.end)
    url = args.to
    if args.takeover:  # the master WebSocket's own way to ask
        url += ("&" if "?" in url else "?") + "takeover=1"
    try:
        sent, refused = trio.run(
            partial(replay_to_server, url, commands, speed=args.speed, loop=args.loop)
        )
    except (OSError, HandshakeError) as exc:
        reason = str(exc.__cause__ or exc) or type(exc).__name__
        raise ArenaError(
            ErrorCode.REMOTE_UNREACHABLE, f"cannot reach --to {args.to}: {reason}"
        ) from None
    except ArenaError as error:
        if error.code is ErrorCode.MASTER_ACTIVE:
            raise ArenaError(
                error.code,
                f"the robot has a master: pass --takeover to replace it (server: {error.message})",
            ) from None
        raise
    print(f"sent {sent} commands, {refused} refused")
    return 0


def format_summary(summary: dict[str, Any]) -> str:
    """`arena inspect`'s text: the file, its robots and topics, then gaps, e-stops, faults,
    actions and episodes (the first LISTED of each)."""
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
        rate = info["rate_hz"]
        # (one message, or all at one instant: no rate to speak of)
        said = "" if rate is None else f"  {rate} Hz"
        lines.append(f"topic      {name:<36} {info['count']:>8} msgs{said}")
    if "gaps" in summary:
        lines.append(f"gaps       {len(summary['gaps'])} ({GAP_MEANING})")
    if summary.get("users"):
        lines.append(f"users      {', '.join(summary['users'])}")
    for key in ("gaps", "estops", "faults", "audit", "episodes"):
        entries: list[dict[str, Any]] = summary.get(key, [])
        if key != "gaps" and entries:
            lines.append(f"{key:<10} {len(entries)}")
        label = "action" if key == "audit" else key[:-1]
        for entry in entries[:LISTED]:
            lines.append(f"  {label:<8} " + " ".join(f"{k}={v}" for k, v in entry.items()))
        if len(entries) > LISTED:
            lines.append(f"  ... and {len(entries) - LISTED} more (--json lists every one)")
    return "\n".join(lines)
