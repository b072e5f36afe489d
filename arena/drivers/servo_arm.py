"""What the USB slave and the USB master share: an arm on a servo bus of either family, its
calibration, and the bus thread's lifetime. The family comes from the robot type's `[bus]`
(`family_of`); everything past it speaks `arena.servo.interface` only."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path

import trio

from arena.drivers.bus_bridge import BusBridge, release_port, start_worker, wait_future
from arena.extras import require
from arena.protocol.errors import ArenaError, ErrorCode
from arena.robot.model import RobotModel
from arena.servo.calibration import Calibration
from arena.servo.interface import ServoBus, ServoFamily
from arena.servo.lerobot_calibration import (
    LeRobotCalibration,
    load_calibration,
    read_register_homings,
)
from arena.servo.worker import BusWorker, WorkerSettings

#: The servo families Arena drives, by the name a robot type's `[bus] family` gives.
FAMILIES = ("feetech", "dynamixel")


def family_named(name: str) -> ServoFamily:
    """The servo family called `name`; `NOT_INSTALLED` when its SDK is missing."""
    if name == "feetech":
        from arena.feetech.bus import FEETECH

        return FEETECH
    if name == "dynamixel":
        require("dynamixel", "A Dynamixel servo bus")
        from arena.dynamixel.bus import DYNAMIXEL

        return DYNAMIXEL
    raise ArenaError(
        ErrorCode.INVALID_CONFIG,
        f"Servo family {name!r} is unknown; Arena drives {', '.join(FAMILIES)}.",
    )


def family_of(model: RobotModel) -> ServoFamily:
    """The servo family of a robot type (its `[bus] family`)."""
    return family_named(model.bus.family)


def open_family_bus(family: ServoFamily, port: str, baud: int) -> ServoBus:
    """A bus of `family` on `port` (not opened yet): what an arm opens by default."""
    return family.open_bus(port, baud)


def servo_models(model: RobotModel, family: ServoFamily) -> dict[int, tuple[int, str]]:
    """The model number (and name) each servo of the robot type must answer a ping with; a
    joint naming a model its family does not have is refused."""
    models: dict[int, tuple[int, str]] = {}
    for joint in model.joints:
        name = (joint.servo_model or family.default_model).lower()
        if name not in family.models:
            raise ArenaError(
                ErrorCode.INVALID_CONFIG,
                f"Robot type {model.robot_type}: joint {joint.name}'s servo_model {name!r} is not "
                f"a {family.name} servo Arena knows ({', '.join(sorted(family.models))}).",
            )
        models[joint.servo_id] = (family.models[name], name.upper())
    return models


class ServoArm:
    """An arm on a servo bus: `prepare()` opens it, `close()` stops its thread.

    `port` None finds the adapter by USB id; `baud` None is the robot type's (or its family's).
    `open_bus` replaces the serial bus (tests, benchmarks). The calibration file is read at
    `prepare()` when it exists. A `leader`'s servos may be any model of the family: leader arms
    are built of other models than their followers (the Koch leader's XL330-M077).
    """

    def __init__(
        self,
        port: str | None,
        baud: int | None,
        model: RobotModel,
        calibration_file: Path | None,
        settings: WorkerSettings,
        open_bus: Callable[[str], ServoBus] | None,
        *,
        leader: bool = False,
    ) -> None:
        self.requested_port = port
        self.model = model
        self.family = family_of(model)
        self.calibration_file = calibration_file
        self.servo_ids = {joint.name: joint.servo_id for joint in model.joints}
        models = {} if leader else servo_models(model, self.family)
        self.settings = dataclasses.replace(settings, models=models)
        rate = baud or model.bus.baud_rate or self.family.default_baud
        family = self.family
        self._open_bus = open_bus or (lambda name: open_family_bus(family, name, rate))
        self.calibration = Calibration.identity(self.servo_ids, model.robot_type)
        self.calibrated = False
        self.port: str | None = None
        #: Who holds the port, as a busy port's error names it ("the usb-slave of robot 'arm'").
        self.holder = "an arm"
        self.worker: BusWorker | None = None
        self.bridge: BusBridge | None = None

    async def prepare(self) -> None:
        """Find and open the bus and check every servo; errors say what to do."""
        if self.worker is not None:
            return
        if self.calibration_file is not None and self.calibration_file.exists():
            # Either format; a LeRobot file that does not fit is refused here, before any torque.
            self.calibration = await trio.to_thread.run_sync(
                load_calibration, self.calibration_file, self.model, self.family
            )
            self.calibrated = True
        ids = tuple(self.servo_ids.values())
        lerobot = isinstance(self.calibration, LeRobotCalibration)
        # Arena's own calibration counts steps within one turn: on servos that count turns
        # (Dynamixel) the worker refuses, before any torque, one that reads outside it (a
        # Homing_Offset written, turns made in extended mode), which goals would send a turn away.
        settings = dataclasses.replace(self.settings, one_turn=not (lerobot or self.family.wraps))
        self.port, self.worker, self.bridge = await start_worker(
            self.requested_port, ids, settings, self._open_bus, self.family.adapters, self.holder
        )
        if isinstance(self.calibration, LeRobotCalibration):
            homings = await wait_future(self.worker.submit(lambda b: read_register_homings(b, ids)))
            self.calibration = self.calibration.with_register_homings(homings)

    async def close(self) -> None:
        """Torque off, port closed, thread ended (also for an arm prepared but never run)."""
        if self.worker is not None:
            with trio.CancelScope(shield=True):
                await trio.to_thread.run_sync(self.worker.stop)
            if self.port is not None:
                release_port(self.port, self.holder)
