"""LeRobot datasets: `export --format lerobot` and `import-dataset`."""

from __future__ import annotations

import argparse
from pathlib import Path

from arena.cli.common import Commands


def add_import(commands: Commands) -> None:
    """Declare `import-dataset` (`export`'s options are declared with the other formats')."""
    import_dataset = commands.add_parser(
        "import-dataset", help="a LeRobot dataset episode as a recording to replay"
    )
    import_dataset.add_argument("folder", help="the dataset's folder (holding meta/info.json)")
    import_dataset.add_argument("--episode", type=int, default=0)
    import_dataset.add_argument("-o", "--output", required=True, help="the MCAP file to write")
    import_dataset.add_argument("--repo-id", help="the dataset's name (default local/FOLDER)")
    import_dataset.add_argument("--robot", default="dataset-arm", help="robot id in the file")
    import_dataset.set_defaults(handler=import_dataset_command)


def export_lerobot(args: argparse.Namespace) -> int:
    """`arena export --format lerobot`: recordings of one robot as a dataset's episodes."""
    from arena.protocol.errors import ArenaError, ErrorCode
    from arena.recording.dataset import export_lerobot as export
    from arena.recording.mcap_file import read_recording
    from arena.recording.replay import pick_robot

    if not args.output:
        raise ArenaError(ErrorCode.INVALID_VALUE, "Say where the dataset goes: -o DIR.")
    paths = [Path(name) for name in args.file]
    robot = args.robot or pick_robot(read_recording(paths[0]), None)
    report = export(
        paths,
        robot,
        Path(args.output),
        fps=args.fps,
        repo_id=args.repo_id,
        slave=args.slave,
        task=args.task,
        corrections_only=args.corrections_only,
    )
    frames = sum(count for _, _, count in report.episodes)
    cameras = ", ".join(report.cameras) or "none"
    print(
        f"{report.root}: {report.repo_id}, {len(report.episodes)} episodes, {frames} frames "
        f"at {report.fps} fps, cameras: {cameras}"
    )
    if report.policies:
        print(f"  an evaluation of {', '.join(report.policies)}")
    for index, task, count in report.episodes:
        print(f"  episode {index}: {count} frames, task {task!r}")
    return 0


def import_dataset_command(args: argparse.Namespace) -> int:
    """`arena import-dataset`: one episode as a recording of commands."""
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
