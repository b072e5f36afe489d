"""The command rate limit (a token bucket) and a joining slave's ramp, pure: time is an
argument everywhere.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

from arena.robot.model import RobotModel


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


class JoinRamp:
    """A measuring slave's own targets while it joins: from where its arm is toward the robot's
    targets, each joint at no more than `speed` deg/s (or its own lower velocity limit).

    For any two targets it gives at times t1 <= t2 (the first compared with the measured
    start), per joint: |x2 - x1| <= speed * (t2 - t1). No burst allowance: a joining arm is
    the one place where the robot does not know that the way is clear, so it never jumps.
    """

    __slots__ = ("_last", "_speeds", "positions")

    def __init__(
        self, model: RobotModel, start: Mapping[str, float], speed: float, now: float
    ) -> None:
        self.positions = {j.name: float(start[j.name]) for j in model.joints}
        self._speeds = {j.name: min(speed, j.max_velocity) for j in model.joints}
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
                continue
            step = self._speeds[name] * elapsed
            self.positions[name] = (
                goal[name] if abs(delta) <= step else position + math.copysign(step, delta)
            )
            changed = changed or step > 0.0
        return dict(self.positions) if changed else None

    def arrived(self, goal: Mapping[str, float]) -> bool:
        """Whether every joint is at `goal`."""
        return all(goal[name] == position for name, position in self.positions.items())
