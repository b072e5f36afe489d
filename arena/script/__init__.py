"""Scripts as masters (specs/scripts.md): a Python script run in a worker process of its own
drives one robot through this module's calls, every command through every rule.

    from arena.script import move_to_pose, gripper, wait

    move_to_pose([0.2, 0.0, 0.15])
    gripper("close")
    wait(0.5)
"""

from arena.script.api import (
    ScriptError,
    gripper,
    joints,
    move,
    move_joints,
    move_to_pose,
    paused,
    pose,
    wait,
)

__all__ = [
    "ScriptError",
    "gripper",
    "joints",
    "move",
    "move_joints",
    "move_to_pose",
    "paused",
    "pose",
    "wait",
]
