"""Planned paths (`POST /api/robots/{id}/move` with `"plan": true`): around a keep-out box on
every robot type, checked by the collision guard's own model; NO_PATH for a goal inside a box;
an e-stop during a plan and during the planned move."""

from __future__ import annotations

import math
from typing import Any

import pytest
import trio

from arena.robot import collision
from arena.robot.cartesian import hand_for
from arena.robot.model import RobotModel, load_robot_model
from arena.robot.workspace import Box, Workspace
from tests.conftest import RecordingSlave, RunningServer, eventually, need

TYPES = ["so-arm100", "so-101", "koch"]


def scene(robot_type: str) -> tuple[RobotModel, dict[str, float], dict[str, float], dict[str, Any]]:
    """A start and a goal of the arm reaching out low, its pan turned 50 degrees each way, and
    a pillar where its hand passes between them (the straight way runs into it)."""
    model = load_robot_model(robot_type)
    hand = hand_for(model)
    assert hand is not None
    zero = {j.name: 0.0 for j in model.joints}
    out = hand.pose(zero)
    assert out is not None
    across = math.hypot(out.position[0], out.position[1])
    forward = (out.position[0] / across, out.position[1] / across)
    solved = hand.solve((forward[0] * 0.22, forward[1] * 0.22, 0.08), None, zero)
    assert solved.reached
    reach = {**zero, **solved.joints}
    there = hand.pose(reach)
    assert there is not None
    x, y, z = there.position
    pillar = {"name": "pillar", "min": [x - 0.03, y - 0.03, 0.0], "max": [x + 0.03, y + 0.03, z + 0.04]}
    pan = hand.joint_names[0]
    return model, {**reach, pan: reach[pan] - 50}, {**reach, pan: reach[pan] + 50}, pillar


def guard_workspace(model: RobotModel, pillar: dict[str, Any]) -> Workspace:
    box = Box(pillar["name"], tuple(pillar["min"]), tuple(pillar["max"]))  # type: ignore[arg-type]
    floor = model.workspace.floor
    return Workspace(floor=floor, keep_out=(box,), margin=model.workspace.margin)


def urdf(model: RobotModel, joints: dict[str, float]) -> dict[str, float]:
    return {j.urdf_name: j.to_urdf(joints[j.name]) for j in model.joints}


async def test_smoke(server: RunningServer) -> None:
    need("ompl", "plan")
    model, start, goal, pillar = scene("so-arm100")
    robot = server.app.manager.get("demo-arm")
    recorder = RecordingSlave()
    await robot.attach_slave(recorder)
    async with server.client() as http:
        r = await http.put("/api/robots/demo-arm/joints", json={"joints": [{"name": n, "value": v} for n, v in start.items()]})
        assert r.status_code == 200, r.text
        await eventually(lambda: not robot.core.motion.moving, what="at the start")
        r = await http.put("/api/robots/demo-arm/workspace", json={"floor": 0.0, "keep_out": [pillar]})
        assert r.status_code == 200, r.text
        straight = await http.post("/api/robots/demo-arm/move", json={"joints": goal})
        print(straight.json())
        r = await http.post("/api/robots/demo-arm/move", json={"joints": goal, "plan": True})
        print(r.json())
        assert r.status_code == 200
        await eventually(lambda: robot.snapshot().master is None, what="done")
        print(len(recorder.targets), recorder.targets[-1])
