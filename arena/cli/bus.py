"""The servo bus: `sim-bus` (a simulated bus on a pty) and `calibrate` (a real arm)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from arena.cli.common import Commands


def add(commands: Commands) -> None:
    """Declare `sim-bus` and `calibrate`."""
    sim_bus = commands.add_parser(
        "sim-bus", help="a simulated servo bus (Feetech or Dynamixel, as the type's) on a pty"
    )
    sim_bus.add_argument(
        "--link", default="/tmp/arena-sim-bus", help="path of the port (a symlink to the pty)"
    )
    sim_bus.add_argument(
        "--ids",
        type=servo_ids,
        default=None,
        help="servo ids, comma-separated (default: the type's)",
    )
    sim_bus.add_argument(
        "--robot-type", default="so-arm100", help=f"whose servos to simulate: {_types()}"
    )
    sim_bus.add_argument(
        "--wire-time", action="store_true", help="answer as slowly as a real wire at --baud"
    )
    sim_bus.add_argument("--baud", type=int, default=None, help="(default: the type's)")
    sim_bus.add_argument(
        "--control",
        type=control_port,
        default=None,
        metavar="PORT",
        help="move joints by hand: JSON lines on 127.0.0.1:PORT (0: any free port)",
    )
    sim_bus.add_argument(
        "--keys", action="store_true", help="move joints by single keys in this terminal"
    )
    sim_bus.add_argument(
        "--calibration",
        default=None,
        help="the arm's calibration file (Arena's or LeRobot's), for --control's values",
    )
    sim_bus.set_defaults(handler=sim_bus_command)
    calibrate = commands.add_parser("calibrate", help="calibrate an arm on a servo bus")
    calibrate.add_argument("--port", help="serial port (default: find the adapter by USB id)")
    calibrate.add_argument("--baud", type=int, default=None, help="(default: the type's)")
    calibrate.add_argument("--robot-type", default="so-arm100", help=f"the arm's type: {_types()}")
    calibrate.add_argument(
        "--out", default="calibration/robot.json", help="calibration file to write"
    )
    calibrate.add_argument(
        "--write-homing", action="store_true", help="also store the offsets in the servos"
    )
    calibrate.add_argument(
        "--format",
        choices=("arena", "lerobot"),
        default="arena",
        help="file format: Arena's, or LeRobot's (read by LeRobot and by Arena)",
    )
    calibrate.set_defaults(handler=calibrate_command)


def _types() -> str:
    """The robot types there are, for a `--robot-type` help line."""
    from arena.robot.model import TYPES_PATH_ENV, list_robot_types

    return f"{', '.join(list_robot_types())} (default so-arm100; more from ${TYPES_PATH_ENV})"


def servo_ids(text: str) -> tuple[int, ...]:
    """`--ids 1,2,3`: servo ids 0-253."""
    try:
        ids = tuple(int(part) for part in text.split(",") if part.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not servo ids such as 1,2,3") from None
    if not ids or not all(0 <= i <= 253 for i in ids):
        raise argparse.ArgumentTypeError(f"{text!r}: servo ids are 0 to 253")
    return ids


def control_port(text: str) -> int:
    """`--control PORT`: 0 (any free port) to 65535."""
    try:
        port = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a port number") from None
    if not 0 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"{text!r}: a port is 0 to 65535")
    return port


def sim_bus_command(args: argparse.Namespace) -> int:
    """`arena sim-bus`: serve the simulated bus until Ctrl-C."""
    from arena.drivers.servo_arm import family_of, simulated_bus
    from arena.robot.model import load_robot_model
    from arena.servo import terminal

    model = load_robot_model(args.robot_type)
    family = family_of(model)
    bus = simulated_bus(model, args.ids)
    baud = args.baud or model.bus.baud_rate or family.default_baud
    keys = args.keys and sys.stdin.isatty()
    if args.keys and not keys:
        print("--keys needs a terminal (stdin is not one): no keys", file=sys.stderr)
    calibration = None
    if args.calibration:
        from arena.servo.lerobot_calibration import load_calibration

        calibration = load_calibration(Path(args.calibration), model, family)
    terminal.serve_sim_bus(
        Path(args.link),
        bus,
        args.wire_time,
        baud,
        model=model,
        control_port=args.control,
        calibration=calibration,
        keys=keys,
    )
    return 0


def calibrate_command(args: argparse.Namespace) -> int:
    """`arena calibrate`: the interactive calibration of an arm on a real bus (or a simulated
    one, waited for as an arm's bus waits)."""
    from arena.drivers.servo_arm import family_of, open_family_bus
    from arena.protocol.errors import ArenaError, ErrorCode
    from arena.robot.model import load_robot_model
    from arena.servo import terminal
    from arena.servo.ports import find_adapter

    model = load_robot_model(args.robot_type)
    family = family_of(model)
    if not family.wraps and args.write_homing:
        # Said before the user poses anything: see specs/servo-bus.md.
        raise ArenaError(
            ErrorCode.INVALID_CONFIG,
            f"{family.name} servos count turns: their offsets stay in the calibration file "
            "(leave out --write-homing).",
        )
    try:
        port = args.port or find_adapter(family.adapters)
    except ArenaError as error:
        raise ArenaError(error.code, f"{error.message} (--port PATH)") from None
    bus = open_family_bus(family, port, args.baud or model.bus.baud_rate or family.default_baud)
    bus.open()
    try:
        terminal.calibrate_interactively(
            bus,
            {joint.name: joint.servo_id for joint in model.joints},
            Path(args.out),
            robot_type=args.robot_type,
            write_homing=args.write_homing,
            lerobot_model=model if args.format == "lerobot" else None,
        )
    finally:
        bus.close()
    return 0
