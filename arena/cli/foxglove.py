"""`arena foxglove-layout`: a Foxglove layout for Arena's robots."""

from __future__ import annotations

import argparse
from pathlib import Path

from arena.cli.common import Commands


def add(commands: Commands) -> None:
    """Declare `foxglove-layout`."""
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
    layout.set_defaults(handler=foxglove_layout_command)


def foxglove_layout_command(args: argparse.Namespace) -> int:
    """`arena foxglove-layout`: the robots named, or a recording's, written or printed."""
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
