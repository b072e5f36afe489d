"""Teleoperation by velocity: the hand follows `ee_velocity` on the mock clock (the forward
kinematics of the targets the robot sends), stops at the dead-man time, stays in its box; and
the same through a real server."""

from __future__ import annotations

import json
import math
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from typing import Any

import pytest
import trio
from trio.testing import MockClock
from trio_websocket import open_websocket_url

from arena.robot.cartesian import POSITION_TOLERANCE, Hand, hand_for
from arena.robot.handle import Robot
from arena.robot.kinematics import Vector
from arena.robot.links import MasterLink
from arena.robot.manager import RobotManager
from arena.robot.motion import Command, CommandResult
from arena.robot.teleop import DEADMAN, TICK, TeleopSettings, VelocityDriver, default_settings
from tests.conftest import RecordingSlave, RunningServer, eventually

#: Where the so-101 starts each test: the hand in front of it, well inside its reach.
START = {"shoulder_lift": -30.0, "elbow_flex": 30.0, "wrist_flex": 40.0}


@dataclass
class Teleop:
    robot: Robot
    link: MasterLink
    hand: Hand
    settings: TeleopSettings
    sent: list[tuple[float, Vector]] = field(default_factory=list)  # (time, tool point)
    refusals: list[CommandResult] = field(default_factory=list)
    driver: VelocityDriver | None = None

    async def send(self, command: Command) -> CommandResult:
        sent_at = trio.current_time()  # (its answer comes on the robot's next tick)
        result = await self.link.command(command)
        goals = {joint.name: joint.goal for joint in self.robot.snapshot().joints}
        pose = self.hand.pose(goals)
        assert pose is not None
        if result.accepted:
            self.sent.append((sent_at, pose.position))
        return result

    async def refused(self, result: CommandResult) -> None:
        self.refusals.append(result)

    def start_point(self) -> Vector:
        pose = self.hand.pose({j.name: j.goal for j in self.robot.snapshot().joints})
        assert pose is not None
        return pose.position


@pytest.fixture
async def teleop(
    autojump_clock: MockClock, manager: RobotManager, nursery: trio.Nursery
) -> AsyncIterator[Teleop]:
    robot = await manager.create_robot("so-101", robot_id="arm")
    await robot.attach_slave(RecordingSlave())
    link = await robot.connect_master("keyboard")
    assert (await link.command(Command.of(START))).accepted
    await trio.sleep(3.0)  # there
    hand = hand_for(robot.model)
    assert hand is not None
    state = Teleop(robot, link, hand, default_settings(hand, robot.workspace))
    state.driver = VelocityDriver(
        hand,
        lambda: {joint.name: joint.goal for joint in robot.snapshot().joints},
        state.send,
        lambda: state.settings,
        state.refused,
    )
    nursery.start_soon(state.driver.run)
    yield state


async def hold_key(teleop: Teleop, linear: Vector, seconds: float, every: float = 0.05) -> float:
    """Send `linear` every `every` seconds for `seconds` (a key held down); the time of the
    last message."""
    assert teleop.driver is not None
    ends = trio.current_time() + seconds
    last = trio.current_time()
    while trio.current_time() < ends - 1e-9:
        teleop.driver.velocity(linear, None, None)
        last = trio.current_time()
        await trio.sleep(every)
    return last


@pytest.mark.parametrize("axis", [0, 1, 2])
async def test_the_hand_moves_along_the_commanded_axis_at_the_commanded_speed(
    teleop: Teleop, axis: int
) -> None:
    start = teleop.start_point()
    velocity = [0.0, 0.0, 0.0]
    velocity[axis] = 0.04 if axis != 1 else -0.04
    began = trio.current_time()
    last = await hold_key(teleop, (velocity[0], velocity[1], velocity[2]), 1.0)
    await trio.sleep(1.0)  # released: the hand stops
    assert len(teleop.sent) > 20  # a target every tick or so
    for when, point in teleop.sent:
        moving = min(when, last + DEADMAN) - began
        expected = [s + v * moving for s, v in zip(start, velocity, strict=True)]
        # Along the axis within a little more than a tick's travel of where the velocity puts
        # it (the target is made on the tick, the time taken when its command is answered);
        # the other axes where they were, within the solver's tolerance.
        assert math.dist(point, expected) < 0.04 * 2.5 * TICK + 2 * POSITION_TOLERANCE, when
    final = teleop.sent[-1][1]
    assert final[axis] - start[axis] == pytest.approx(
        velocity[axis] * (last + DEADMAN - began), abs=0.001
    )


async def test_the_hand_stops_within_the_dead_man_time(teleop: Teleop) -> None:
    assert teleop.driver is not None
    start = teleop.start_point()
    teleop.driver.velocity((0.05, 0.0, 0.0), None, None)
    heard = trio.current_time()
    await trio.sleep(2.0)
    assert teleop.sent
    # The last command leaves on the first tick past the dead-man time (a tick is TICK after
    # the previous command's answer, which the robot gives on its own tick: at most another).
    assert all(when <= heard + DEADMAN + 2 * TICK + 1e-9 for when, _ in teleop.sent)
    travelled = teleop.sent[-1][1][0] - start[0]
    assert travelled == pytest.approx(0.05 * DEADMAN, abs=0.0015)
    # A longer dead-man time, set while it waits, lets it go on for that long.
    teleop.settings = TeleopSettings(teleop.settings.low, teleop.settings.high, deadman=0.5)
    teleop.sent.clear()
    teleop.driver.velocity((0.05, 0.0, 0.0), None, None)
    heard = trio.current_time()
    await trio.sleep(2.0)
    assert all(when <= heard + 0.5 + 2 * TICK + 1e-9 for when, _ in teleop.sent)
    assert teleop.sent[-1][1][0] - start[0] == pytest.approx(0.05 * (DEADMAN + 0.5), abs=0.002)


async def test_the_hand_never_leaves_its_box(teleop: Teleop) -> None:
    x, y, z = teleop.start_point()
    teleop.settings = TeleopSettings((x - 0.01, y - 0.05, z - 0.03), (x + 0.02, y + 0.05, z + 0.01))
    await hold_key(teleop, (0.1, 0.0, 0.1), 1.0)  # far past two of its walls
    await hold_key(teleop, (-0.1, 0.0, -0.1), 1.0)  # and back past the other two
    await trio.sleep(0.5)
    low, high = teleop.settings.low, teleop.settings.high
    for _, point in teleop.sent:
        for k in range(3):
            assert low[k] - POSITION_TOLERANCE <= point[k] <= high[k] + POSITION_TOLERANCE
    xs = [point[0] for _, point in teleop.sent]
    assert max(xs) == pytest.approx(high[0], abs=POSITION_TOLERANCE)  # it went to the walls
    assert min(xs) == pytest.approx(low[0], abs=POSITION_TOLERANCE)


async def test_an_estop_stops_the_hand_and_says_why(teleop: Teleop) -> None:
    assert teleop.driver is not None
    teleop.driver.velocity((0.0, 0.0, 0.05), None, None)
    await trio.sleep(0.1)
    await teleop.robot.estop("stop it")
    await hold_key(teleop, (0.0, 0.0, 0.05), 0.3)
    assert teleop.refusals and str(teleop.refusals[0].code) == "ESTOPPED"


# -- through a real server ------------------------------------------------------------------


async def test_ee_velocity_over_the_master_websocket_moves_the_hand_up(
    server: RunningServer,
) -> None:
    async with server.client() as client:
        settings = (await client.get("/api/robots/demo-arm/teleop")).json()
        assert settings["deadman"] == 200
        low, high = settings["box"]["min"], settings["box"]["max"]
        assert low[2] >= 0.02 and all(a < b for a, b in zip(low, high, strict=True))
        for body, code in [
            ({"box": {"min": [0, 0, 0], "max": [0, 1, 1]}}, "INVALID_VALUE"),
            ({"deadman": 0}, "INVALID_BODY"),
            ({"deadman": 200, "clutch": True}, "UNKNOWN_FIELD"),
        ]:
            refused = await client.put("/api/robots/demo-arm/teleop", json=body)
            assert refused.json()["error"]["code"] == code, (body, refused.text)
        changed = await client.put("/api/robots/demo-arm/teleop", json={"deadman": 300})
        assert changed.json()["deadman"] == 300 and changed.json()["box"]["min"] == low

        async def height() -> float:
            pose = (await client.get("/api/robots/demo-arm/pose")).json()
            value: float = pose["commanded"]["position"][2]
            return value

        before = await height()
        async with open_websocket_url(server.ws_url + "/ws/master/demo-arm") as ws:
            message = {"type": "ee_velocity", "data": {"linear": [0, 0, 0.05]}}

            async def risen() -> bool:
                await ws.send_message(json.dumps(message))
                return await height() > before + 0.005

            await eventually(risen, what="the hand risen 5 mm")
            await ws.send_message(
                json.dumps({"type": "ee_velocity", "data": {"linear": [0, 0, 0], "gripper": 1e4}})
            )
            error = await _next(ws, "error")
            assert error["data"]["code"] == "INVALID_MESSAGE"


async def _next(ws: Any, wanted: str) -> dict[str, Any]:
    with trio.fail_after(30):
        while True:
            message: dict[str, Any] = json.loads(await ws.get_message())
            if message["type"] == wanted:
                return message
