"""The thread that owns a servo bus and runs its control loop.

Each cycle: write the newest goals (if any arrived), read present positions (every few cycles
the whole telemetry block: position, velocity, load, voltage, temperature), check servo health,
hand the reading to the listener. Between cycles it runs jobs other threads submit (torque,
hold, calibration reads), so the bus is only ever touched from this thread. When the bus fails
or a servo stays silent, it reports the loss and reconnects on its own.

Connecting is always safe: present positions are read and written back as goals before torque
goes on, so nothing jumps, and goals queued before the connection are dropped.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Protocol, TypeVar

import msgspec

from arena.protocol.errors import ArenaError, ErrorCode
from arena.servo.calibration import Calibration, homing_offset_register
from arena.servo.health import HealthLimits, HealthMonitor, ServoFault
from arena.servo.interface import BusError, ServoBus

T = TypeVar("T")
log = logging.getLogger(__name__)
#: The raw present positions (low, high, inclusive) a servo may read when torque goes on, by id.
Frames = dict[int, tuple[int, int]]


@dataclass(frozen=True, slots=True)
class Reading:
    """Raw present positions by servo id; telemetry when this cycle read it."""

    positions: dict[int, int]
    time: float  # time.monotonic() of the read
    temperatures: dict[int, int] | None = None
    loads: dict[int, int] | None = None
    voltages: dict[int, float] | None = None
    load_percent: dict[int, float] | None = None  # loads in percent of full torque


@dataclass(frozen=True, slots=True)
class Connected:
    """The bus answers; `again` after a loss."""

    again: bool


@dataclass(frozen=True, slots=True)
class Lost:
    """The bus or a servo stopped answering; the worker keeps trying to reconnect."""

    reason: str


WorkerEvent = Connected | Lost | ServoFault


class Listener(Protocol):
    """Receives what the worker sees. Called from the worker thread: must not block."""

    def reading(self, reading: Reading) -> None: ...

    def event(self, event: WorkerEvent) -> None: ...


@dataclass
class WorkerSettings:
    """How the loop runs. `rate` 0 means as fast as the bus allows."""

    rate: float = 100.0
    telemetry_rate: float = 10.0
    reconnect_interval: float = 0.5
    speed_limit: int | None = None  # the servos' speed (steps/s) set at connect
    torque_on_connect: bool = True  # False for a leader arm, moved by hand
    limits: HealthLimits = field(default_factory=HealthLimits)
    #: The model numbers each servo may answer a ping with (by id), and how to name them.
    models: dict[int, tuple[frozenset[int], str]] = field(default_factory=dict)
    #: For servos that count turns: each servo's frame (`Frames`), worked out at every
    #: connection before any torque. A servo outside it refuses the connection and every
    #: torque-on, and is a fault while it lasts: goals, clamped into the frame, would send it a
    #: whole turn (specs/servo-bus.md). None: no frame (servos that wrap within one turn).
    frames: Callable[[ServoBus], Frames] | None = None
    #: What to do about a servo outside its frame, added to the refusal.
    frame_hint: str = ""
    #: Percent of full torque each servo may give, by id (absent: 100), written at every
    #: connection before the hold (`ServoBus.set_torque_limits`); the servos named are
    #: prepared for it (`ServoBus.prepare`'s `limited`). specs/force.md.
    torque_limits: dict[int, float] = field(default_factory=dict)


@dataclass
class WorkerStats:
    """Counters for benchmarks and status."""

    cycles: int = 0
    started: float = 0.0
    busy: float = 0.0  # seconds spent inside cycles
    thread_cpu: float = 0.0  # CPU seconds of the worker thread


class BusWorker:
    """Run a `ServoBus` in a thread of its own. See the module docstring."""

    def __init__(
        self,
        open_bus: Callable[[], ServoBus],
        servo_ids: Sequence[int],
        listener: Listener,
        settings: WorkerSettings | None = None,
    ) -> None:
        self.open_bus = open_bus
        self.servo_ids = tuple(servo_ids)
        self.listener = listener
        self.settings = settings or WorkerSettings()
        self.health = HealthMonitor(self.servo_ids, self.settings.limits)
        self.stats = WorkerStats()
        self.first_connect: Future[None] = Future()
        self.torque_wanted = self.settings.torque_on_connect
        #: How the servos are left when the thread ends. None: limp (torque off). True or
        #: False: goal = present, then torque on or off (a planned stop, by the slave's e-stop
        #: setting): no motion left, and nothing jumps when torque comes back.
        self.torque_at_exit: bool | None = None
        self.frames: Frames = {}  # this connection's (`WorkerSettings.frames`)
        self.torqued = False  # the torque the last successful `hold` set
        #: The torque limits in force (percent by servo id): the settings', lowered at run
        #: time (`set_torque_limits`: stall, heat, compliance); written again at a reconnection.
        self.torque_limits = {
            sid: self.settings.torque_limits.get(sid, 100.0) for sid in self.servo_ids
        }
        #: Set from another thread: raise again every fault that lasts (`HealthMonitor.rearm`).
        self.rearm_health = False
        self._bus: ServoBus | None = None
        self._lock = threading.Lock()
        self._goals: dict[int, int] | None = None
        self._jobs: list[tuple[Callable[[ServoBus], object], Future[object]]] = []
        self._stopping = threading.Event()
        # Set by whatever wants the thread between two cycles (goals, a job, the stop): goals
        # are written when they come, not at the next cycle (a tick's wait off every target).
        self._wake = threading.Event()
        self._thread = threading.Thread(target=self._main, name="servo-bus", daemon=True)

    # -- other threads ------------------------------------------------------------------------

    def start(self) -> None:
        """Start the thread; `first_connect` resolves once the first connection is made or fails."""
        self._thread.start()

    def stop(self, timeout: float = 5.0) -> None:
        """Torque off (or as `torque_at_exit` says), close the port, end the thread (blocks until
        it has)."""
        self._stopping.set()
        self._wake.set()
        if self._thread.is_alive():
            self._thread.join(timeout)

    def set_goals(self, goals: Mapping[int, int]) -> None:
        """New raw goal steps; only the newest set is written (older ones are dropped).

        Goals given while the bus is away are dropped: they would be stale when it returns.
        """
        with self._lock:
            if self._bus is None:
                return
            self._goals = dict(goals) if self._goals is None else {**self._goals, **goals}
        self._wake.set()

    def clear_goals(self) -> None:
        """Drop goals not yet written."""
        with self._lock:
            self._goals = None

    def submit(self, job: Callable[[ServoBus], T]) -> Future[T]:
        """Run `job(bus)` in the worker thread as soon as the cycle under way ends (fails at
        once if the bus is away)."""
        future: Future[T] = Future()
        with self._lock:
            if self._bus is None:
                future.set_exception(
                    ArenaError(ErrorCode.PORT_DISCONNECTED, "The servo bus is not connected.")
                )
                return future
            self._jobs.append((job, future))  # type: ignore[arg-type]
        self._wake.set()
        return future

    @property
    def connected(self) -> bool:
        """Whether the bus is up now."""
        return self._bus is not None

    # -- the thread ---------------------------------------------------------------------------

    def _main(self) -> None:
        try:
            self._loop()
        finally:
            cpu = time.thread_time()
            self.stats.thread_cpu = cpu
            self._shutdown()
            if not self.first_connect.done():
                self.first_connect.set_exception(
                    ArenaError(
                        ErrorCode.NO_HARDWARE, "The servo bus was stopped before it connected."
                    )
                )

    def _loop(self) -> None:
        period = 1.0 / self.settings.rate if self.settings.rate > 0 else 0.0
        telemetry_every = (
            max(1, round(self.settings.rate / self.settings.telemetry_rate))
            if self.settings.rate > 0 and self.settings.telemetry_rate > 0
            else 10
        )
        again = False
        self.stats.started = time.monotonic()
        next_cycle = time.monotonic()
        while not self._stopping.is_set():
            if self._bus is None:
                if not self._try_connect(again):
                    self._stopping.wait(self.settings.reconnect_interval)
                    continue
                again = True
                next_cycle = time.monotonic()
            self._run_jobs()
            started = time.monotonic()
            try:
                self._cycle(self.stats.cycles % telemetry_every == 0)
            except BusError as exc:
                self._lose(exc.message)
                continue
            except Exception as exc:  # a bug must not leave the arm with nobody watching
                log.exception("servo bus cycle failed")
                self._lose(f"internal error: {exc!r}")
                continue
            self.stats.cycles += 1
            self.stats.busy += time.monotonic() - started
            if (silent := self.health.lost) is not None:
                self._lose(
                    f"servo {silent} has not answered for {self.settings.limits.lost_after} cycles"
                )
                continue
            if period:
                next_cycle += period
                delay = next_cycle - time.monotonic()
                if delay > 0:
                    try:
                        self._between(next_cycle)
                    except BusError as exc:
                        self._lose(exc.message)
                else:
                    next_cycle = time.monotonic()  # fell behind: do not try to catch up
            self.stats.thread_cpu = time.thread_time()

    def _between(self, until: float) -> None:
        """Wait for the next cycle (`until`, monotonic), running jobs and writing goals as
        they come (at most one write between two cycles: goals that come faster merge, the
        newest wins, as at a cycle)."""
        wrote = False
        while not self._stopping.is_set():
            delay = until - time.monotonic()
            if delay <= 0 or not self._wake.wait(delay):
                return
            self._wake.clear()  # (before looking: a wake after this is seen at the next wait)
            self._run_jobs()
            if self._bus is None:
                return  # (a job lost it: the loop connects again)
            if wrote:
                continue
            with self._lock:
                goals, self._goals = self._goals, None
            if goals:
                self._bus.write_goals(goals)
                wrote = True

    def _try_connect(self, again: bool) -> bool:
        bus = self.open_bus()
        try:
            bus.open()
            torque = self._connect(bus)
            with self._lock:  # from here `submit` queues jobs instead of failing them
                self._bus = bus
            if self.torque_wanted != torque:
                # Changed while connecting (an e-stop's torque-off, say): its job was refused
                # because the bus was away, so it is applied here, before anything else runs.
                self.hold(bus, torque=self.torque_wanted)
        except ArenaError as exc:
            self._bus = None
            self._fail_jobs()
            bus.close()
            if not self.first_connect.done():
                self.first_connect.set_exception(exc)
                self._stopping.set()  # the caller hears why; nothing to retry for
            return False
        for ended in self.health.reset():
            self.listener.event(ended)
        if not self.first_connect.done():
            self.first_connect.set_result(None)
        self.listener.event(Connected(again))
        return True

    def _connect(self, bus: ServoBus) -> bool:
        """Check every servo, then hold each where it is, then torque (if wanted); the torque
        it applied."""
        for servo_id in self.servo_ids:
            model = _ping(bus, servo_id)
            expected = self.settings.models.get(servo_id)
            if expected is not None and model not in expected[0]:
                raise ArenaError(
                    ErrorCode.SERVO_WRONG_MODEL,
                    f"Servo {servo_id} is model {model}, not {expected[1]}.",
                )
        bus.prepare(self.servo_ids, limited=sorted(self.settings.torque_limits))
        bus.set_torque_limits(self.torque_limits)
        self.frames = self.settings.frames(bus) if self.settings.frames else {}
        if self.frames:  # torque or not: a servo a turn away reads wrong values too
            check_frames(read_positions(bus, self.servo_ids), self.frames, self.settings.frame_hint)
        self.clear_goals()  # goals from before the connection are stale
        torque = self.torque_wanted
        self.hold(bus, torque=torque)
        return torque

    def set_torque_limits(self, bus: ServoBus, limits: Mapping[int, float]) -> None:
        """New torque limits (percent by servo id) for the servos named (call it in the worker
        thread); kept for the next connection."""
        bus.set_torque_limits(limits)
        self.torque_limits.update(limits)

    def hold(self, bus: ServoBus, *, torque: bool) -> dict[int, int]:
        """`hold_here` with this arm's speed and frames (call it in the worker thread)."""
        present = hold_here(
            bus,
            self.servo_ids,
            torque=torque,
            speed=self.settings.speed_limit,
            frames=self.frames,
            hint=self.settings.frame_hint,
        )
        self.torqued = torque
        return present

    def _lose(self, reason: str) -> None:
        self.torqued = False
        if self._bus is not None:
            self._bus.close()
            self._bus = None
        self.clear_goals()
        self._fail_jobs()
        self.listener.event(Lost(reason))

    def _cycle(self, telemetry: bool) -> None:
        assert self._bus is not None
        with self._lock:
            goals, self._goals = self._goals, None
        if goals:
            self._bus.write_goals(goals)
        if telemetry:
            values, result = self._bus.read_telemetry(self.servo_ids)
            reading = Reading(
                values.positions,
                time.monotonic(),
                temperatures=values.temperatures,
                loads=values.loads,
                voltages=values.voltages,
                load_percent=values.load_percent,
            )
        else:
            positions, result = self._bus.read_positions(self.servo_ids)
            reading = Reading(positions, time.monotonic())
        if self.rearm_health:
            self.rearm_health = False
            self.health.rearm()
        faults = self.health.on_read(result)
        if reading.temperatures:
            faults += self.health.on_temperatures(reading.temperatures)
        if self.frames and self.torqued:  # (a limp servo is checked at its torque-on)
            faults += self.health.on_frames(reading.positions, self.frames)
        for fault in faults:
            self.listener.event(fault)
        if reading.positions:
            self.listener.reading(reading)

    def _run_jobs(self) -> None:
        with self._lock:
            jobs, self._jobs = self._jobs, []
        for job, future in jobs:
            if not future.set_running_or_notify_cancel():
                continue
            try:
                assert self._bus is not None
                future.set_result(job(self._bus))
            except BusError as exc:
                future.set_exception(exc)
                self._lose(exc.message)
                return
            except Exception as exc:
                future.set_exception(exc)

    def _fail_jobs(self) -> None:
        with self._lock:
            jobs, self._jobs = self._jobs, []
        for _, future in jobs:
            if future.set_running_or_notify_cancel():
                future.set_exception(
                    ArenaError(ErrorCode.PORT_DISCONNECTED, "The servo bus is not connected.")
                )

    def _shutdown(self) -> None:
        self._fail_jobs()
        if self._bus is None:
            return
        with contextlib.suppress(ArenaError):  # a bus that is gone hears nothing anyway
            if self.torque_at_exit is not None:
                self.hold(self._bus, torque=self.torque_at_exit)
            else:
                set_torque(self._bus, self.servo_ids, on=False)
        self._bus.close()
        self._bus = None


def read_positions(bus: ServoBus, servo_ids: Sequence[int]) -> dict[int, int]:
    """Present positions of every servo; `SERVO_TIMEOUT` naming any that did not answer."""
    positions, result = bus.read_positions(servo_ids)
    if result.missing or result.corrupt:
        silent = sorted(result.missing + result.corrupt)
        raise ArenaError(
            ErrorCode.SERVO_TIMEOUT, f"Servo(s) {silent} did not answer the position read."
        )
    return positions


def set_torque(bus: ServoBus, servo_ids: Sequence[int], *, on: bool) -> None:
    """Torque on or off for every servo."""
    bus.set_torque(servo_ids, on=on)


def outside_frames(present: Mapping[int, int], frames: Frames) -> dict[int, int]:
    """The servos (and their readings) outside their frames."""
    return {
        sid: step
        for sid, step in present.items()
        if sid in frames and not frames[sid][0] <= step <= frames[sid][1]
    }


def check_frames(present: Mapping[int, int], frames: Frames, hint: str = "") -> None:
    """`SERVO_OUT_OF_RANGE` naming every servo that reads outside its frame, and its reading."""
    outside = outside_frames(present, frames)
    if outside:
        named = "; ".join(
            f"servo {sid} reads {step} (its frame {frames[sid][0]}..{frames[sid][1]})"
            for sid, step in sorted(outside.items())
        )
        raise ArenaError(
            ErrorCode.SERVO_OUT_OF_RANGE,
            f"{named.capitalize()}: a servo that counts turns is a turn or more away, where "
            f"goals would send it back a whole turn, so its torque stays off. {hint}".strip(),
        )


def hold_here(
    bus: ServoBus,
    servo_ids: Sequence[int],
    *,
    torque: bool,
    speed: int | None = None,
    frames: Frames | None = None,
    hint: str = "",
) -> dict[int, int]:
    """Goal = present for every servo, then torque as asked: nothing jumps. Returns the pose.

    Torque on is refused while a servo reads outside its frame (`frames`): goal = present is
    still written (it stops whatever moves), the servos outside go limp, the others keep their
    torque, and `SERVO_OUT_OF_RANGE` names them.
    """
    present = read_positions(bus, servo_ids)
    outside = outside_frames(present, frames) if torque and frames else {}
    bus.write_goals(present)
    if speed is not None:
        bus.set_speed(servo_ids, speed)
    if outside:
        set_torque(bus, sorted(outside), on=False)
        check_frames(present, frames or {}, hint)
    set_torque(bus, servo_ids, on=torque)
    return present


def store_offsets_in_servos(
    bus: ServoBus, calibration: Calibration, servo_ids: Sequence[int]
) -> Calibration:
    """Move each joint's offset into its servo's Homing_Offset register (EEPROM).

    The servo then reports calibrated steps itself, and the returned calibration carries zero
    offsets. Every offset is checked against the register's range before anything is written.
    """
    ids = [j.servo_id for j in calibration.joints.values() if j.servo_id in servo_ids]
    current = bus.read_homings(ids)
    wanted = {
        joint.servo_id: homing_offset_register(joint.offset, current[joint.servo_id], bus.family)
        for joint in calibration.joints.values()
        if joint.servo_id in current
    }
    for servo_id, homing in wanted.items():
        bus.write_homing(servo_id, homing)
    joints = {
        name: msgspec.structs.replace(joint, offset=0) if joint.servo_id in wanted else joint
        for name, joint in calibration.joints.items()
    }
    return msgspec.structs.replace(calibration, joints=joints, homing_in_servos=True)


#: Pings of one servo before it counts as missing at connect: a reply lost once (a busy
#: adapter, a loaded machine running the simulated bus) must not refuse the whole arm.
PING_ATTEMPTS = 3


def _ping(bus: ServoBus, servo_id: int) -> int:
    """The servo's model number, asked up to `PING_ATTEMPTS` times."""
    for attempt in range(PING_ATTEMPTS):
        try:
            return bus.ping(servo_id)
        except ArenaError as exc:
            if exc.code is not ErrorCode.SERVO_TIMEOUT or attempt == PING_ATTEMPTS - 1:
                raise
    raise AssertionError("unreachable")
