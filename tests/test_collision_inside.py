"""The collision guard when the arm is measured where the model says it collides (issue 57): a
move that increases the clearance it lacks is let out, every target on the way checked; a move
that decreases it, or brings another part into something, is refused with the signed
clearances in the sentence. The core's rules, on the Koch's model (its hand put in the table
by a measured pose)."""

from __future__ import annotations

import re

from arena.protocol.errors import ErrorCode
from arena.robot import collision, collision_inside
from arena.robot.core import RobotCore
from arena.robot.model import load_robot_model
from arena.robot.motion import Command

MODEL = load_robot_model("koch")
GUARD = collision.for_model(MODEL)
#: A pose the Koch's model puts the hand about 6 cm into the table at.
INSIDE = {
    "shoulder_pan": 0.0,
    "shoulder_lift": -20.0,
    "elbow_flex": 30.0,
    "wrist_flex": -40.0,
    "wrist_roll": 0.0,
    "gripper": 50.0,
}


def urdf(degrees: dict[str, float]) -> dict[str, float]:
    return {j.urdf_name: j.to_urdf(degrees[j.name]) for j in MODEL.joints}


def clearances(degrees: dict[str, float]) -> dict[str, float]:
    assert GUARD is not None
    found = collision_inside.clearances(GUARD, urdf(degrees), MODEL.workspace)
    return {str(hit): gap for hit, gap in found.items()}


def measured_inside() -> RobotCore:
    """A core whose arm reported `INSIDE` and was adopted there."""
    core = RobotCore(MODEL, 0.0)
    core.slave_attached("arm", measures=True)
    changes = core.slave_measured("arm", INSIDE, 0.0)
    assert next(c.change for c in changes) == "adopted"
    return core


def drive(core: RobotCore, values: dict[str, float], now: float) -> list[dict[str, float]]:
    """Every target the core emits for a command until its motion ends (or it is refused)."""
    result, step = core.command(None, Command.of(values), now)
    emitted = [step.targets] if step.targets else []
    t = now
    while result.accepted and (due := core.next_tick(t)) is not None:
        t = due
        if targets := core.tick(t):
            emitted.append(targets)
    return emitted


def test_the_pose_collides_in_the_model() -> None:
    gaps = clearances(INSIDE)
    assert -0.08 < gaps["hand and floor"] < -0.03
    assert min(gaps.values()) == gaps["hand and floor"]


def test_a_move_deeper_in_is_refused_saying_the_clearance_decreases() -> None:
    core = measured_inside()
    before = clearances(INSIDE)["hand and floor"]
    result, step = core.command(None, Command.of({"shoulder_lift": -25.0}), 1.0)
    assert not result.accepted and result.code is ErrorCode.COLLISION and step.targets is None
    assert "already collides" in result.message and "decreases" in result.message
    assert "shoulder_lift" in result.message and "hand and floor" in result.message
    # From where it is to the first pose checked on the way where it is smaller.
    numbers = [float(n) for n in re.findall(r"([+-]\d+\.\d) mm", result.message)]
    after = clearances({**INSIDE, "shoulder_lift": -25.0})["hand and floor"]
    assert numbers[0] == round(before * 1000, 1)
    assert round(after * 1000, 1) <= numbers[1] < numbers[0] < 0
    assert core.motion.goals == INSIDE  # nothing changed


def test_a_move_out_is_accepted_and_every_target_on_the_way_gains_clearance() -> None:
    core = measured_inside()
    goal = {"shoulder_lift": 10.0, "elbow_flex": 0.0}
    result, _ = core.command(None, Command.of(goal), 1.0)
    assert result.accepted, result.message
    assert result.message.startswith("out of a collision in the model: hand and floor -")
    core = measured_inside()
    emitted = drive(core, goal, 1.0)
    assert emitted and core.collision_stops == 0
    assert {name: emitted[-1][name] for name in goal} == goal  # all the way out
    last = clearances(INSIDE)
    for targets in emitted:
        gaps = clearances(targets)
        for hit, gap in gaps.items():
            assert gap >= 0 or gap >= last[hit] - 1e-6, (hit, gap, last[hit])
        last = gaps
    assert min(last.values()) > 0  # out of every collision


def test_a_move_that_keeps_the_clearance_is_accepted() -> None:
    """A turn about the vertical leaves every height as it was: the arm in the table may pan
    (a real arm the model is slightly off for must not be stuck)."""
    core = measured_inside()
    result, _ = core.command(None, Command.of({"shoulder_pan": 5.0}), 1.0)
    assert result.accepted, result.message
    assert "out of a collision in the model" in result.message


def test_a_move_out_that_brings_another_part_into_something_is_refused() -> None:
    """A keep-out box beside the arm: leaving the table by swinging the hand into the box is
    refused, naming the box and the clearance it would lose."""
    from arena.robot.workspace import Box, Workspace

    core = measured_inside()
    assert GUARD is not None
    lifted = urdf({**INSIDE, "shoulder_lift": 10.0, "elbow_flex": 0.0})
    hand = GUARD.kinematics.link_poses(lifted)["hand"][1]
    box = Box(
        "camera",
        (hand[0] - 0.02, hand[1] - 0.02, hand[2] - 0.02),
        (
            hand[0] + 0.02,
            hand[1] + 0.02,
            hand[2] + 0.02,
        ),
    )
    core.workspace = Workspace(floor=0.0, margin=0.005, keep_out=(box,))
    result, _ = core.command(None, Command.of({"shoulder_lift": 10.0, "elbow_flex": 0.0}), 1.0)
    assert not result.accepted and result.code is ErrorCode.COLLISION
    assert "camera" in result.message and "decreases" in result.message
