"""No jerk at the handover (specs/safety-state-machine.md, "Pause, resume and intervention"): a
leader arm on a simulated bus intervenes on a follower on another, the robot's running master
paused. A passive leader makes the follower travel to the leader's pose at the joining speed;
an actuated one is first driven to the follower's pose at the joining speed, then goes limp.
The speeds are measured on the targets the robot recorded and on the goals the leader was
given. These wait for events (`eventually`), never for a time to pass."""

from __future__ import annotations

import itertools
from collections.abc import Awaitable, Callable
from pathlib import Path

import pytest

from arena.robot.events import TargetsSent
from arena.robot.handle import Robot
from arena.robot.manager import RobotManager
from arena.robot.safety import Mode
from arena.servo.sim_pty import PtySimBus
from tests.conftest import RunningServer, eventually
from tests.hardware import servo_torque, usb_slave, wait_joined
from tests.test_usb_master import (
    FOLLOWER_REST,
    LEADER_REST,
    MODEL,
    calibrated_at,
    follower,  # noqa: F401 (the fixture)
    leader,  # noqa: F401 (the fixture)
    leader_arm,
    pose,
)

#: The leader is this far from the follower's pose when it intervenes (raw steps of servo 1,
#: the base: 300 steps are 26.4 degrees).
OFFSET = 300


async def follower_arm(manager: RobotManager, follower: PtySimBus, tmp_path: Path) -> Robot:  # noqa: F811
    """A robot whose follower arm, at its rest pose, has joined."""
    pose(follower, FOLLOWER_REST)
    robot = await manager.create_robot("so-arm100", robot_id="arm")
    await robot.attach_slave(
        usb_slave(follower, MODEL, calibrated_at(FOLLOWER_REST, tmp_path / "arm.json"))
    )
    await eventually(lambda: all(servo_torque(follower).values()), what="follower torque")
    await wait_joined(robot)
    return robot


async def paused_policy(manager: RobotManager, follower: PtySimBus, tmp_path: Path) -> Robot:  # noqa: F811
    """A follower at its rest pose, held by a master that stands in for a policy."""
    robot = await follower_arm(manager, follower, tmp_path)
    await robot.connect_master("policy")
    return robot


def speeds(points: list[tuple[float, dict[str, float]]], burst: float) -> list[float]:
    """Every joint's speed (deg/s) between consecutive points; `burst`: seconds added
    to each interval (0: the trajectory has no burst allowance, specs/motion.md)."""
    found = []
    for (t0, a), (t1, b) in itertools.pairwise(points):
        for name, value in b.items():
            if value != a[name]:
                found.append(abs(value - a[name]) / (t1 - t0 + burst))
    return found


async def brought_to_the_leader(
    robot: Robot,
    leader: PtySimBus,  # noqa: F811
    tmp_path: Path,
    *,
    intervene: bool,
) -> None:
    """Attach a passive leader that a hand holds `OFFSET` from the follower's pose: the
    follower travels there, never faster than the join speed (the targets the robot sent)."""
    pose(leader, {**LEADER_REST, 1: LEADER_REST[1] + OFFSET})  # the hand holds it elsewhere
    master = leader_arm(leader, calibrated_at(LEADER_REST, tmp_path / "arm-leader.json"))
    await master.prepare()
    start, far = robot.core.motion.positions["Rotation"], OFFSET * 360 / 4096
    with robot.subscribe(kinds=[TargetsSent]) as events:
        await robot.attach_master(master, intervene=intervene)
        assert robot.snapshot().mode is (Mode.INTERVENED if intervene else Mode.MASTERED)
        assert not any(servo_torque(leader).values())  # a passive leader stays limp
        await eventually(
            lambda: (
                abs(robot.core.motion.positions["Rotation"] - start) >= far * 0.9
                and robot.core.easing is None
                and not robot.core.motion.moving
            ),
            timeout=far / MODEL.safety.join_speed * 4 + 10,
            what="the follower at the leader's pose",
        )
        targets = [(e.time, e.joints) for e in events.drain() if isinstance(e, TargetsSent)]
    moved = targets[-1][1]["Rotation"] - targets[0][1]["Rotation"]
    assert abs(moved) >= far * 0.9  # it did travel to the leader's pose...
    join, burst = MODEL.safety.join_speed, 0.0
    assert max(speeds(targets, burst)) <= join + 1e-6  # ...never faster than the join speed
    assert targets[-1][0] - targets[0][0] >= abs(moved) / join - 0.1


# An intervening leader, and one attached as the robot's own master (the dashboard's "Attach
# leader arm"): either is wherever the hand holds it, and the follower once swung to the
# latter at full speed (a newcomer: 133 degrees in under 0.9 s).
@pytest.mark.parametrize("intervene", [True, False], ids=["intervening", "as-the-master"])
async def test_a_passive_leader_brings_the_follower_to_its_pose_at_the_join_speed(
    manager: RobotManager,
    leader: PtySimBus,  # noqa: F811
    follower: PtySimBus,  # noqa: F811
    tmp_path: Path,
    intervene: bool,
) -> None:
    if intervene:
        robot = await paused_policy(manager, follower, tmp_path)
    else:
        robot = await follower_arm(manager, follower, tmp_path)
    await brought_to_the_leader(robot, leader, tmp_path, intervene=intervene)


async def test_an_actuated_leader_is_driven_to_the_follower_then_goes_limp(
    manager: RobotManager,
    leader: PtySimBus,  # noqa: F811
    follower: PtySimBus,  # noqa: F811
    tmp_path: Path,
) -> None:
    robot = await paused_policy(manager, follower, tmp_path)
    held = dict(robot.joint_values()[0])
    pose(leader, {**LEADER_REST, 1: LEADER_REST[1] + OFFSET})
    master = leader_arm(
        leader, calibrated_at(LEADER_REST, tmp_path / "arm-leader.json"), actuated=True
    )
    await master.prepare()
    with robot.subscribe(kinds=[TargetsSent]) as events:
        await robot.attach_master(master, intervene=True)
        await eventually(lambda: master.approach, what="the leader on its way")
        await eventually(
            lambda: master.sent > 0 and not any(servo_torque(leader).values()),
            timeout=30,
            what="the leader at the follower's pose, limp, commanding",
        )
        await eventually(lambda: not robot.core.motion.moving, what="the follower still")
        targets = [(e.time, e.joints) for e in events.drain() if isinstance(e, TargetsSent)]
    join = MODEL.safety.join_speed
    # The leader was given goals no faster than the join speed, from where it was...
    assert max(speeds(master.approach, 0.0)) <= join + 1e-6
    start, end = master.approach[0][1], master.approach[-1][1]
    assert abs(start["Rotation"] - end["Rotation"]) >= OFFSET * 360 / 4096 * 0.9
    # ...to the follower's pose: the follower barely moves when the hand takes over.
    for _, joints in targets:
        for name, value in joints.items():
            assert abs(value - held[name]) <= 2.0, (name, value, held[name])


async def test_a_leader_arm_intervenes_over_rest_and_frees_its_port_when_handed_back(
    start_server: Callable[..., Awaitable[RunningServer]],
    leader: PtySimBus,  # noqa: F811
    tmp_path: Path,
) -> None:
    server = await start_server(calibration_dir=str(tmp_path / "calibration"))
    leader_config = {"type": "usb-master", "port": str(leader.link), "actuated": True}
    sequence = {"type": "mock-sequence", "sequences": ["gentle-wave"], "loop": True}
    async with server.client() as http:
        await http.post("/api/robots", json={"id": "arm"})
        await http.post("/api/robots/arm/slaves", json={"type": "mock-slave"})
        assert (await http.post("/api/robots/arm/master", json=sequence)).status_code == 201
        for _ in range(2):  # twice: the leader's port was freed at the hand-back
            taken = await http.post("/api/robots/arm/intervention", json={"master": leader_config})
            assert taken.status_code == 201, taken.text
            shown = (await http.get("/api/robots/arm")).json()
            assert shown["master"]["type"] == "usb-master" and shown["state"] == "intervened"
            assert shown["paused_master"]["type"] == "mock-sequence"
            busy = await http.post("/api/robots/arm/intervention", json={"master": leader_config})
            assert busy.json()["error"]["code"] == "INTERVENTION_ACTIVE"
            back = await http.request("DELETE", "/api/robots/arm/intervention")
            assert back.status_code == 200, back.text
            assert back.json()["master"]["type"] == "mock-sequence"
            assert not back.json()["master"]["paused"]
    # Limp again, its port closed. (The hand-back waits for that at most 6 s; a CI run with
    # the machine loaded by a benchmark found torque still on right after it, once, not
    # reproduced: waited for here, the limp leader is what this test holds to.)
    await eventually(
        lambda: not any(servo_torque(leader).values()), timeout=30, what="the leader limp"
    )
