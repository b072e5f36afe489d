"""REST for a robot's leader arm when it is a simulated one the server owns
(`arena.server.sim_leaders`): `GET /api/robots/{id}/leader` says which leader arm drives the
robot (or waits while another intervenes), whether it is simulated, and where its joints are;
`PUT /api/robots/{id}/leader/joints` moves a simulated leader's joints as a hand would, and its
usb-master drives the robot from what it reads, through every rule. So teleoperation and a
correction of a running policy can be tried from the dashboard without an arm.
"""

from __future__ import annotations

from typing import Any

import trio
from quart import Blueprint, current_app

from arena.protocol.errors import ArenaError, ErrorCode
from arena.protocol.rest import LeaderJointsBody
from arena.robot.handle import Robot
from arena.robot.model import PERCENT
from arena.server.base import ArenaApp, read_body
from arena.server.sim_leaders import SimLeader
from arena.servo.sim_control import ControlError, SimControl

blueprint = Blueprint("sim_leader", __name__)

#: The control's refusals as the API's codes.
_CODE_FOR = {
    "UNKNOWN_JOINT": ErrorCode.UNKNOWN_JOINT,
    "OUT_OF_RANGE": ErrorCode.INVALID_VALUE,
}


def _app() -> ArenaApp:
    return current_app  # type: ignore[return-value]


def _simulated(app: ArenaApp, robot: Robot) -> tuple[str, SimLeader, SimControl]:
    """The robot's simulated leader arm: its master id, the arm and its hand; NO_LEADER or
    LEADER_NOT_SIMULATED."""
    found = app.sim_leaders.leader_of(robot)
    if found is None:
        raise ArenaError(
            ErrorCode.NO_LEADER,
            f"No leader arm drives robot {robot.robot_id!r}: attach one first (a usb-master, "
            "as its master or as an intervention).",
        )
    master_id, driver, _ = found
    sim = app.sim_leaders.owning(driver.port)
    if sim is None:
        raise ArenaError(
            ErrorCode.LEADER_NOT_SIMULATED,
            f"Leader arm {master_id!r} on {driver.port} is not one of this server's simulated "
            "leaders: move it by hand.",
        )
    return master_id, sim, _hand(sim, master_id, driver)


def _hand(sim: SimLeader, master_id: str, driver: Any) -> SimControl:
    return sim.control(master_id, driver.model, driver.calibration)


@blueprint.get("/api/robots/<robot_id>/leader")
async def leader(robot_id: str) -> dict[str, Any]:
    """The server's simulated leader arms, and the robot's leader arm (null: none)."""
    app = _app()
    robot = app.manager.get(robot_id)
    simulated = [
        {"port": sim.port, "robot_type": sim.robot_type} for sim in app.sim_leaders.leaders
    ]
    found = app.sim_leaders.leader_of(robot)
    if found is None:
        return {"simulated": simulated, "leader": None}
    master_id, driver, driving = found
    sim = app.sim_leaders.owning(driver.port)
    shown: dict[str, Any] = {
        "id": master_id,
        "port": driver.port,
        "driving": driving,
        "simulated": sim is not None,
    }
    if sim is not None:
        hand = _hand(sim, master_id, driver)
        values = await trio.to_thread.run_sync(hand.read)
        shown["joints"] = [
            {
                "name": joint.name,
                "value": values.get(joint.name),
                "min": round(joint.lower, 3),
                "max": round(joint.upper, 3),
                "unit": "%" if joint.unit == PERCENT else "deg",
            }
            for joint in hand.model.joints
        ]
    return {"simulated": simulated, "leader": shown}


@blueprint.put("/api/robots/<robot_id>/leader/joints")
async def move_leader(robot_id: str) -> dict[str, Any]:
    """Move the robot's simulated leader arm's joints (as a hand moves a real one's)."""
    app = _app()
    robot = app.manager.get(robot_id)
    body: LeaderJointsBody = await read_body(LeaderJointsBody)
    master_id, sim, hand = _simulated(app, robot)
    goals: dict[str, float] = {}
    for joint in body.joints:
        if joint.name in goals:
            raise ArenaError(ErrorCode.INVALID_BODY, f"Joint {joint.name!r} is named twice.")
        goals[joint.name] = joint.value
    try:
        checked = hand.check_goals(goals)
    except ControlError as error:
        raise ArenaError(_CODE_FOR.get(error.code, ErrorCode.INVALID_BODY), error.message) from None
    if not sim.allow(trio.current_time()):
        raise ArenaError(
            ErrorCode.RATE_LIMITED,
            f"More than {sim.rate:g} moves a second of this leader arm; move dropped.",
        )
    seconds = body.duration / 1000.0
    await trio.to_thread.run_sync(hand.move, checked, seconds, hand.clock())
    return {"leader": master_id, "moving": sorted(checked), "duration": body.duration}
