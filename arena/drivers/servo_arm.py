"""What the USB slave and the USB master share: an arm on a servo bus, its calibration, and the
bus thread's lifetime."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import trio

from arena.drivers.bus_bridge import BusBridge, start_worker, wait_future
from arena.feetech.bus import ServoBus
from arena.feetech.calibration import Calibration
from arena.feetech.lerobot_calibration import (
    LeRobotCalibration,
    load_calibration,
    read_register_homings,
)
from arena.feetech.worker import BusWorker, WorkerSettings
from arena.robot.model import RobotModel


class ServoArm:
    """An arm on a Feetech bus: `prepare()` opens it, `close()` stops its thread.

    `port` None finds the adapter by USB id. `open_bus` replaces the serial bus (tests,
    benchmarks). The calibration file is read at `prepare()` when it exists.
    """

    def __init__(
        self,
        port: str | None,
        baud: int,
        model: RobotModel,
        calibration_file: Path | None,
        settings: WorkerSettings,
        open_bus: Callable[[str], ServoBus] | None,
    ) -> None:
        self.requested_port = port
        self.model = model
        self.calibration_file = calibration_file
        self.servo_ids = {joint.name: joint.servo_id for joint in model.joints}
        self.settings = settings
        self._open_bus = open_bus or (lambda name: ServoBus(name, baud))
        self.calibration = Calibration.identity(self.servo_ids, model.robot_type)
        self.calibrated = False
        self.port: str | None = None
        self.worker: BusWorker | None = None
        self.bridge: BusBridge | None = None

    async def prepare(self) -> None:
        """Find and open the bus and check every servo; errors say what to do."""
        if self.worker is not None:
            return
        if self.calibration_file is not None and self.calibration_file.exists():
            # Either format; a LeRobot file that does not fit is refused here, before any torque.
            self.calibration = await trio.to_thread.run_sync(
                load_calibration, self.calibration_file, self.model
            )
            self.calibrated = True
        ids = tuple(self.servo_ids.values())
        self.port, self.worker, self.bridge = await start_worker(
            self.requested_port, ids, self.settings, self._open_bus
        )
        if isinstance(self.calibration, LeRobotCalibration):
            homings = await wait_future(self.worker.submit(lambda b: read_register_homings(b, ids)))
            self.calibration = self.calibration.with_register_homings(homings)

    async def close(self) -> None:
        """Torque off, port closed, thread ended (also for an arm prepared but never run)."""
        if self.worker is not None:
            with trio.CancelScope(shield=True):
                await trio.to_thread.run_sync(self.worker.stop)
