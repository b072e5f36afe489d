"""The command rate limit (a token bucket) and a joining slave's ramp, pure: time is an
argument everywhere.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

from arena.robot.model import RobotModel
from arena.robot.steps import stopping_speed


class RateLimiter:
    """Token bucket: `rate` commands per second with bursts of up to `burst`."""

    __slots__ = ("_last", "_tokens", "burst", "rate")

    def __init__(self, rate: float, burst: int, now: float) -> None:
        self.rate = rate
        self.burst = float(burst)
        self._tokens = float(burst)
        self._last = now

    def allow(self, now: float) -> bool:
        """Take one token if there is one."""
        tokens = self._tokens
        if now > self._last:  # (no min or max: this runs for every command)
            tokens += (now - self._last) * self.rate
            if tokens > self.burst:
                tokens = self.burst
            self._last = now
        if tokens >= 1.0:
            self._tokens = tokens - 1.0
            return True
        self._tokens = tokens
        return False


#: Degrees within which a joining joint given any time at all lands on its goal (a distance
#: whose braking speed underflows).
LANDING = 1e-12


class JoinRamp:
    """A measuring slave's own targets while it joins: from where its arm is toward the robot's
    targets, each joint at no more than `speed` deg/s (or its own lower velocity limit), its
    velocity changed at no more than the joint's acceleration limit: it starts from rest and
    brakes to land on the robot's pose.

    For any two targets it gives at times t1 <= t2 (the first compared with the measured
    start), per joint: |x2 - x1| <= speed * (t2 - t1), and the velocity between two targets
    differs from the one before by at most the acceleration limit times the time between
    them. No burst allowance: a joining arm is the one place where the robot does not know
    that the way is clear, so it never jumps.
    """

    __slots__ = ("_accels", "_last", "_speeds", "_velocity", "positions")

    def __init__(
        self, model: RobotModel, start: Mapping[str, float], speed: float, now: float
    ) -> None:
        self.positions = {j.name: float(start[j.name]) for j in model.joints}
        self._speeds = {j.name: min(speed, j.max_velocity) for j in model.joints}
        self._accels = {j.name: j.max_acceleration for j in model.joints}
        self._velocity = dict.fromkeys(self.positions, 0.0)
        self._last = now

    def advance(self, goal: Mapping[str, float], now: float) -> dict[str, float] | None:
        """Step every joint toward `goal` (the robot's targets now) by what the time since
        the last step allows. Returns the new targets, or None if nothing moved."""
        elapsed = max(0.0, now - self._last)
        self._last = now
        changed = False
        for name, position in self.positions.items():
            delta = goal[name] - position
            if delta == 0.0:
                self._velocity[name] = 0.0
                continue
            # The speed from which braking at the acceleration limit, step by step, stops on
            # the goal (`steps.stopping_speed`, as a held-back stream's), and no more than that
            # limit's change from the last step's.
            accel, was = self._accels[name], self._velocity[name]
            stop = stopping_speed(abs(delta), accel, elapsed)
            wanted = math.copysign(min(self._speeds[name], stop), delta)
            change = accel * elapsed
            velocity = max(was - change, min(was + change, wanted))
            step = velocity * elapsed
            if elapsed and (
                abs(delta) <= LANDING or (step * delta > 0.0 and abs(step) >= abs(delta))
            ):
                # (it gets there, or is within float dust of it: land on it)
                self.positions[name], self._velocity[name] = goal[name], 0.0
            else:
                self.positions[name], self._velocity[name] = position + step, velocity
            changed = changed or self.positions[name] != position
        return dict(self.positions) if changed else None

    def arrived(self, goal: Mapping[str, float]) -> bool:
        """Whether every joint is at `goal`."""
        return all(goal[name] == position for name, position in self.positions.items())
