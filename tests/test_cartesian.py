"""Poses: forward kinematics against yourdfpy's, inverse kinematics round trips on every robot
type, UNREACHABLE, and `pose` over REST and the master WebSocket of a real server."""

from __future__ import annotations

import json
import math
import random
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import trio
import yourdfpy
from trio_websocket import open_websocket_url

from arena.protocol.errors import ArenaError, ErrorCode
from arena.robot.cartesian import Hand, angle_between, hand_for
from arena.robot.model import BUILTIN_TYPES_DIR, TYPES_PATH_ENV, RobotModel, load_robot_model
from tests.conftest import RunningServer, eventually

TYPES = ["so-arm100", "so-101", "koch"]


def hand(robot_type: str) -> tuple[RobotModel, Hand]:
    model = load_robot_model(robot_type)
    found = hand_for(model)
    assert found is not None
    return model, found


def useful_pose(rng: random.Random, model: RobotModel, arm: Hand, spread: float = 0.7) -> dict:
    """Joint values (wire units) drawn from the middle `spread` of each range, the tool point
    above the table: the poses a person or an agent asks for."""
    while True:
        values = {
            j.name: (j.lower + j.upper) / 2 + rng.uniform(-spread, spread) * (j.upper - j.lower) / 2
            for j in model.joints
        }
        pose = arm.pose(values)
        assert pose is not None
        if pose.position[2] > 0.03:
            return values


@pytest.mark.parametrize("robot_type", TYPES)
def test_forward_kinematics_match_yourdfpy_on_random_joints(robot_type: str) -> None:
    model, arm = hand(robot_type)
    effector = model.end_effector
    assert effector is not None
    urdf = yourdfpy.URDF.load(
        str(model.urdf_path), load_meshes=False, build_collision_scene_graph=False
    )
    rng = random.Random(1)
    for _ in range(25):
        values = {j.name: rng.uniform(j.lower, j.upper) for j in model.joints}
        urdf.update_cfg({j.urdf_name: j.to_urdf(values[j.name]) for j in model.joints})
        frame = urdf.get_transform(effector.link, urdf.base_link)
        expected = frame @ np.array([*effector.offset, 1.0])
        pose = arm.pose(values)
        assert pose is not None
        assert np.allclose(pose.position, expected[:3], atol=1e-9)
        # The same rotation: a quaternion and its negative are one rotation.
        x, y, z, w = pose.orientation
        mine = np.array(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
            ]
        )
        assert np.allclose(mine, frame[:3, :3], atol=1e-9)
        assert pose.gripper == values[arm.gripper.name if arm.gripper else ""]


@pytest.mark.parametrize("robot_type", TYPES)
@pytest.mark.parametrize("with_orientation", [False, True])
def test_poses_round_trip_within_a_millimetre_from_varied_starts(
    robot_type: str, with_orientation: bool
) -> None:
    model, arm = hand(robot_type)
    rng = random.Random(5)
    for trial in range(30):
        goal = useful_pose(rng, model, arm)
        target = arm.pose(goal)
        assert target is not None
        # The neutral pose, near the goal, anywhere: each in turn.
        start = [
            {j.name: 0.0 for j in model.joints},
            {name: value + rng.uniform(-20, 20) for name, value in goal.items()},
            useful_pose(rng, model, arm, spread=1.0),
        ][trial % 3]
        orientation = target.orientation if with_orientation else None
        solution = arm.solve(target.position, orientation, start)
        assert solution.reached, (trial, solution)
        reached = arm.pose({**start, **solution.joints})
        assert reached is not None
        assert math.dist(reached.position, target.position) < 0.001
        if with_orientation:
            assert math.degrees(angle_between(reached.orientation, target.orientation)) < 1.0
        for name, value in solution.joints.items():
            joint = model.joint(name)
            assert joint is not None and joint.lower <= value <= joint.upper


@pytest.mark.parametrize("robot_type", TYPES)
def test_a_far_point_is_unreachable_with_the_distance_of_the_nearest(robot_type: str) -> None:
    model, arm = hand(robot_type)
    far = (1.5, 0.0, 0.3)
    solution = arm.solve(far, None, {j.name: 0.0 for j in model.joints})
    assert not solution.reached
    nearest = arm.pose(solution.joints)
    assert nearest is not None
    # The nearest pose it found is the one it says, no nearer than the arm's length allows,
    # and about as near as the best of many random poses of the arm (a local search: within a
    # few centimetres of the nearest, specs/cartesian.md).
    assert solution.distance == pytest.approx(math.dist(nearest.position, far), abs=1e-6)
    assert math.dist(far, arm.shoulder) - arm.reach <= solution.distance
    rng = random.Random(2)
    sampled = []
    for _ in range(3000):
        pose = arm.pose({j.name: rng.uniform(j.lower, j.upper) for j in model.joints})
        assert pose is not None
        sampled.append(math.dist(pose.position, far))
    assert solution.distance <= min(sampled) + 0.05


def test_an_end_effector_must_be_a_link_of_the_urdf(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    folder = tmp_path / "so-101-odd"
    shutil.copytree(BUILTIN_TYPES_DIR / "so-101", folder)
    config = folder / "robot.toml"
    config.write_text(config.read_text().replace('"gripper_frame_link"', '"fingertip"'))
    monkeypatch.setenv(TYPES_PATH_ENV, str(tmp_path))
    with pytest.raises(ArenaError) as info:
        load_robot_model("so-101-odd")
    assert info.value.code is ErrorCode.INVALID_CONFIG
    assert "'fingertip' is not a link" in info.value.message


# -- over the API ---------------------------------------------------------------------------


def target_of(robot_type: str, joints: dict[str, float]) -> list[float]:
    """The tool point (metres) at these joint values."""
    _, arm = hand(robot_type)
    model = load_robot_model(robot_type)
    pose = arm.pose({**{j.name: 0.0 for j in model.joints}, **joints})
    assert pose is not None
    return list(pose.position)


async def commanded(client: Any, robot: str) -> dict[str, Any]:
    response = await client.get(f"/api/robots/{robot}/pose")
    assert response.status_code == 200, response.text
    body: dict[str, Any] = response.json()
    return body


async def test_rest_pose_reads_moves_and_refuses_what_it_cannot_reach(
    server: RunningServer,
) -> None:
    async with server.client() as client:
        first = await commanded(client, "demo-arm")
        assert first["link"] == "gripper" and first["frame"] == "base"
        await eventually(lambda: _measured(client), what="the mock slave's first report")
        goal = target_of("so-arm100", {"Rotation": 20, "Pitch": -20, "Elbow": 25})
        response = await client.put(
            "/api/robots/demo-arm/pose", json={"position": goal, "gripper": 40, "duration": 500}
        )
        assert response.status_code == 200, response.text
        answer = response.json()
        assert answer["status"] == "accepted" and answer["distance"] < 0.0005
        pose = await commanded(client, "demo-arm")
        assert math.dist(pose["commanded"]["position"], goal) < 0.001
        assert pose["commanded"]["gripper"] == pytest.approx(40)

        async def measured_there() -> bool:
            measured = (await commanded(client, "demo-arm"))["measured"]
            return measured is not None and math.dist(measured["position"], goal) < 0.001

        await eventually(measured_there, what="the arm at the pose")

        far = await client.put("/api/robots/demo-arm/pose", json={"position": [2.0, 0.0, 0.2]})
        assert far.status_code == 422
        error = far.json()["error"]
        assert error["code"] == "UNREACHABLE" and "mm away" in error["message"]
        assert error["nearest"]["distance"] > 1.0
        now = (await commanded(client, "demo-arm"))["commanded"]
        assert math.dist(now["position"], goal) < 1e-3

        for body, code in [
            ({"position": [0.1, 0.0]}, "INVALID_BODY"),
            ({"position": [0.1, 0.0, 0.2], "orientation": [0, 0, 0, 0]}, "INVALID_VALUE"),
            ({"position": [0.1, 0.0, 0.2], "speed": 3}, "UNKNOWN_FIELD"),
            ({"position": [99.0, 0.0, 0.2]}, "INVALID_BODY"),
        ]:
            refused = await client.put("/api/robots/demo-arm/pose", json=body)
            assert refused.json()["error"]["code"] == code, (body, refused.text)


async def _measured(client: Any) -> bool:
    return (await commanded(client, "demo-arm"))["measured"] is not None


async def test_pose_as_a_master_message_is_acknowledged_and_moves_the_hand(
    server: RunningServer,
) -> None:
    goal = target_of("so-arm100", {"Rotation": -15, "Pitch": 10, "Elbow": -30, "Wrist_Pitch": 20})
    async with (
        server.client() as client,
        open_websocket_url(server.ws_url + "/ws/master/demo-arm") as ws,
    ):
        await ws.send_message(json.dumps({"type": "pose", "data": {"position": goal}}))
        ack = await _next(ws, "ack")
        assert ack["data"]["status"] == "accepted"
        now = (await commanded(client, "demo-arm"))["commanded"]
        assert math.dist(now["position"], goal) < 1e-3
        # Manual control is refused while a master holds the robot, as PUT .../joints is.
        held = await client.put("/api/robots/demo-arm/pose", json={"position": goal})
        assert held.json()["error"]["code"] == "MASTER_ACTIVE"
        await ws.send_message(json.dumps({"type": "pose", "data": {"position": [0, 0, 3]}}))
        error = await _next(ws, "error")
        assert error["data"]["code"] == "UNREACHABLE"


async def _next(ws: Any, wanted: str) -> dict[str, Any]:
    with trio.fail_after(30):
        while True:
            message: dict[str, Any] = json.loads(await ws.get_message())
            if message["type"] == wanted:
                return message
