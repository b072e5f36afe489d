"""What the USB slave and the USB master share: an arm on a servo bus of either family, its
calibration, and the bus thread's lifetime. The family comes from the robot type's `[bus]`
(`family_of`); everything past it speaks `arena.servo.interface` only."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from pathlib import Path

import trio

from arena.drivers.bus_bridge import BusBridge, release_port, start_worker, wait_future
from arena.extras import require
from arena.protocol.errors import ArenaError, ErrorCode
from arena.robot.links import MasterLink, SlaveLink
from arena.robot.model import PERCENT, RobotModel
from arena.servo import sim_pace
from arena.servo.calibration import Calibration
from arena.servo.health import ServoFault
from arena.servo.interface import MAX_STEP, ServoBus, ServoFamily
from arena.servo.lerobot_calibration import (
    LeRobotCalibration,
    load_calibration,
    read_register_homings,
)
from arena.servo.ports import DEFAULT_TIMEOUT_MARGIN
from arena.servo.sim_pty import SimulatedBus
from arena.servo.worker import BusWorker, Frames, WorkerSettings

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
    """A bus of `family` on `port` (not opened yet): what an arm opens by default. On the port
    of a simulated bus (`arena sim-bus`), its reply timeout also waits for what the simulator
    owes (`arena.servo.sim_pace`): a simulator kept off the CPU is no silent servo."""
    if sim_pace.find(port) is None:
        return family.open_bus(port, baud)
    paced = sim_pace.paced_class(family.port_class)
    handler = paced(port, DEFAULT_TIMEOUT_MARGIN, lambda: sim_pace.find(port))
    return family.open_bus(port, baud, timeout_margin=DEFAULT_TIMEOUT_MARGIN, port_handler=handler)


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


def simulated_bus(model: RobotModel, ids: tuple[int, ...] | None = None) -> SimulatedBus:
    """A simulated bus of the robot type's servo family with its servos (`ids`, default the
    type's; a Dynamixel servo not of the type is its first one's model): what `arena sim-bus`
    serves, and a simulated leader arm of the server's."""
    family = family_of(model)
    if family.name == "dynamixel":
        from arena.dynamixel.sim import SimBus as DynamixelSimBus

        models = {sid: number for sid, (number, _) in servo_models(model, family).items()}
        if ids:
            first = next(iter(models.values()))
            models = {sid: models.get(sid, first) for sid in ids}
        return DynamixelSimBus(models)
    from arena.feetech.sim import SimBus

    return SimBus(ids or tuple(j.servo_id for j in model.joints))


def allowed_models(
    model: RobotModel, family: ServoFamily, *, leader: bool
) -> dict[int, tuple[frozenset[int], str]]:
    """The model numbers each servo may answer a ping with, and how to name them: a follower's
    is the one its robot type names; a leader's any of its family's table (all of them 4096
    steps a turn, the frame every calibration assumes), since leader arms are built of other
    models than their followers (the Koch leader's XL330-M077)."""
    if not leader:
        return {
            sid: (frozenset({number}), f"an {name} ({number})")
            for sid, (number, name) in servo_models(model, family).items()
        }
    known = ", ".join(f"{name.upper()} ({number})" for name, number in family.models.items())
    anyone = (frozenset(family.models.values()), f"a {family.name} model Arena knows: {known}")
    return {joint.servo_id: anyone for joint in model.joints}


class ServoArm:
    """An arm on a servo bus: `prepare()` opens it, `close()` stops its thread.

    `port` None finds the adapter by USB id; `baud` None is the robot type's (or its family's).
    `open_bus` replaces the serial bus (tests, benchmarks). The calibration file is read at
    `prepare()` when it exists. A `leader`'s servos may be any model of the family's table
    (`allowed_models`).
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
        self.joint_of = {sid: name for name, sid in self.servo_ids.items()}
        #: The joints the robot type reads 0..100 (LeRobot's grippers), with their URDF spans
        #: in degrees: the calibration gives their values so (`Calibration.to_values`).
        self.spans = {j.name: math.degrees(j.span) for j in model.joints if j.unit == PERCENT}
        self.leader = leader
        models = allowed_models(model, self.family, leader=leader)
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

    async def tell_fault(self, link: MasterLink | SlaveLink, fault: ServoFault) -> None:
        """A servo's fault, or its end, told to the robot: the one way for a follower (a
        slave's link) and a leader (a master's) alike, naming the servo's joint."""
        joint = self.joint_of.get(fault.servo_id) if fault.servo_id is not None else None
        message = f"{joint}: {fault.message}" if joint else fault.message
        if fault.cleared:
            await link.clear_fault(fault.code, joint, message)
        else:
            await link.report_fault(fault.code, message, fault.severity, joint)

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
        frames, hint = self._frames(ids)
        settings = dataclasses.replace(self.settings, frames=frames, frame_hint=hint)
        self.port, self.worker, self.bridge = await start_worker(
            self.requested_port, ids, settings, self._open_bus, self.family.adapters, self.holder
        )
        if isinstance(self.calibration, LeRobotCalibration):
            homings = await wait_future(self.worker.submit(lambda b: read_register_homings(b, ids)))
            self.calibration = self.calibration.with_register_homings(homings)

    def _frames(self, ids: tuple[int, ...]) -> tuple[Callable[[ServoBus], Frames] | None, str]:
        """`WorkerSettings.frames` and `frame_hint` for servos that count turns (Dynamixel): a
        joint turned a turn away by hand (while limp, or by another program) would be sent
        back a whole turn by goals clamped into its frame. Arena's own calibration counts
        steps within one turn (0..4095); a LeRobot file spans its range (and a margin), in the
        frame the servos' Homing_Offset registers give, read at each connection. A leader
        with a LeRobot file takes no torque and reads what LeRobot reads: no frame."""
        calibration = self.calibration
        if self.family.wraps or (self.leader and isinstance(calibration, LeRobotCalibration)):
            return None, ""
        if isinstance(calibration, LeRobotCalibration):
            return (
                lambda bus: calibration.with_register_homings(
                    read_register_homings(bus, ids)
                ).frames(),
                "Turn the joint back into its range by hand (torque is off).",
            )
        return (
            lambda bus: dict.fromkeys(ids, (0, MAX_STEP)),
            "Turn the joint back by hand; or, if this arm keeps a calibration in its servos "
            '(LeRobot\'s), attach it with that calibration file ("calibration": "lerobot:ID" '
            "or a path).",
        )

    async def close(self) -> None:
        """Torque off, port closed, thread ended (also for an arm prepared but never run)."""
        if self.worker is not None:
            with trio.CancelScope(shield=True):
                await trio.to_thread.run_sync(self.worker.stop)
            if self.port is not None:
                release_port(self.port, self.holder)
