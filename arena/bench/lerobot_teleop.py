"""LeRobot's own teleoperation loop, for `arena bench teleop` (arena/bench/teleop.py), run in
LeRobot 0.6's Python (`make compat`), not Arena's:

    python lerobot_teleop.py FPS LEADER_PORT FOLLOWER_PORT FOLDER

What `lerobot-teleoperate` does with an SO-101 leader and follower (lerobot/scripts/
lerobot_teleoperate.py, `teleop_loop`): each frame the follower's observation, the leader's
action, the default (identity) processors, `robot.send_action`, then `precise_sleep` to the
frame rate. Calibration files matching the simulated servos are written first (in FOLDER), so
`connect()` asks nothing. The ports are Arena's simulated buses in the bench's process: their
SDK port handler is paced as Arena's own drivers' are on a simulator (arena/servo/sim_pace.py: a
simulator kept off the CPU of a loaded machine is no missed packet; a silent servo still is).
Prints `ready` once connected, runs until a line on stdin, then prints its frame count as JSON.
A failed read or write ends the loop, as it ends LeRobot's.
"""

from __future__ import annotations

import json
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # this tree's arena.servo.sim_pace

NAMES = ("shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll", "gripper")


def calibration(folder: Path, name: str) -> None:
    """A LeRobot calibration file `name`.json in `folder` matching a fresh simulated servo (no
    homing offset, limits 0-4095), which LeRobot's `is_calibrated` then accepts as it is."""
    folder.mkdir(parents=True, exist_ok=True)
    body = {
        motor: {"id": k + 1, "drive_mode": 0, "homing_offset": 0, "range_min": 0, "range_max": 4095}
        for k, motor in enumerate(NAMES)
    }
    (folder / f"{name}.json").write_text(json.dumps(body, indent=4))


def paced(bus: object, port: str) -> None:
    """Give LeRobot's bus a port handler paced on Arena's simulator (before it connects)."""
    import scservo_sdk as scs

    from arena.servo import sim_pace

    class Port(scs.PortHandler):  # type: ignore[misc]
        def __init__(self, port_name: str, timeout_margin: float) -> None:
            super().__init__(port_name)

    handler = sim_pace.paced_class(Port)(port, 0.0, lambda: sim_pace.find(port))
    bus.port_handler = handler  # type: ignore[attr-defined]
    bus.sync_reader = scs.GroupSyncRead(handler, bus.packet_handler, 0, 0)  # type: ignore[attr-defined]
    bus.sync_writer = scs.GroupSyncWrite(handler, bus.packet_handler, 0, 0)  # type: ignore[attr-defined]


def main() -> int:
    """Connect, say `ready`, run the loop until told to stop."""
    from lerobot.processor import make_default_processors
    from lerobot.robots.so_follower import SO101Follower, SO101FollowerConfig
    from lerobot.teleoperators.so_leader import SO101Leader, SO101LeaderConfig
    from lerobot.utils.robot_utils import precise_sleep

    fps, leader_port, follower_port, folder = sys.argv[1:5]
    leader_dir, follower_dir = (Path(folder) / "lerobot" / arm for arm in ("leader", "follower"))
    calibration(leader_dir, "bench")
    calibration(follower_dir, "bench")
    teleop = SO101Leader(
        SO101LeaderConfig(port=leader_port, id="bench", calibration_dir=leader_dir)
    )
    robot = SO101Follower(
        SO101FollowerConfig(port=follower_port, id="bench", calibration_dir=follower_dir)
    )
    paced(teleop.bus, leader_port)
    paced(robot.bus, follower_port)
    teleop_processor, robot_processor, _ = make_default_processors()
    teleop.connect()
    robot.connect()
    stop = threading.Event()

    def wait_for_stop() -> None:
        sys.stdin.readline()
        stop.set()

    threading.Thread(target=wait_for_stop, daemon=True).start()
    print("ready", flush=True)
    frames = 0
    try:
        while not stop.is_set():  # lerobot_teleoperate.teleop_loop, without its display
            loop_start = time.perf_counter()
            observation = robot.get_observation()
            raw_action = teleop.get_action()
            action = teleop_processor((raw_action, observation))
            robot.send_action(robot_processor((action, observation)))
            frames += 1
            precise_sleep(max(1 / int(fps) - (time.perf_counter() - loop_start), 0.0))
    finally:
        teleop.disconnect()
        robot.disconnect()
    print(json.dumps({"frames": frames}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
