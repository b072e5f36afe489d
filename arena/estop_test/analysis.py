"""What an e-stop did, from timestamps and joint samples: pure functions, no I/O, no clock.

The live test (`live.py`) and the offline check of a recording both come here with the same
kinds of evidence: when the stop was triggered, when the robot said it was e-stopped, the
targets a slave received and when it got its stop notice, and the measured joint values
around the stop. From them: the delays, the stopping time and distance of each joint (until
it stays within `threshold` degrees of where it came to rest), whether anything was sent or
moved after the stop, the percentiles of each measure over the trials, and the limits broken.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

#: A measured pose: (seconds on the tester's clock, joint -> degrees).
Sample = tuple[float, Mapping[str, float]]
#: The measures of a trial that have percentiles and limits, in milliseconds or degrees.
MEASURES = (
    "estopped_ms",
    "last_target_ms",
    "stop_notice_ms",
    "stopping_time_ms",
    "stopping_distance_deg",
)
STATISTICS = ("p50", "p99", "max")
#: Seconds a joint must stay within the threshold for its motion to count as over.
STILL_FOR = 0.2


@dataclass(frozen=True, slots=True)
class JointStop:
    """How one joint stopped: time from the trigger to rest, and how far it went meanwhile
    (the largest excursion from where it was at the trigger, overshoot included)."""

    time_ms: float
    distance_deg: float
    at_rest: bool  # it stayed still for STILL_FOR before the samples ended


def joint_stops(
    samples: Sequence[Sample], trigger: float, threshold: float, until: float
) -> dict[str, JointStop]:
    """Each joint's stop, from samples in time order that span the trigger, watched until
    `until` (a pose that stopped changing is sent no more: silence is rest).

    A joint is at rest from the first sample after which it never leaves `threshold` degrees
    of its last value; without a sample at or before the trigger, the first after it stands
    for the pose at the trigger.
    """
    after = [(t, pose) for t, pose in samples if t > trigger]
    before = [pose for t, pose in samples if t <= trigger]
    if not after:
        return {}
    start = before[-1] if before else after[0][1]
    stops: dict[str, JointStop] = {}
    for joint, origin in start.items():
        series = [(t, pose[joint]) for t, pose in after if joint in pose]
        if not series:
            continue
        final = series[-1][1]
        rest = len(series) - 1
        while rest > 0 and abs(series[rest - 1][1] - final) <= threshold:
            rest -= 1
        rested_at = trigger if rest == 0 and abs(origin - final) <= threshold else series[rest][0]
        excursion = max(abs(value - origin) for _, value in series[: rest + 1])
        stops[joint] = JointStop(
            time_ms=(rested_at - trigger) * 1000.0,
            distance_deg=excursion,
            at_rest=until - rested_at >= STILL_FOR,
        )
    return stops


@dataclass
class Trial:
    """One stop: what triggered it and what was measured (None: not observed)."""

    path: str
    estopped_ms: float | None = None
    last_target_ms: float | None = None  # the last target any slave got after the trigger
    stop_notice_ms: float | None = None
    sent_after_stop: int = 0  # targets a slave got after its stop notice
    joints: dict[str, JointStop] = field(default_factory=dict)
    error: str | None = None  # the stop did not happen as it should (no e-stop, ...)
    #: (seconds from the trigger, joint -> degrees) for plots
    trace: list[tuple[float, dict[str, float]]] = field(default_factory=list)

    @property
    def stopping_time_ms(self) -> float | None:
        """The slowest joint's stopping time."""
        return max((s.time_ms for s in self.joints.values()), default=None)

    @property
    def stopping_distance_deg(self) -> float | None:
        """The farthest any joint went after the trigger."""
        return max((s.distance_deg for s in self.joints.values()), default=None)

    @property
    def moved_after_stop(self) -> bool:
        """A target went out after the stop notice, or a joint was still moving at the end."""
        return self.sent_after_stop > 0 or any(not s.at_rest for s in self.joints.values())

    def measure(self, name: str) -> float | None:
        """A measure of `MEASURES` by name."""
        value = getattr(self, name)
        return None if value is None else float(value)

    def to_json(self) -> dict[str, Any]:
        """Everything about the trial, for `--json`."""
        return {
            **{name: self.measure(name) for name in MEASURES},
            "sent_after_stop": self.sent_after_stop,
            "moved_after_stop": self.moved_after_stop,
            "joints": {
                joint: {"time_ms": s.time_ms, "distance_deg": s.distance_deg, "at_rest": s.at_rest}
                for joint, s in self.joints.items()
            },
            "error": self.error,
        }


def stop_trial(
    path: str,
    trigger: float,
    *,
    estopped: float | None,
    notice: float | None,
    targets: Iterable[float],
    samples: Sequence[Sample],
    threshold: float,
    until: float,
) -> Trial:
    """A trial from its evidence: every time on one clock, `targets` the arrival times of
    targets at the slave that watches, `until` the end of the watch."""
    arrivals = sorted(targets)
    after_trigger = [t for t in arrivals if t >= trigger]
    trial = Trial(
        path,
        estopped_ms=None if estopped is None else (estopped - trigger) * 1000.0,
        stop_notice_ms=None if notice is None else (notice - trigger) * 1000.0,
        last_target_ms=(after_trigger[-1] - trigger) * 1000.0 if after_trigger else 0.0,
        sent_after_stop=0 if notice is None else sum(t > notice for t in arrivals),
        joints=joint_stops(samples, trigger, threshold, until),
        trace=[(t - trigger, dict(pose)) for t, pose in samples],
    )
    if samples:  # the pose holds until the end of the watch (an unchanged pose is not sent)
        trial.trace.append((until - trigger, dict(samples[-1][1])))
    if estopped is None:
        trial.error = "the robot never said it was e-stopped"
    elif notice is None:
        trial.error = "the watching slave got no stop notice"
    return trial


def percentile(values: Sequence[float], q: float) -> float:
    """The nearest-rank percentile `q` (0-100) of values (not empty)."""
    ordered = sorted(values)
    rank = max(1, math.ceil(q / 100.0 * len(ordered)))
    return ordered[rank - 1]


def summarize(trials: Sequence[Trial]) -> dict[str, dict[str, float]]:
    """p50, p99 and max of every measure observed in the trials."""
    summary: dict[str, dict[str, float]] = {}
    for name in MEASURES:
        values = [v for v in (trial.measure(name) for trial in trials) if v is not None]
        if values:
            summary[name] = {
                "p50": percentile(values, 50),
                "p99": percentile(values, 99),
                "max": max(values),
            }
    return summary


@dataclass(frozen=True, slots=True)
class Breach:
    """A figure over its limit, or a stop that did not stop."""

    path: str
    what: str  # "estopped_ms.p99", "moved_after_stop", "error"
    value: float | str
    limit: float | None

    def __str__(self) -> str:
        if self.limit is None:
            return f"{self.path}: {self.what}: {self.value}"
        return f"{self.path}: {self.what} = {self.value:.3f} over the limit {self.limit:g}"


def load_limits(path: Path) -> dict[str, dict[str, float]]:
    """Limits from a TOML file: a table per stop path (`"*"` for every path) of
    `"<measure>.<statistic>" = bound`, e.g. `"estopped_ms.p99" = 20`.

    Raises ValueError naming what is wrong.
    """
    data = tomllib.loads(path.read_text(encoding="utf-8"))
    limits: dict[str, dict[str, float]] = {}
    for table, entries in data.items():
        if not isinstance(entries, dict):
            raise ValueError(f"[{table}] must be a table of limits")
        for key, bound in entries.items():
            measure, _, statistic = key.partition(".")
            if measure not in MEASURES or statistic not in STATISTICS:
                raise ValueError(
                    f"[{table}] {key!r}: expected <measure>.<statistic> with a measure of "
                    f"{', '.join(MEASURES)} and a statistic of {', '.join(STATISTICS)}"
                )
            if isinstance(bound, bool) or not isinstance(bound, int | float):
                raise ValueError(f"[{table}] {key!r} must be a number")
            limits.setdefault(table, {})[key] = float(bound)
    return limits


def breaches(
    path: str, trials: Sequence[Trial], limits: Mapping[str, Mapping[str, float]]
) -> list[Breach]:
    """Everything wrong with one stop path's trials: errors, motion after the stop, and
    figures over the limits of its table (or of `"*"`)."""
    found = [Breach(path, "error", t.error, None) for t in trials if t.error]
    moved = sum(t.moved_after_stop for t in trials)
    if moved:
        found.append(Breach(path, "moved_after_stop", f"in {moved} of {len(trials)} trials", None))
    summary = summarize(trials)
    bounds = {**limits.get("*", {}), **limits.get(path, {})}
    for key, bound in bounds.items():
        measure, _, statistic = key.partition(".")
        value = summary.get(measure, {}).get(statistic)
        if value is not None and value > bound:
            found.append(Breach(path, key, value, bound))
    return found


def recorded_stops(
    messages: Sequence[Any], *, threshold: float, window: float = 2.0
) -> dict[str, list[Trial]]:
    """Every e-stop in a recording's messages (`RecordedMessage`s, in log order), per robot:
    targets recorded while it stayed e-stopped (there must be none) and how the measured
    joints came to rest within `window` seconds (until the reset, if sooner).

    Times are the records' `t` (the robot's clock); the recording has no trigger or slave
    notice, so the e-stop's own record stands for both."""
    by_robot: dict[str, list[Any]] = {}
    for message in messages:
        by_robot.setdefault(message.robot_id, []).append(message)
    found: dict[str, list[Trial]] = {}
    for robot_id, records in by_robot.items():
        states = [m for m in records if m.kind == "state"]
        for number, state in enumerate(states):
            if state.data["mode"] != "estopped":
                continue
            start = float(state.data["t"])
            later = [float(s.data["t"]) for s in states[number + 1 :]]
            end = min([start + window, *later])
            sent = [
                float(m.data["t"])
                for m in records
                if m.kind == "targets" and start < float(m.data["t"]) <= end
            ]
            samples = _recorded_samples(records, start - window, end)
            trial = stop_trial(
                f"{robot_id}: {state.data.get('estop_reason') or state.data['cause']}",
                start,
                estopped=start,
                notice=start,
                targets=sent,
                samples=samples,
                threshold=threshold,
                until=end,
            )
            trial.stop_notice_ms = None  # not in a recording
            found.setdefault(robot_id, []).append(trial)
    return found


def _recorded_samples(records: Sequence[Any], start: float, end: float) -> list[Sample]:
    """Joint states between two times; with several slaves, joints are named `slave/joint`."""
    states = [m.data for m in records if m.kind == "joint_states"]
    slaves = {data["slave_id"] for data in states}
    samples: list[Sample] = []
    for data in states:
        t = float(data["t"])
        if start <= t <= end:
            joints = data["joints"]
            if len(slaves) > 1:
                joints = {f"{data['slave_id']}/{name}": v for name, v in joints.items()}
            samples.append((t, joints))
    return samples
