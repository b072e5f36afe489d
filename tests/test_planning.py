"""Planned paths (`POST /api/robots/{id}/move` with `"plan": true`, specs/cartesian.md): around
a keep-out box on every robot type, every target sent checked by the collision guard's own
model; NO_PATH for a goal inside a box; an e-stop answered while a plan runs, and one that
stops a planned move; the move without `plan`; the timing within the joints' limits."""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
import sys
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import pytest
import trio
from trio.testing import MockClock
from trio_websocket import open_websocket_url

from arena.robot import collision, planning
from arena.robot.cartesian import hand_for
from arena.robot.events import FaultReported, NoticeKind
from arena.robot.handle import Robot
from arena.robot.model import RobotModel, load_robot_model
from arena.robot.workspace import Box, Workspace
from tests.conftest import RecordingSlave, RunningServer, eventually, need

TYPES = ["so-arm100", "so-101", "koch"]
#: A search budget (ms) no loaded machine runs out of on these scenes (p99 ~1 s, with the
#: simplifier, at a load average of 10: specs/cartesian.md): a planned move that must succeed.
GENEROUS = 8000
StartServer = Callable[..., Awaitable[RunningServer]]


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
    pillar = {
        "name": "pillar",
        "min": [x - 0.03, y - 0.03, 0.0],
        "max": [x + 0.03, y + 0.03, z + 0.04],
    }
    pan = hand.joint_names[0]
    return model, {**reach, pan: reach[pan] - 50}, {**reach, pan: reach[pan] + 50}, pillar


def boxes(model: RobotModel, *entries: dict[str, Any]) -> Workspace:
    """The workspace the server will have, for the guard's model in the test."""
    keep_out = tuple(Box(e["name"], tuple(e["min"]), tuple(e["max"])) for e in entries)
    floor, margin = model.workspace.floor, model.workspace.margin
    return Workspace(floor=floor, keep_out=keep_out, margin=margin)  # type: ignore[arg-type]


def guarded(
    model: RobotModel, pillar: dict[str, Any]
) -> tuple[collision.CollisionModel, Workspace]:
    """The guard's own model of `model` and the workspace with the pillar, as the server has."""
    guard = collision.for_model(model)
    assert guard is not None
    return guard, boxes(model, pillar)


async def keep_out(http: Any, robot: Robot, *entries: dict[str, Any]) -> None:
    """PUT the workspace with these boxes, the robot type's floor and margin kept (a PUT
    replaces the whole workspace: without them the server's guard had no table, and the
    planner could take the hand under it), and check the server's guard now has the one the
    test's own checks use (`boxes`)."""
    floor, margin = robot.model.workspace.floor, robot.model.workspace.margin
    body = {"floor": floor, "margin": margin, "keep_out": list(entries)}
    put = await http.put(f"/api/robots/{robot.robot_id}/workspace", json=body)
    assert put.status_code == 200, put.text
    assert robot.workspace == boxes(robot.model, *entries)


def urdf(model: RobotModel, joints: dict[str, float]) -> dict[str, float]:
    return {j.urdf_name: j.to_urdf(joints[j.name]) for j in model.joints}


def as_list(joints: dict[str, float]) -> dict[str, Any]:
    return {"joints": [{"name": n, "value": v} for n, v in joints.items()]}


async def arm_at(
    server: RunningServer, http: Any, robot_id: str, joints: dict[str, float]
) -> Robot:
    """The robot, moved (straight, no box yet) to `joints` and at rest there."""
    robot: Robot = server.app.manager.get(robot_id)
    answer = await http.put(f"/api/robots/{robot_id}/joints", json=as_list(joints))
    assert answer.status_code == 200, answer.text
    await eventually(lambda: not robot.core.motion.moving, what="the arm at its start")
    return robot


@pytest.mark.parametrize("robot_type", TYPES)
async def test_a_planned_move_goes_around_a_pillar_the_straight_way_runs_into(
    start_server: StartServer, robot_type: str
) -> None:
    need("ompl", "plan")
    model, start, goal, pillar = scene(robot_type)
    guard, workspace = guarded(model, pillar)
    straight = guard.path_hit(urdf(model, start), urdf(model, goal), workspace)[0]
    assert straight is not None and straight.second == "pillar"  # the scene is what it says
    server = await start_server()
    async with server.client() as http:
        made = await http.post("/api/robots", json={"robot_type": robot_type, "id": "arm"})
        assert made.status_code == 201, made.text
        robot = await arm_at(server, http, "arm", start)
        recorder = RecordingSlave()
        await robot.attach_slave(recorder)
        await keep_out(http, robot, pillar)
        # Without a plan the move is the straight way, which the guard refuses.
        refused = await http.post("/api/robots/arm/move", json={"joints": goal})
        assert refused.status_code == 422, refused.text
        assert refused.json()["error"]["code"] == "COLLISION"
        assert "pillar" in refused.json()["error"]["message"]
        body = {"joints": goal, "plan": True, "budget": GENEROUS}
        planned = await http.post("/api/robots/arm/move", json=body)
        assert planned.status_code == 200, planned.text
        answer = planned.json()
        assert answer["plan"] is True and answer["straight"] is False
        assert len(answer["waypoints"]) >= 3  # a way around, not the straight one
        await eventually(lambda: robot.snapshot().master is None, what="the planned move played")
        await eventually(lambda: not robot.core.motion.moving, what="the arm at rest")
    sent = [joints for _, joints in recorder.targets]
    assert len(sent) > 10
    for joints in sent:  # every target that went out: the guard's own model finds it clear
        assert guard.hit(urdf(model, joints), workspace) is None, joints
    assert robot.core.collision_stops == 0  # no target on the way was held back by the guard
    for name, value in goal.items():
        assert sent[-1][name] == pytest.approx(value, abs=1e-6)


async def test_a_goal_inside_a_box_has_no_path_and_says_what_it_would_hit(
    server: RunningServer,
) -> None:
    need("ompl", "plan")
    model, start, goal, _ = scene("so-arm100")
    hand = hand_for(model)
    assert hand is not None
    there = hand.pose(goal)
    assert there is not None
    x, y, z = there.position
    cup = {"name": "cup", "min": [x - 0.02, y - 0.02, 0.0], "max": [x + 0.02, y + 0.02, z + 0.02]}
    async with server.client() as http:
        await arm_at(server, http, "demo-arm", start)
        put = await http.put("/api/robots/demo-arm/workspace", json={"keep_out": [cup]})
        assert put.status_code == 200, put.text
        for goal_body in ({"joints": goal}, {"pose": {"position": [x, y, z]}}):
            answer = await http.post("/api/robots/demo-arm/move", json={**goal_body, "plan": True})
            assert answer.status_code == 422, answer.text
            error = answer.json()["error"]
            assert error["code"] == "NO_PATH", error
            assert "the goal itself" in error["message"] and "cup" in error["message"]
            assert "cup" in error["blocked"]
        assert server.app.manager.get("demo-arm").snapshot().master is None


def wall(pillar: dict[str, Any], inner: float) -> dict[str, Any]:
    """A wall from `inner` metres off the base out along the way the pillar lies, from the floor
    up 1 m: the pan cannot turn the arm across it, nor past it the other way round (its
    limits), and the arm does not fold within `inner`."""
    cx = (pillar["min"][0] + pillar["max"][0]) / 2
    assert abs(cx) < 0.01  # the so-arm100 reaches along -y
    return {"name": "wall", "min": [-0.005, -1.0, 0.0], "max": [0.005, -inner, 1.0]}


async def test_an_estop_answers_while_a_plan_runs_and_ends_the_plan(
    server: RunningServer,
) -> None:
    need("ompl", "plan")
    _, start, goal, pillar = scene("so-arm100")
    blocking = wall(pillar, 0.12)
    async with server.client() as http:
        robot = await arm_at(server, http, "demo-arm", start)
        put = await http.put("/api/robots/demo-arm/workspace", json={"keep_out": [blocking]})
        assert put.status_code == 200, put.text
        answers: list[Any] = []

        async def plan() -> None:
            body = {"joints": goal, "plan": True, "budget": 10_000}
            answers.append(await http.post("/api/robots/demo-arm/move", json=body))

        async with trio.open_nursery() as nursery:
            nursery.start_soon(plan)

            def planning_now() -> bool:
                plans = server.app.extensions.get("arena-planning")
                return plans is not None and "demo-arm" in plans.robots

            await eventually(planning_now, what="the plan running")
            # One plan at a time per robot: a second one is refused, not queued.
            second = await http.post(
                "/api/robots/demo-arm/move", json={"joints": goal, "plan": True}
            )
            assert second.status_code == 429, second.text
            assert second.json()["error"]["code"] == "LIMIT_REACHED"
            stopped = await http.post("/api/robots/demo-arm/estop", json={"reason": "stop it"})
            assert stopped.status_code == 200, stopped.text
            assert robot.snapshot().mode == "estopped"
        # The plan had 10 s and no way around the wall: it ended because of the e-stop.
        (answer,) = answers
        assert answer.status_code == 423, answer.text
        assert answer.json()["error"]["code"] == "ESTOPPED", answer.text
        assert "while its path was planned" in answer.json()["error"]["message"]
        assert robot.snapshot().master is None


async def test_an_estop_during_a_planned_move_stops_it(server: RunningServer) -> None:
    need("ompl", "plan")
    _, start, goal, pillar = scene("so-arm100")
    async with server.client() as http:
        robot = await arm_at(server, http, "demo-arm", start)
        recorder = RecordingSlave()
        await robot.attach_slave(recorder)
        await http.put("/api/robots/demo-arm/workspace", json={"keep_out": [pillar]})
        body = {"joints": goal, "plan": True, "speed": 0.05, "budget": GENEROUS}  # ~20 s long
        planned = await http.post("/api/robots/demo-arm/move", json=body)
        assert planned.status_code == 200, planned.text
        master = planned.json()["master"]
        assert robot.snapshot().master is not None
        assert robot.snapshot().master.peer_id == master  # type: ignore[union-attr]
        await eventually(lambda: len(recorder.targets) >= 5, what="the move under way")
        stopped = await http.post("/api/robots/demo-arm/estop")
        assert stopped.status_code == 200, stopped.text
        await eventually(lambda: robot.snapshot().master is None, what="the move's master gone")
    (estop_at,) = [at for at, notice in recorder.notices if notice.kind == NoticeKind.ESTOP]
    assert all(at <= estop_at for at, _ in recorder.targets)  # nothing went out after it
    last = recorder.targets[-1][1]
    pan = "Rotation"
    assert abs(last[pan] - goal[pan]) > 20  # stopped on the way, far from the goal


async def test_a_master_plans_a_move_and_plays_it_as_its_own_commands(
    server: RunningServer,
) -> None:
    need("ompl", "plan")
    model, start, goal, pillar = scene("so-arm100")
    guard, workspace = guarded(model, pillar)
    async with server.client() as http:
        robot = await arm_at(server, http, "demo-arm", start)
        recorder = RecordingSlave()
        await robot.attach_slave(recorder)
        await keep_out(http, robot, pillar)
        async with open_websocket_url(server.ws_url + "/ws/master/demo-arm?id=planner") as ws:
            move = {"type": "move", "data": {"joints": goal, "plan": True, "budget": GENEROUS}}
            await ws.send_message(json.dumps(move))
            ack = await next_of(ws, "ack")
            assert ack["data"]["status"] == "accepted" and "planned" in ack["data"]["message"]
            await eventually(
                lambda: (
                    robot.core.motion.goals["Rotation"] == pytest.approx(goal["Rotation"])
                    and not robot.core.motion.moving
                ),
                what="the arm at the goal",
            )
            assert robot.snapshot().master.peer_id == "planner"  # type: ignore[union-attr]
            # Straight back is refused (the pillar), as a command would be.
            back = {"type": "move", "data": {"joints": start}}
            await ws.send_message(json.dumps(back))
            refused = await next_of(ws, "ack")
            assert refused["data"]["code"] == "COLLISION"
            inside = {"type": "move", "data": {"pose": {"position": centre(pillar)}, "plan": True}}
            await ws.send_message(json.dumps(inside))
            error = await next_of(ws, "error")
            assert error["data"]["code"] in ("NO_PATH", "UNREACHABLE"), error
    sent = [joints for _, joints in recorder.targets]
    assert len(sent) > 10
    for joints in sent:
        assert guard.hit(urdf(model, joints), workspace) is None, joints


def centre(box: dict[str, Any]) -> list[float]:
    return [(lo + hi) / 2 for lo, hi in zip(box["min"], box["max"], strict=True)]


async def next_of(ws: Any, wanted: str) -> dict[str, Any]:
    with trio.fail_after(30):
        while True:
            message: dict[str, Any] = json.loads(await ws.get_message())
            if message["type"] == wanted:
                return message


async def test_a_move_without_plan_is_one_command_and_bad_bodies_are_refused(
    server: RunningServer,
) -> None:
    async with server.client() as http:
        moved = await http.post("/api/robots/demo-arm/move", json={"joints": {"Rotation": 10}})
        assert moved.status_code == 200, moved.text
        assert moved.json()["status"] == "accepted" and moved.json()["plan"] is False
        robot = server.app.manager.get("demo-arm")
        assert robot.core.motion.goals["Rotation"] == 10
        hand = hand_for(robot.model)
        assert hand is not None
        here = hand.pose(robot.core.motion.goals)
        assert here is not None
        pose = {"pose": {"position": [here.position[0], here.position[1], here.position[2] + 0.02]}}
        lifted = await http.post("/api/robots/demo-arm/move", json=pose)
        assert lifted.status_code == 200, lifted.text
        assert lifted.json()["distance"] < 0.0005
        for body, code in [
            ({}, "INVALID_VALUE"),
            ({"joints": {"Rotation": 1}, **pose}, "INVALID_VALUE"),
            ({"joints": {"Rotation": 1}, "budget": 500}, "INVALID_VALUE"),
            ({"joints": {"Rotation": 1}, "plan": True, "duration": 500}, "INVALID_VALUE"),
            ({"joints": {"Rotation": 1}, "plan": True, "budget": 5}, "INVALID_BODY"),
            ({"joints": {"Rotation": 1}, "plan": True, "speed": 2}, "INVALID_BODY"),
            ({"joints": {"Rotation": 1}, "plan": True, "speed": 1e-9}, "INVALID_BODY"),
            ({"joints": {"Nope": 1}, "plan": True}, "UNKNOWN_JOINT"),
            ({"joints": {"Rotation": 1}, "plan": "yes"}, "INVALID_BODY"),
            ({"joints": {"Rotation": 1}, "via": []}, "UNKNOWN_FIELD"),
        ]:
            refused = await http.post("/api/robots/demo-arm/move", json=body)
            assert refused.json()["error"]["code"] == code, (body, refused.text)
        # PUT .../joints's list, sent here: the answer shows this route's form.
        listed = {"joints": [{"name": "Rotation", "value": 1}]}
        refused = await http.post("/api/robots/demo-arm/move", json=listed)
        assert refused.json()["error"]["code"] == "INVALID_BODY", refused.text
        assert '{"Rotation": 10}' in refused.json()["error"]["message"], refused.text
        sequence = await http.post("/api/robots/demo-arm/play-sequence/gentle-wave")
        assert sequence.status_code == 200, sequence.text
        held = await http.post(
            "/api/robots/demo-arm/move", json={"joints": {"Rotation": 1}, "plan": True}
        )
        assert held.json()["error"]["code"] == "MASTER_ACTIVE", held.text


async def test_without_ompl_a_planned_move_says_what_to_install(
    server: RunningServer, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setitem(sys.modules, "ompl", None)  # import ompl raises ImportError
    async with server.client() as http:
        body = {"joints": {"Rotation": 10}, "plan": True}
        answer = await http.post("/api/robots/demo-arm/move", json=body)
    assert answer.status_code == 501, answer.text
    error = answer.json()["error"]
    assert error["code"] == "NOT_INSTALLED" and "arena[plan]" in error["message"]


@pytest.mark.parametrize("robot_type", TYPES)
def test_the_timed_path_keeps_every_joint_within_its_limits_and_stops_at_each_corner(
    robot_type: str,
) -> None:
    model = load_robot_model(robot_type)
    corners = [
        tuple(s.to_urdf(v) for s, v in zip(model.joints, values, strict=False))
        for values in ([0, 0, 0, 0, 0, 0], [60, -30, 20, 0, 90, 50], [60, -29, 20, 0, 90, 50])
    ] + [tuple(s.to_urdf(-40) for s in model.joints)]
    for speed in (1.0, 0.3):
        samples = planning.timed(corners, model, speed)
        times = [0.0] + [t for t, _ in samples]
        poses = [corners[0]] + [p for _, p in samples]
        assert poses[-1] == corners[-1]
        assert all(b - a <= planning.SAMPLE_PERIOD + 1e-9 for a, b in itertools.pairwise(times))
        for k, spec in enumerate(model.joints):
            limit = spec.max_velocity * spec.radians_per_unit * speed
            speeds = [
                (q[k] - p[k]) / (b - a)
                for a, b, p, q in zip(times, times[1:], poses, poses[1:], strict=False)
                if b > a
            ]
            assert max(abs(v) for v in speeds) <= limit * (1 + 1e-9)
            # the change of speed between two steps: within the acceleration limit (the mean
            # speeds of two steps are half a step apart, or less at a corner's short step)
            for (v1, a1, b1), (v2, a2, b2) in zip(
                zip(speeds, times, times[1:], strict=False),
                zip(speeds[1:], times[1:], times[2:], strict=False),
                strict=False,
            ):
                gap = (b2 - a2) / 2 + (b1 - a1) / 2
                assert abs(v2 - v1) <= limit / planning.ACCELERATION_TIME * gap * (1 + 1e-6) + 1e-9
        # at each corner the arm is at rest: the pose is sent as the corner, then the next
        # step starts from rest (its first step is no longer than the acceleration allows)
        for corner in corners[1:-1]:
            assert corner in poses


def test_a_timed_path_keeps_a_joints_declared_acceleration_when_it_is_lower() -> None:
    # A robot type whose joints declare 100 deg/s^2 (`max_acceleration` in robot.toml): far
    # below the planner's own gentleness (the velocity limit in 0.25 s, 800 deg/s^2 here).
    import dataclasses

    base = load_robot_model("so-arm100")
    model = dataclasses.replace(
        base, joints=tuple(dataclasses.replace(j, acceleration=100.0) for j in base.joints)
    )
    corners = [tuple(0.0 for _ in model.joints), tuple(s.to_urdf(60) for s in model.joints)]
    samples = planning.timed(corners, model)
    times = [0.0] + [t for t, _ in samples]
    poses = [corners[0]] + [p for _, p in samples]
    for k, spec in enumerate(model.joints):
        limit = 100.0 * spec.radians_per_unit
        speeds = [
            ((q[k] - p[k]) / (b - a), (a + b) / 2)
            for a, b, p, q in zip(times, times[1:], poses, poses[1:], strict=False)
            if b > a
        ]
        for (v1, t1), (v2, t2) in itertools.pairwise(speeds):
            assert abs(v2 - v1) <= limit * (t2 - t1) * (1 + 1e-6) + 1e-9


async def test_a_script_plans_its_move_around_the_pillar_on_the_server(
    start_server: StartServer, tmp_path: Path
) -> None:
    need("ompl", "plan")
    model, start, goal, pillar = scene("so-arm100")
    guard, workspace = guarded(model, pillar)
    folder = tmp_path / "scripts"
    folder.mkdir()
    (folder / "around.py").write_text(
        "from arena.script import move\n"
        f"move({goal!r}, plan=True)\n"
        f"move({start!r})  # straight back: through the pillar\n"
    )
    server = await start_server(demo=True, script_dir=str(folder))
    async with server.client() as http:
        robot = await arm_at(server, http, "demo-arm", start)
        recorder = RecordingSlave()
        await robot.attach_slave(recorder)
        await keep_out(http, robot, pillar)
        with robot.subscribe(kinds=[FaultReported]) as faults:
            body = {"type": "script", "path": "around.py"}
            attached = await http.post("/api/robots/demo-arm/master", json=body)
            assert attached.status_code == 201, attached.text
            fault = await faults.get()  # the script's end: its straight move refused
        await eventually(lambda: robot.snapshot().master is None, what="the script ended")
    assert isinstance(fault, FaultReported) and fault.code == "SCRIPT_FAILED", fault
    assert "line 3" in fault.message and "COLLISION" in fault.message, fault.message
    sent = [joints for _, joints in recorder.targets]
    assert len(sent) > 10
    for joints in sent:  # the planned way went around: every target clear in the guard's model
        assert guard.hit(urdf(model, joints), workspace) is None, joints
    for name, value in goal.items():  # and reached the goal
        assert sent[-1][name] == pytest.approx(value, abs=1e-6)


async def test_a_goal_in_the_table_or_a_box_is_refused_naming_it_whatever_the_solver_found(
    server: RunningServer,
) -> None:
    """A pose goal under the table (or inside a keep-out box) is a collision of the goal
    itself: refused COLLISION naming the floor (or the box) straight, NO_PATH with `blocked`
    planned, whether or not the solver got the hand there. It was `UNREACHABLE` ("4.4 mm
    away", the solver's residual) wherever the solver fell short of a point in the table."""
    need("ompl", "plan")
    robot: Robot = server.app.manager.get("demo-arm")
    hand = hand_for(robot.model)
    assert hand is not None and robot.workspace.floor == 0.0
    shelf = {"name": "shelf", "min": [-0.1, -0.8, 0.05], "max": [0.1, -0.6, 0.2]}
    async with server.client() as http:
        await keep_out(http, robot, shelf)
        goals = [
            ([0.0, -0.2, -0.05], "floor"),  # the solver gets there: the guard refuses it
            ([0.0, -0.1, -0.2], "floor"),  # the solver falls short (mm away)
            ([0.0, -0.4, -0.2], "floor"),
            ([0.0, -0.7, 0.1], "shelf"),  # out of reach, and in the box anyway
        ]
        start = {j.name: j.goal for j in robot.snapshot().joints}
        reached = [hand.solve(tuple(p), None, start).reached for p, _ in goals]  # type: ignore[arg-type]
        assert reached[0] and not any(reached[1:]), reached  # both ways are tried
        for position, what in goals:
            for method, path, body in (
                ("PUT", "pose", {"position": position}),
                ("POST", "move", {"pose": {"position": position}}),
                ("POST", "move", {"pose": {"position": position}, "plan": True}),
            ):
                answer = await http.request(method, f"/api/robots/demo-arm/{path}", json=body)
                assert answer.status_code == 422, (position, body, answer.text)
                error = answer.json()["error"]
                planned = body.get("plan") is True
                assert error["code"] == ("NO_PATH" if planned else "COLLISION"), (body, error)
                assert what in error["message"], (body, error)
                if planned:
                    assert error["blocked"][1] == what, (body, error)
        assert {j.name: j.goal for j in robot.snapshot().joints} == start  # nothing moved


@pytest.mark.parametrize("seed", range(14, 22))
async def test_a_path_the_arm_trails_is_run_on_the_lines_that_were_checked(
    autojump_clock: MockClock, manager: Any, seed: int
) -> None:
    # A path timed for an arm ten times as fast as this one: the trajectory trails the plan's
    # poses. Two things keep it on the path that was checked: the player waits at each corner
    # (the way from where the arm is to a pose past a corner cuts the corner, into the pillar:
    # refused COLLISION; without the wait 4 of these 8 plans, 21 of 40), and a stream the
    # limits hold back is held back with one factor for every joint (clipped joint by joint,
    # the arm left the line between two poses: a collision stop in 3 of these 8 plans, 8 of
    # 40). Every pose accepted, every target clear. (The planner's random numbers seeded: the
    # same plans in every run.)
    from arena.drivers.planned_move import PlannedMove

    need("ompl", "plan")
    model, start, goal, pillar = scene("so-arm100")
    guard, workspace = guarded(model, pillar)
    specs = tuple(dataclasses.replace(j, max_velocity=10 * j.max_velocity) for j in model.joints)
    fast = dataclasses.replace(model, joints=specs)
    planning.ompl_modules()[2].RNG.setSeed(seed)
    path = planning.plan(fast, guard, workspace, start, goal, budget=GENEROUS)
    robot = await manager.create_robot("so-arm100", robot_id="arm")
    recorder = RecordingSlave()
    await robot.attach_slave(recorder)
    from arena.robot.motion import Command

    assert (await robot.command(Command.of(start))).accepted
    await eventually(lambda: not robot.core.motion.moving, what="the arm at its start")
    await robot.set_workspace(workspace)
    player = PlannedMove(path)
    await robot.attach_master(player)
    await eventually(lambda: robot.snapshot().master is None, what="the planned move played")
    await eventually(lambda: not robot.core.motion.moving, what="the arm at rest")
    assert not player.refusals, player.refusals
    assert player.sent == len(path.samples)
    for _, joints in recorder.targets:
        assert guard.hit(urdf(model, joints), workspace) is None, joints
    assert robot.core.collision_stops == 0
    await eventually(
        lambda: recorder.targets[-1][1] == pytest.approx(goal, abs=1e-6),
        what="the last target, on the goal, delivered",
    )
