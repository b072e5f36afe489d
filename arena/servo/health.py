"""Servo health, without I/O: which faults to report, and when the bus counts as lost.

Faults are reported on their rising edge (once while they last), so a servo that stays hot
gives one message, not one per control cycle, and their end on the falling edge (a `ServoFault`
with `cleared`), so that what a robot shows of its arm is what lasts.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass

from arena.protocol.errors import ErrorCode, Severity
from arena.servo.interface import FaultBit, SyncReadResult

# Status error bits -> (code, severity, what it means). Overheat, overload and over-current
# are critical: the servo protects itself by dropping torque, so the arm is no longer held.
ERROR_BITS: dict[FaultBit, tuple[ErrorCode, Severity, str]] = {
    FaultBit.OVERHEAT: (ErrorCode.SERVO_OVERHEAT, Severity.CRITICAL, "is overheating"),
    FaultBit.OVERLOAD: (ErrorCode.SERVO_OVERLOAD, Severity.CRITICAL, "is overloaded"),
    FaultBit.OVERCURRENT: (
        ErrorCode.SERVO_OVERCURRENT,
        Severity.CRITICAL,
        "draws too much current",
    ),
    FaultBit.VOLTAGE: (
        ErrorCode.SERVO_VOLTAGE,
        Severity.ERROR,
        "has its supply voltage out of range",
    ),
    FaultBit.ANGLE: (ErrorCode.SERVO_ANGLE, Severity.ERROR, "reports a position sensor error"),
}


@dataclass(frozen=True, slots=True)
class ServoFault:
    """A fault of one servo (or of the bus, `servo_id` None)."""

    code: ErrorCode
    severity: Severity
    servo_id: int | None
    message: str
    cleared: bool = False  # the fault is over (`message` says so)


@dataclass(frozen=True, slots=True)
class HealthLimits:
    """Thresholds: temperatures in degrees C; `lost_after` consecutive failed cycles."""

    hot: float = 55.0
    overheat: float = 65.0
    lost_after: int = 20


class HealthMonitor:
    """Feed it each cycle's read result (and telemetry); it says what to report."""

    def __init__(self, servo_ids: Iterable[int], limits: HealthLimits | None = None) -> None:
        self.servo_ids = tuple(servo_ids)
        self.limits = limits or HealthLimits()
        # (code, servo, source): the same code can come from the error bits and from telemetry.
        self._active: set[tuple[ErrorCode, int | None, str]] = set()
        self._misses: dict[int, int] = dict.fromkeys(self.servo_ids, 0)

    @property
    def lost(self) -> int | None:
        """A servo silent for `lost_after` cycles in a row (the bus counts as lost), or None."""
        for servo_id, misses in self._misses.items():
            if misses >= self.limits.lost_after:
                return servo_id
        return None

    def reset(self) -> list[ServoFault]:
        """Forget everything (after a reconnection): the end of every fault that lasted (what
        still ails the arm is raised again by the next reads)."""
        ended = [
            self._ended(code, servo_id, "the bus connected again")
            for code, servo_id, _ in sorted(self._active, key=str)
        ]
        self._active.clear()
        self._misses = dict.fromkeys(self.servo_ids, 0)
        return ended

    def rearm(self) -> None:
        """Raise again, from the next reads, every fault that still lasts (the robot was reset:
        what it showed was acknowledged and cleared)."""
        self._active.clear()

    def on_read(self, result: SyncReadResult) -> list[ServoFault]:
        """The faults a cycle's read result raises."""
        faults: list[ServoFault] = []
        for servo_id in self.servo_ids:
            if servo_id in result.missing:
                self._misses[servo_id] += 1
                faults += self._edge(
                    True,
                    ErrorCode.SERVO_TIMEOUT,
                    Severity.ERROR,
                    servo_id,
                    f"Servo {servo_id} does not answer; retrying.",
                )
                continue
            if servo_id in result.corrupt:
                faults += self._edge(
                    True,
                    ErrorCode.SERVO_CORRUPT,
                    Severity.WARNING,
                    servo_id,
                    f"Servo {servo_id} sent a garbled answer (bad checksum).",
                )
                continue
            self._misses[servo_id] = 0
            faults += self._edge(False, ErrorCode.SERVO_TIMEOUT, Severity.ERROR, servo_id, "")
            faults += self._edge(False, ErrorCode.SERVO_CORRUPT, Severity.WARNING, servo_id, "")
            bits = FaultBit(result.errors.get(servo_id, 0))
            for bit, (code, severity, what) in ERROR_BITS.items():
                faults += self._edge(
                    bool(bits & bit), code, severity, servo_id, f"Servo {servo_id} {what}."
                )
        return faults

    def on_temperatures(self, temperatures: Mapping[int, float]) -> list[ServoFault]:
        """The faults a telemetry read's temperatures raise."""
        faults: list[ServoFault] = []
        for servo_id, celsius in temperatures.items():
            faults += self._edge(
                celsius >= self.limits.overheat,
                ErrorCode.SERVO_OVERHEAT,
                Severity.CRITICAL,
                servo_id,
                f"Servo {servo_id} is at {celsius:.0f} C (limit {self.limits.overheat:.0f} C).",
                source="temperature",
            )
            faults += self._edge(
                self.limits.hot <= celsius < self.limits.overheat,
                ErrorCode.SERVO_HOT,
                Severity.WARNING,
                servo_id,
                f"Servo {servo_id} is warm: {celsius:.0f} C.",
            )
        return faults

    def on_frames(
        self, positions: Mapping[int, int], frames: Mapping[int, tuple[int, int]]
    ) -> list[ServoFault]:
        """The faults of servos reading outside their frames (`arena.servo.worker.Frames`):
        turned a turn or more away by hand, so that goals would send them back a whole turn."""
        faults: list[ServoFault] = []
        for servo_id, step in positions.items():
            if servo_id not in frames:
                continue
            low, high = frames[servo_id]
            faults += self._edge(
                not low <= step <= high,
                ErrorCode.SERVO_OUT_OF_RANGE,
                Severity.CRITICAL,
                servo_id,
                f"Servo {servo_id} reads {step} (its frame {low}..{high}): a turn or more "
                "away, where goals would send it back a whole turn; turn it back by hand.",
            )
        return faults

    def _edge(
        self,
        active: bool,
        code: ErrorCode,
        severity: Severity,
        servo_id: int | None,
        message: str,
        source: str = "",
    ) -> list[ServoFault]:
        key = (code, servo_id, source)
        if not active:
            if key not in self._active:
                return []
            self._active.discard(key)
            if any(k[:2] == (code, servo_id) for k in self._active):
                return []  # the same code from another source lasts (bits and temperature)
            return [self._ended(code, servo_id, "it is over")]
        if key in self._active:
            return []
        self._active.add(key)
        return [ServoFault(code, severity, servo_id, message)]

    @staticmethod
    def _ended(code: ErrorCode, servo_id: int | None, why: str) -> ServoFault:
        who = "the bus" if servo_id is None else f"Servo {servo_id}"
        return ServoFault(code, Severity.INFO, servo_id, f"{who}: {code} cleared ({why}).", True)
