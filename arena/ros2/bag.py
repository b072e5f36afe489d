"""A recording as a ROS 2 bag in one MCAP file (`arena export FILE --format ros2 -o OUT.mcap`).

Written by rosbags' rosbag2 writer (MCAP storage: CDR messages, `ros2msg` schemas), so
`ros2 bag info OUT.mcap`, `ros2 bag play` and Foxglove's ROS view read it. Per recorded robot
(its ROS name by `wire.NameBook`, as `arena serve --ros2` names it):

  /<name>/joint_states        sensor_msgs/msg/JointState   the slaves' reports, URDF radians
  /<name>/joint_trajectory    trajectory_msgs/msg/JointTrajectory   each accepted command: one
                              point, `time_from_start` its duration (0: at once)
  /<name>/robot_description   std_msgs/msg/String          the URDF the file holds, once
  /tf                         tf2_msgs/msg/TFMessage       frames `<name>/<link>` at each report

Each message's bag time is its MCAP log time in the recording.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path
from typing import Any

from rosbags.rosbag2 import StoragePlugin, Writer

from arena.protocol.errors import ArenaError, ErrorCode
from arena.recording.mcap_file import Recording
from arena.robot.kinematics import Kinematics
from arena.robot.model import JointSpec, RobotModel, load_robot_model
from arena.ros2 import messages, wire


class _Robot:
    """One recorded robot's topics and joints."""

    def __init__(self, name: str, model: RobotModel, urdf: str | None) -> None:
        self.name = name
        self.model = model
        self.urdf = urdf
        self.kinematics = (
            Kinematics.from_urdf(urdf) if urdf else Kinematics.from_urdf(model.urdf_path)
        )
        self.degrees: dict[str, float] = {}


def export_bag(recording: Recording, output: Path) -> dict[str, int]:
    """Write `recording` as a ROS 2 bag to `output` (a new `.mcap` file); returns the messages
    written by topic."""
    if output.exists():
        raise ArenaError(ErrorCode.INVALID_VALUE, f"{output} exists already (-o): not overwriting.")
    if output.suffix != ".mcap":
        raise ArenaError(ErrorCode.INVALID_VALUE, f"-o {output}: a ROS 2 bag here is a .mcap file.")
    names = wire.NameBook()
    robots: dict[str, _Robot] = {}
    for message in recording.messages:
        if message.robot_id not in robots:
            meta = recording.metadata.get(f"robot/{message.robot_id}", {})
            robot_type = meta.get("robot_type")
            if robot_type is None:
                raise ArenaError(
                    ErrorCode.INVALID_RECORDING,
                    f"{recording.path.name} does not say robot {message.robot_id!r}'s type.",
                )
            robots[message.robot_id] = _Robot(
                names.take(message.robot_id), load_robot_model(robot_type), meta.get("urdf")
            )
    counts: dict[str, int] = {}
    with tempfile.TemporaryDirectory(dir=output.parent) as folder:
        bag = Path(folder) / output.stem
        writer = Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP)
        writer.open()
        connections: dict[str, Any] = {}

        def write(topic: str, ros_type: str, stamp: int, data: bytes) -> None:
            if topic not in connections:
                connections[topic] = writer.add_connection(
                    topic, ros_type, typestore=messages.store()
                )
            writer.write(connections[topic], stamp, data)
            counts[topic] = counts.get(topic, 0) + 1

        start = min((m.log_time for m in recording.messages), default=0)
        for robot in robots.values():
            if robot.urdf:
                write(
                    f"/{robot.name}/robot_description",
                    messages.STRING,
                    start,
                    messages.string(robot.urdf),
                )
        for message in recording.messages:
            robot = robots[message.robot_id]
            if message.kind == "joint_states":
                robot.degrees.update(message.data["joints"])
                names_, positions, radians = _urdf(robot.model.joints, robot.degrees)
                stamp = message.log_time
                state = messages.joint_state(stamp, names_, positions)
                write(f"/{robot.name}/joint_states", messages.JOINT_STATE, stamp, state)
                frames = [
                    (f"{robot.name}/{joint.parent}", f"{robot.name}/{joint.child}", pose)
                    for joint, pose in robot.kinematics.joint_transforms(radians)
                ]
                write("/tf", messages.TF_MESSAGE, stamp, messages.transforms(stamp, frames))
            elif message.kind == "command" and message.data["accepted"]:
                goals = {j["name"]: float(j["value"]) for j in message.data["joints"]}
                duration = (message.data.get("duration") or 0.0) / 1000.0
                joints = [robot.model.joint(name) for name in goals]
                known = [(j, goals[name]) for j, name in zip(joints, goals, strict=True) if j]
                point = messages.trajectory(
                    message.log_time,
                    [j.urdf_name for j, _ in known],
                    [j.to_urdf(v) for j, v in known],
                    duration,
                )
                write(
                    f"/{robot.name}/joint_trajectory", messages.TRAJECTORY, message.log_time, point
                )
        writer.close()
        (written,) = Path(bag).glob("*.mcap")
        shutil.move(written, output)
    return counts


def _urdf(
    joints: tuple[JointSpec, ...], degrees: dict[str, float]
) -> tuple[list[str], list[float], dict[str, float]]:
    names, positions, radians = [], [], {}
    for joint in joints:
        value = degrees.get(joint.name)
        if value is not None:
            names.append(joint.urdf_name)
            positions.append(joint.to_urdf(value))
            radians[joint.urdf_name] = positions[-1]
    return names, positions, radians
