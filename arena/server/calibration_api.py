"""REST for calibrating hardware slaves: start, capture the rest pose, finish, cancel, read.

The seed's workflow: torque off, the user poses the arm like the twin (the robot's virtual
pose, unless the request gives a rest pose), capture computes one offset per joint, the user
moves each joint through its range, finish stores the calibration (and, if asked, the offsets
in the servos' Homing_Offset registers) and torque comes back with goal = present.
"""

from __future__ import annotations

from typing import Any, Protocol

import msgspec
from quart import Blueprint, current_app, request

from arena.protocol.errors import ArenaError, ErrorCode
from arena.protocol.rest import CalibrationBody
from arena.robot.safety import Mode
from arena.server.base import ArenaApp, read_body
from arena.servo.calibration import Calibration

blueprint = Blueprint("calibration", __name__)


class Calibratable(Protocol):
    """A slave driver that can be calibrated (the USB slave)."""

    running: bool

    async def calibration_start(self, rest: dict[str, float]) -> None: ...
    async def calibration_capture(self) -> Calibration: ...
    async def calibration_finish(self, write_homing: bool = False) -> Calibration: ...
    async def calibration_cancel(self) -> None: ...
    def calibration_status(self) -> dict[str, Any]: ...


def _app() -> ArenaApp:
    return current_app  # type: ignore[return-value]


async def _body() -> CalibrationBody:
    body: CalibrationBody = await read_body(CalibrationBody, optional=True)
    return body


def _driver(robot_id: str, slave_id: str | None) -> tuple[str, Calibratable]:
    robot = _app().manager.get(robot_id)
    attached = {slave.peer_id for slave in robot.snapshot().slaves}
    return _app().hardware.find(robot_id, slave_id, attached)


def _status(robot_id: str, slave_id: str, driver: Calibratable) -> dict[str, Any]:
    status = msgspec.to_builtins(driver.calibration_status())
    assert isinstance(status, dict)
    return {"robot": robot_id, "slave": slave_id, **status}


@blueprint.get("/api/robots/<robot_id>/calibration")
async def read_calibration(robot_id: str) -> dict[str, Any]:
    """The calibration in use and any session in progress."""
    slave_id, driver = _driver(robot_id, request.args.get("slave"))
    return _status(robot_id, slave_id, driver)


@blueprint.post("/api/robots/<robot_id>/calibration/start")
async def start_calibration(robot_id: str) -> dict[str, Any]:
    """Torque off; the user poses the arm like the twin (or like `rest`)."""
    body = await _body()
    robot = _app().manager.get(robot_id)
    snapshot = robot.snapshot()
    if snapshot.mode is Mode.MASTERED:
        raise ArenaError(
            ErrorCode.MASTER_ACTIVE,
            f"Master {snapshot.owner!r} is driving this robot: detach it before calibrating.",
        )
    slave_id, driver = _driver(robot_id, body.slave)
    rest = (
        body.rest if body.rest is not None else {j.name: j.virtual_value for j in snapshot.joints}
    )
    await driver.calibration_start(rest)
    return _status(robot_id, slave_id, driver)


@blueprint.post("/api/robots/<robot_id>/calibration/capture")
async def capture_calibration(robot_id: str) -> dict[str, Any]:
    """Take the present pose as the rest pose; the range capture starts."""
    slave_id, driver = _driver(robot_id, (await _body()).slave)
    await driver.calibration_capture()
    return _status(robot_id, slave_id, driver)


@blueprint.post("/api/robots/<robot_id>/calibration/finish")
async def finish_calibration(robot_id: str) -> dict[str, Any]:
    """Store the calibration; torque back on where the arm is."""
    body = await _body()
    slave_id, driver = _driver(robot_id, body.slave)
    await driver.calibration_finish(body.writeHoming)
    return _status(robot_id, slave_id, driver)


@blueprint.post("/api/robots/<robot_id>/calibration/cancel")
async def cancel_calibration(robot_id: str) -> dict[str, Any]:
    """Back to the previous calibration; torque back on where the arm is."""
    slave_id, driver = _driver(robot_id, (await _body()).slave)
    await driver.calibration_cancel()
    return _status(robot_id, slave_id, driver)
