"""The USB slave: an arm on a servo bus (Feetech or Dynamixel) follows the robot's targets.

The bus belongs to a `BusWorker` thread (the trio loop never waits on serial I/O). Targets go
through the calibration to raw goal steps; present positions come back as degrees. E-stop:
`hold` keeps torque with goal = present, `torque-off` releases the servos; either way targets
are ignored until the reset. Losing the bus applies the robot's loss policy while the worker
reconnects; after a reconnection nothing queued during the outage is executed.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import trio

from arena.drivers.bus_bridge import wait_future
from arena.drivers.config import UsbSlaveConfig
from arena.drivers.servo_arm import ServoArm
from arena.protocol.errors import ArenaError, ErrorCode, Severity
from arena.robot.events import NoticeKind, SlaveNotice
from arena.robot.links import SlaveLink
from arena.robot.model import RobotModel
from arena.servo.calibration import (
    DEGREES_PER_STEP,
    Calibration,
    RangeCapture,
    calibrate_rest,
    rest_degrees,
)
from arena.servo.force import ForceGuard, ForceSettings, Stalled
from arena.servo.health import ServoFault
from arena.servo.interface import STEPS_PER_TURN, ServoBus
from arena.servo.lerobot_calibration import LeRobotCalibration
from arena.servo.worker import (
    Connected,
    Lost,
    Reading,
    WorkerSettings,
    read_positions,
    store_offsets_in_servos,
)

log = logging.getLogger(__name__)
T = TypeVar("T")


@dataclass
class CalibrationSession:
    """A calibration in progress: `posing` until the rest pose is captured, then `range`."""

    rest: dict[str, float]
    previous: Calibration
    phase: str = "posing"
    capture: RangeCapture = field(default_factory=RangeCapture)


class UsbSlave(ServoArm):
    """See the module docstring. `open_bus` replaces the serial bus (tests, benchmarks)."""

    kind = "usb-slave"
    measures = True  # a real arm, wherever it rests: it joins before it follows

    def __init__(
        self,
        config: UsbSlaveConfig,
        model: RobotModel,
        calibration_file: Path | None = None,
        *,
        settings: WorkerSettings | None = None,
        open_bus: Callable[[str], ServoBus] | None = None,
    ) -> None:
        super().__init__(
            config.port,
            config.baud_rate,
            model,
            calibration_file,
            settings or WorkerSettings(rate=config.rate, speed_limit=_speed_limit(model)),
            open_bus,
        )
        self.config = config
        self.settings = dataclasses.replace(
            self.settings, torque_limits=torque_limits(model, config.torque_limit)
        )
        grippers = [
            j.servo_id
            for j in model.joints
            if "gripper" in {name.lower() for name in (j.name, *j.aliases)}
        ]
        #: Stall and heat protection (specs/force.md).
        self.guard = ForceGuard(
            self.settings.torque_limits,
            grippers,
            ForceSettings(stall_time=config.stall_time, hot=self.settings.limits.hot),
        )
        self._limits_written: dict[int, float] = {}  # the torque limits the guard last wrote
        self._held: dict[int, int] = {}  # stalled joints held where they stopped (raw steps)
        #: The newest reading: raw steps by servo id, and the joints' values (for hand guiding).
        self.present: dict[int, int] = {}
        self.pose: dict[str, float] = {}
        #: deg/s of its way to the robot's pose when it joins (None: the robot type's).
        self.join_speed = config.join_speed
        self.session: CalibrationSession | None = None
        self.frozen = False  # e-stopped: targets are ignored until the reset
        self.telemetry: Reading | None = None
        self.running = False
        self.link: SlaveLink | None = None  # while it runs
        self._accept_after = 0.0  # targets sent before this trio time are stale (bus was away)
        self._range_since = 0.0  # readings older than this (monotonic) predate the rest pose

    async def run(self, link: SlaveLink) -> None:
        """Follow targets and report joint states until detached; torque off at the end."""
        await self.prepare()
        assert self.worker is not None
        self.running = True
        self.link = link
        try:
            if not self.calibrated:
                await link.report_fault(
                    ErrorCode.UNCALIBRATED,
                    "This arm has no calibration yet: raw step 2048 is taken as 0 degrees. "
                    "Calibrate it before trusting its poses.",
                    Severity.WARNING,
                )
            async with trio.open_nursery() as nursery:
                nursery.start_soon(self._report, link)
                await self._follow(link)
                nursery.cancel_scope.cancel()
        finally:
            self.running = False
            self.link = None
            await self.close()

    def planned_stop(self) -> None:
        """The server stops as planned (SIGTERM): when this driver ends, leave the servos as
        its `estop` setting says (goal = present, then torque on for `hold`, off for
        `torque-off`) rather than limp whatever the setting, as a detach leaves them."""
        if self.worker is not None:
            self.worker.torque_at_exit = self.config.estop == "hold"

    # -- targets and notices ------------------------------------------------------------------

    async def _follow(self, link: SlaveLink) -> None:
        assert self.worker is not None
        async for message in link.messages():
            if isinstance(message, SlaveNotice):
                await self._on_notice(message.kind)
                continue
            if self.frozen or self.session is not None or message.time < self._accept_after:
                continue  # e-stopped, calibrating, or sent while the bus was away: never later
            goals = self.calibration.to_goal_steps(message.joints, self.spans)
            for servo_id, steps in goals.items():
                if self.guard.stalled(servo_id):
                    if self.guard.pushes_on(servo_id, steps):
                        if servo_id in self._held:  # no new command: it stays where it is
                            goals[servo_id] = self._held[servo_id]
                        continue
                    await self._release(link, servo_id)
                self.guard.goal(servo_id, steps)
            self.worker.set_goals(goals)

    async def _on_notice(self, kind: NoticeKind) -> None:
        torque_off = self.config.estop == "torque-off"
        if kind is NoticeKind.ESTOP:
            self.frozen = True
            held = None
            if self.session is None:
                held = await self._safe_hold(torque=not torque_off)
            if torque_off:  # limp: it may sag or be moved by hand before the reset
                await self._rejoin("torque off for the e-stop: the arm may be moved", held)
        elif kind is NoticeKind.HOLD:
            if self.session is None:
                await self._safe_hold(torque=True)
        elif kind is NoticeKind.RESET:
            self.frozen = False
            if self.worker is not None:  # the reset cleared its faults: what lasts comes back
                self.worker.rearm_health = True
            if self.session is None:  # torque back (or kept) with goal = present: no motion
                await self._safe_hold(torque=True)

    def _hold(self, bus: ServoBus, *, torque: bool) -> dict[int, int]:
        # Runs in the worker thread: goals not yet written are dropped, then hold where it is.
        # Returns where that is (raw steps by servo id).
        assert self.worker is not None
        self.worker.clear_goals()
        self.worker.torque_wanted = torque
        try:
            return self.worker.hold(bus, torque=torque)
        except ArenaError as exc:
            if exc.code is ErrorCode.SERVO_OUT_OF_RANGE:  # (the servos outside are limp now)
                self.worker.torque_wanted = False
            raise

    async def _safe_hold(self, *, torque: bool) -> dict[int, int] | None:
        """Hold where it is with this torque: now (the pose held), or if the bus is away, when
        it returns (None). A torque-on refused because a servo reads outside its frame (a
        turn away) is a critical fault, and the arm stays stopped until it is turned back and
        reset (None)."""
        assert self.worker is not None
        # Set before the job: if the bus is away the job is refused, and the worker applies
        # torque_wanted when it reconnects (an e-stop's torque-off must not come back on).
        self.worker.torque_wanted = torque
        try:
            return await wait_future(self.worker.submit(lambda bus: self._hold(bus, torque=torque)))
        except ArenaError as exc:
            if exc.code is not ErrorCode.SERVO_OUT_OF_RANGE:
                log.warning("usb-slave on %s: %s", self.port, exc.message)
                return None
            self.frozen = True
            if self.link is not None:
                await self.link.report_fault(exc.code, exc.message, Severity.CRITICAL)
            return None

    async def _safe_job(self, job: Callable[[ServoBus], T]) -> T | None:
        """`job` on the bus; None if the bus is down."""
        assert self.worker is not None
        try:
            return await wait_future(self.worker.submit(job))
        except ArenaError as exc:
            log.warning("usb-slave on %s: %s", self.port, exc.message)
            return None

    # -- what the bus reports -----------------------------------------------------------------

    async def _report(self, link: SlaveLink) -> None:
        assert self.bridge is not None
        while True:
            reading, events = await self.bridge.next()
            for event in events:
                await self._on_event(link, event)
            if reading is None:
                continue
            if reading.temperatures is not None:
                self.telemetry = reading
                await self._protect(link, reading)
            # (a reading read before the rest pose was captured may still be on its way: it
            # shows the arm before it was posed, no part of its range)
            session = self.session
            if (
                session is not None
                and session.phase == "range"
                and reading.time >= self._range_since
            ):
                session.capture.observe(self.calibration.to_degrees(reading.positions))
            self.present = dict(reading.positions)
            self.pose = self.calibration.to_values(reading.positions, self.spans)
            await link.report_joint_states(self.pose)

    # -- stall and heat (specs/force.md) ------------------------------------------------------

    async def _protect(self, link: SlaveLink, reading: Reading) -> None:
        """A telemetry read through the guard: stalled joints stop pushing, torque limits
        follow the temperatures and the stalls."""
        assert reading.temperatures is not None
        stalled = self.guard.observe(
            reading.time,
            reading.positions,
            reading.load_percent or {},
            {sid: float(c) for sid, c in reading.temperatures.items()},
        )
        for stall in stalled:
            await self._stall(link, stall)
        await self._write_limits()

    async def _stall(self, link: SlaveLink, stall: Stalled) -> None:
        assert self.worker is not None
        sid, name = stall.servo_id, self.joint_of[stall.servo_id]
        values = self.calibration.to_values({sid: stall.present}, self.spans)
        goals = self.calibration.to_values({sid: stall.goal}, self.spans)
        if sid in self.guard.grippers:
            what = f"it holds with {self.guard.settings.hold_torque:.0f} % torque"
        else:  # it stops pushing: its goal is where it is, until a new command
            self._held[sid] = stall.present
            self.worker.set_goals({sid: stall.present})
            what = "it holds where it is"
        await link.report_fault(
            ErrorCode.STALL,
            f"{name}: stalled at {values[name]:.1f}, short of its goal {goals[name]:.1f}, pushing "
            f"with {stall.load:.0f} % torque (its limit {stall.limit:.0f} %) for "
            f"{self.guard.settings.stall_time:g} s: {what} until a new command moves it.",
            Severity.WARNING,
            name,
        )

    async def _release(self, link: SlaveLink, servo_id: int) -> None:
        """A new command for a stalled joint: it pushes again, with its limit back."""
        self.guard.release(servo_id)
        self._held.pop(servo_id, None)
        name = self.joint_of[servo_id]
        await link.clear_fault(ErrorCode.STALL, name, f"{name}: a new command moves it again")
        await self._write_limits()

    async def _write_limits(self) -> None:
        """The torque limits the guard wants, where they changed."""
        assert self.worker is not None
        worker = self.worker
        changed = {
            sid: limit
            for sid in self.servo_ids.values()
            if (limit := self.guard.limit(sid))
            != self._limits_written.get(sid, worker.torque_limits.get(sid, 100.0))
        }
        if not changed:
            return
        self._limits_written.update(changed)
        await self._safe_job(lambda bus: worker.set_torque_limits(bus, changed))

    # -- compliance (hand guiding, specs/force.md) ---------------------------------------------

    def servo_ids_of(self, joints: Sequence[str]) -> dict[str, int]:
        """The servo id of each joint named (protocol names or aliases); `UNKNOWN_JOINT` for a
        name the robot type lacks."""
        found: dict[str, int] = {}
        for name in joints:
            joint = self.model.joint(name)
            if joint is None:
                raise ArenaError(
                    ErrorCode.UNKNOWN_JOINT,
                    f"No joint {name!r} on robot type {self.model.robot_type} (its joints: "
                    f"{', '.join(self.model.joint_names)}).",
                )
            found[joint.name] = joint.servo_id
        return found

    async def enter_compliance(self, joints: Sequence[str], torque: float) -> None:
        """The joints named give at most `torque` percent (a person can move them), and are
        never taken for stalled while they are compliant."""
        if not self.running or self.worker is None:
            raise ArenaError(ErrorCode.NO_HARDWARE, "The arm is not running: attach it first.")
        worker = self.worker
        servo_ids = list(self.servo_ids_of(joints).values())
        for servo_id in servo_ids:
            self.guard.release(servo_id)
            self._held.pop(servo_id, None)
            self.guard.overrides[servo_id] = torque
        wanted = {sid: self.guard.limit(sid) for sid in servo_ids}
        try:  # (a servo that cannot be limited refuses: say so, and change nothing)
            await self._job(lambda bus: worker.set_torque_limits(bus, wanted))
        except ArenaError:
            for servo_id in servo_ids:
                del self.guard.overrides[servo_id]
            await self._write_limits()
            raise
        self._limits_written.update(wanted)

    async def leave_compliance(self) -> None:
        """Compliance ends: the compliant joints hold where they are (goal = present), with
        their own torque limits back."""
        if not self.guard.overrides or self.worker is None:
            return
        servo_ids = list(self.guard.overrides)
        self.guard.overrides.clear()
        here = {sid: self.present[sid] for sid in servo_ids if sid in self.present}
        if not self.frozen:
            self.worker.set_goals(here)
        await self._write_limits()

    @property
    def compliant(self) -> list[str]:
        """The joints in compliance now."""
        return [self.joint_of[sid] for sid in self.guard.overrides]

    def servo_state(self) -> dict[str, tuple[float, float]]:
        """Each joint's last temperature (C) and load (percent of full torque), for /metrics."""
        reading = self.telemetry
        if reading is None or reading.temperatures is None:
            return {}
        loads = reading.load_percent or {}
        return {
            self.joint_of[sid]: (float(celsius), loads.get(sid, 0.0))
            for sid, celsius in reading.temperatures.items()
            if sid in self.joint_of
        }

    async def _on_event(self, link: SlaveLink, event: object) -> None:
        if isinstance(event, ServoFault):
            await self.tell_fault(link, event)
        elif isinstance(event, Lost):
            self._accept_after = math.inf
            await link.connection_lost(f"servo bus on {self.port}: {event.reason}")
        elif isinstance(event, Connected) and event.again:
            self._accept_after = trio.current_time()
            await link.connection_restored(f"servo bus on {self.port} answers again")

    # -- calibration --------------------------------------------------------------------------

    async def calibration_start(self, rest: Mapping[str, float]) -> None:
        """Torque off so the user can pose the arm like the twin's `rest` pose (degrees)."""
        if self.session is not None:
            raise ArenaError(ErrorCode.CALIBRATION_STATE, "A calibration is already running.")
        if isinstance(self.calibration, LeRobotCalibration):  # Arena never writes over it
            raise ArenaError(
                ErrorCode.CALIBRATION_STATE,
                f"This arm reads LeRobot's calibration {self.calibration.source}: calibrate it "
                "with LeRobot, or attach it with an Arena calibration name to calibrate here.",
            )
        unknown = sorted(set(rest) - set(self.servo_ids))
        if unknown:
            raise ArenaError(
                ErrorCode.UNKNOWN_JOINT, f"Unknown joints in the rest pose: {unknown}."
            )
        self.session = CalibrationSession(
            {name: float(rest.get(name, 0.0)) for name in self.servo_ids}, self.calibration
        )
        await self._job(lambda bus: self._hold(bus, torque=False))

    async def calibration_capture(self) -> Calibration:
        """Take the present pose as the rest pose; then the range capture runs."""
        session = self._session("posing")
        ids = tuple(self.servo_ids.values())
        self._range_since = time.monotonic()  # the clock of `Reading.time`
        raw = await self._job(lambda bus: read_positions(bus, ids))
        rest = rest_degrees(session.rest, self.spans)  # (the file holds degrees)
        self.calibration = calibrate_rest(self.calibration, raw, rest)
        session.phase = "range"
        session.capture.observe(self.calibration.to_degrees(raw))
        return self.calibration

    async def calibration_finish(self, write_homing: bool = False) -> Calibration:
        """Keep the captured ranges, store the calibration, torque back on (goal = present)."""
        session = self._session("range")
        calibration = session.capture.apply(self.calibration)
        if write_homing:
            ids = tuple(self.servo_ids.values())
            calibration = await self._job(
                lambda bus: store_offsets_in_servos(bus, calibration, ids)
            )
        if self.calibration_file is not None:
            await trio.to_thread.run_sync(calibration.save, self.calibration_file)
        self.calibration = calibration
        self.calibrated = True
        self.session = None
        if self.link is not None:
            await self.link.clear_fault(ErrorCode.UNCALIBRATED, message="calibrated")
        held = await self._job(lambda bus: self._hold(bus, torque=not self._torque_stays_off()))
        await self._rejoin("calibrated: its pose is measured anew", held)
        return calibration

    async def calibration_cancel(self) -> None:
        """Back to the calibration from before; torque back on (goal = present)."""
        session = self._session(None)
        self.calibration = session.previous
        self.session = None
        held = await self._job(lambda bus: self._hold(bus, torque=not self._torque_stays_off()))
        await self._rejoin("calibration cancelled: the arm was moved by hand", held)

    def calibration_status(self) -> dict[str, Any]:
        """The calibration in use and the session, for the REST API."""
        session = self.session
        return {
            "calibrated": self.calibrated,
            "file": str(self.calibration_file) if self.calibration_file else None,
            "calibration": self.calibration,
            "session": None
            if session is None
            else {
                "phase": session.phase,
                "rest": session.rest,
                # in the robot type's units: a percent joint's share of its span so far
                "range": {
                    name: [
                        session.capture.low[name] * self._unit_per_degree(name),
                        session.capture.high[name] * self._unit_per_degree(name),
                    ]
                    for name in session.capture.low
                },
            },
        }

    async def _rejoin(self, reason: str, held: dict[int, int] | None) -> None:
        # The arm is where a person left it (and maybe read through a new calibration): the
        # robot's targets must not pull it back at full speed. `held`: the raw pose the hold
        # just read, so that the join starts from it (a reading already on its way is older).
        if self.link is not None:
            pose = None if held is None else self.calibration.to_values(held, self.spans)
            await self.link.rejoin(reason, pose)

    def _unit_per_degree(self, name: str) -> float:
        span = self.spans.get(name)
        return 1.0 if span is None else 100.0 / span

    def _torque_stays_off(self) -> bool:
        return self.frozen and self.config.estop == "torque-off"

    def _session(self, phase: str | None) -> CalibrationSession:
        if self.session is None:
            raise ArenaError(ErrorCode.CALIBRATION_STATE, "No calibration is running: start one.")
        if phase is not None and self.session.phase != phase:
            hint = "capture the rest pose first" if phase == "range" else "it was captured already"
            raise ArenaError(
                ErrorCode.CALIBRATION_STATE,
                f"The calibration is in its {self.session.phase} phase: {hint}.",
            )
        return self.session

    async def _job(self, job: Callable[[ServoBus], Any]) -> Any:
        if self.worker is None or not self.worker.connected:
            raise ArenaError(ErrorCode.PORT_DISCONNECTED, "The servo bus is not connected.")
        return await wait_future(self.worker.submit(job))


def torque_limits(model: RobotModel, overrides: Mapping[str, float]) -> dict[int, float]:
    """Percent of full torque by servo id: the robot type's caps (its gripper's), then the
    slave's own (`overrides`, by joint name or alias); a name the type lacks is refused."""
    limits = {j.servo_id: j.torque_limit for j in model.joints if j.torque_limit is not None}
    for name, percent in overrides.items():
        joint = model.joint(name)
        if joint is None:
            raise ArenaError(
                ErrorCode.UNKNOWN_JOINT,
                f"torqueLimit names {name!r}, not a joint of robot type {model.robot_type} "
                f"(its joints: {', '.join(model.joint_names)}).",
            )
        limits[joint.servo_id] = float(percent)
    return limits


def _speed_limit(model: RobotModel) -> int:
    """Goal_Velocity for the servos, in steps/s: the lowest joint velocity limit, so that no
    servo outruns the robot's own limit even on a jump the limiter did not shape."""
    lowest_limit = min(joint.max_velocity for joint in model.joints)
    return max(1, min(STEPS_PER_TURN, round(lowest_limit / DEGREES_PER_STEP)))
