"""Force limits, stall and heat protection: through a real server on the simulated buses."""

from __future__ import annotations

from collections.abc import Awaitable, Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from arena.drivers.usb_slave import torque_limits
from arena.feetech import registers as reg
from arena.protocol.errors import ArenaError, ErrorCode
from arena.robot.model import load_robot_model
from arena.servo.sim_pty import PtySimBus
from tests.conftest import RunningServer, eventually
from tests.hardware import open_test_bus, running_sim
from tests.lerobot_arms import joined

StartServer = Callable[..., Awaitable[RunningServer]]
GRIPPER = 6


@pytest.fixture
def sim(tmp_path: Path) -> Iterator[PtySimBus]:
    yield from running_sim(tmp_path)


def peek(sim: PtySimBus, sid: int, register: reg.Register) -> int:
    """A register of one simulated servo."""
    with sim.paused() as bus:
        return int(bus.servo(sid).peek(register))


async def attach_so101(http: Any, sim: PtySimBus, **more: Any) -> Any:
    """Robot `arm` of type so-101, its usb-slave on the simulated bus; the attach's reply."""
    made = await http.post("/api/robots", json={"id": "arm", "robot_type": "so-101"})
    assert made.status_code == 201, made.text
    body = {"type": "usb-slave", "port": str(sim.link), **more}
    return await http.post("/api/robots/arm/slaves", json=body)


async def grip_an_object(http: Any, sim: PtySimBus) -> None:
    """An object between the jaws: a stop 60 steps on from where the gripper is, and a command
    that drives the gripper far past it (uncalibrated, 2048 reads 0 %, 100 % is 1250 steps on)."""
    here = peek(sim, GRIPPER, reg.PRESENT_POSITION)
    with sim.paused() as bus:
        bus.servo(GRIPPER).place_obstacle(here + 60)
    move = {"joints": [{"name": "gripper", "value": 100}]}
    answer = await http.put("/api/robots/arm/joints", json=move)
    assert answer.status_code == 200, answer.text
    await eventually(
        lambda: peek(sim, GRIPPER, reg.GOAL_POSITION) > here + 200, what="the gripper's goal"
    )


async def test_a_torque_limit_is_written_to_the_servo_and_obeyed(
    start_server: StartServer, sim: PtySimBus
) -> None:
    server = await start_server()
    async with server.client() as http:
        attached = await attach_so101(
            http, sim, torqueLimit={"gripper": 30, "shoulder_pan": 80}, stallTime=60
        )
        assert attached.status_code == 201, attached.text
        await eventually(lambda: joined(http), what="the arm joined")
        limits = {sid: peek(sim, sid, reg.TORQUE_LIMIT) for sid in range(1, 7)}
        assert limits == {1: 800, 2: 1000, 3: 1000, 4: 1000, 5: 1000, 6: 300}
        await grip_an_object(http, sim)
        # Held by the object, it pushes with what its limit allows and no more.
        await eventually(
            lambda: peek(sim, GRIPPER, reg.PRESENT_LOAD) == 300, what="the gripper pushing at 30 %"
        )
        assert peek(sim, GRIPPER, reg.TORQUE_ENABLE) == 1


async def test_the_so101_gripper_is_capped_as_lerobot_caps_it(
    start_server: StartServer, sim: PtySimBus
) -> None:
    with sim.paused() as bus:
        bus.servo(GRIPPER).poke(reg.TORQUE_LIMIT, 1000)
    server = await start_server()
    async with server.client() as http:
        attached = await attach_so101(http, sim)
        assert attached.status_code == 201, attached.text
        await eventually(lambda: joined(http), what="the arm joined")
        # LeRobot's Max_Torque_Limit 500 for the SO follower's gripper (so_follower.py).
        assert peek(sim, GRIPPER, reg.TORQUE_LIMIT) == 500
        assert peek(sim, 1, reg.TORQUE_LIMIT) == 1000


@pytest.mark.parametrize(
    ("limits", "status", "code"),
    [
        ({"thumb": 50}, 422, "UNKNOWN_JOINT"),
        ({"gripper": 150}, 422, "INVALID_BODY"),
        ({"gripper": 0}, 422, "INVALID_BODY"),
        ({f"j{k}": 10 for k in range(40)}, 422, "INVALID_BODY"),
    ],
)
async def test_a_bad_torque_limit_is_refused_with_a_reason(
    start_server: StartServer, sim: PtySimBus, limits: dict[str, int], status: int, code: str
) -> None:
    server = await start_server()
    async with server.client() as http:
        refused = await attach_so101(http, sim, torqueLimit=limits)
        assert refused.status_code == status, refused.text
        assert refused.json()["error"]["code"] == code
        assert refused.json()["error"]["message"]
        assert peek(sim, 1, reg.TORQUE_ENABLE) == 0  # nothing was started


def test_the_koch_gripper_is_current_based_as_lerobot_runs_it(tmp_path: Path) -> None:
    pytest.importorskip("dynamixel_sdk")
    from arena.dynamixel import registers as dr
    from arena.dynamixel.sim import SimBus as DynamixelSim

    model = load_robot_model("koch")
    assert torque_limits(model, {}) == {GRIPPER: 100.0}
    assert torque_limits(model, {"gripper": 40}) == {GRIPPER: 40.0}
    for sim in running_sim(tmp_path, bus=DynamixelSim()):
        bus = open_test_bus(str(sim.link))
        bus.open()
        try:
            bus.prepare(range(1, 7), limited=[GRIPPER])
            bus.set_torque_limits({sid: 100.0 for sid in range(1, 6)} | {GRIPPER: 40.0})
            bus.read_positions(range(1, 7))  # (answered after the write: it was handled)
            with sim.paused() as servos:
                modes = {sid: s.peek(dr.OPERATING_MODE) for sid, s in servos.servos.items()}
                goal_current = servos.servo(GRIPPER).peek(dr.GOAL_CURRENT)
            assert modes == {1: 3, 2: 3, 3: 3, 4: 3, 5: 3, 6: dr.OperatingMode.CURRENT_POSITION}
            assert goal_current == 700  # 40 % of the XL330-M288's 1750 mA
            # A limit on an XL430, which reads no current, is refused, naming it.
            with pytest.raises(ArenaError) as refused:
                bus.prepare(range(1, 7), limited=[2, GRIPPER])
            assert refused.value.code is ErrorCode.INVALID_CONFIG
            assert "XL430-W250" in refused.value.message and "servo 2" in refused.value.message
        finally:
            bus.close()
