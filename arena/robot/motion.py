"""Motion safety, pure: command validation, clamping, velocity limits, interpolation, rate limits.

Every target that reaches a slave comes out of `MotionLimiter.advance`. Its guarantee, per joint,
for any two targets it emits at times t1 <= t2:

    |x2 - x1| <= v * (t2 - t1) + v * velocity_burst

where v is the joint's velocity limit (or the lower `speed` a command asked for). A small step
inside that budget goes out at once; a larger one is spread over the following control ticks.
A command in the middle of a master's burst (`advance(now, fresh=True)`) moves at once only
the joints it finds at rest; a joint still on its way to an earlier goal (trailing a master
faster than it may move) is left to the ticks. Emitting a sliver of motion per command while
a joint trails gave a master streaming 10,000 commands a second as many targets (each checked
by the collision guard, recorded and offered to the slaves, which keep only the newest) for no
motion the ticks would not give. Outside a burst every command moves every joint it can at
once: the slave hears of it without waiting for a tick.
Time is an argument everywhere (seconds, any monotonic origin): nothing here reads a clock.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping

import msgspec

from arena.protocol.errors import ArenaError, ErrorCode
from arena.protocol.messages import ClampInfo, JointValue
from arena.robot.model import RobotModel

#: One joint's requested value in wire degrees, with an optional speed cap in deg/s: the
#: wire's own type, so a command off the wire (or out of a recording) keeps its joints as
#: they were decoded.
JointGoal = JointValue


class Command(msgspec.Struct, frozen=True, gc=False):
    """A request to move some joints; `duration` (seconds) asks for a smooth move over that time."""

    joints: tuple[JointGoal, ...]
    duration: float | None = None
    source: str | None = None  # free-form label (the wire's metadata.source)

    @classmethod
    def of(cls, values: Mapping[str, float], duration: float | None = None) -> Command:
        """Shorthand: `Command.of({"Rotation": 45})`."""
        return cls(tuple(JointGoal(n, v) for n, v in values.items()), duration)


#: A requested value that was outside the limits and what was applied instead: the wire's
#: own type, so an acknowledgment and a record carry a command's clamps as they are.
Clamp = ClampInfo


class CommandResult(msgspec.Struct, frozen=True, gc=False):
    """The answer to a command: accepted (maybe clamped) or refused with a code."""

    accepted: bool
    code: ErrorCode | None = None
    message: str = ""
    clamped: tuple[Clamp, ...] = ()

    @classmethod
    def refused(cls, code: ErrorCode, message: str) -> CommandResult:
        """A refusal."""
        return cls(False, code, message)


class ResolvedGoal(msgspec.Struct, frozen=True, gc=False):
    """A validated goal: protocol joint name, value inside the limits, effective speed."""

    name: str
    value: float
    speed: float


def resolve_command(model: RobotModel, command: Command) -> tuple[list[ResolvedGoal], list[Clamp]]:
    """Validate a command against the model.

    Unknown joints, non-finite values, bad speeds or durations raise `ArenaError`; values outside
    the limits are clamped and listed. Names come back as protocol names (aliases resolved).
    """
    if not command.joints:
        raise ArenaError(ErrorCode.EMPTY_COMMAND, "The command names no joints.")
    if command.duration is not None and not (
        math.isfinite(command.duration) and command.duration >= 0
    ):
        raise ArenaError(ErrorCode.INVALID_VALUE, "duration must be a finite number >= 0.")
    goals: list[ResolvedGoal] = []
    clamps: list[Clamp] = []
    seen: set[str] = set()
    for goal in command.joints:
        spec = model.joint(goal.name)
        if spec is None:
            known = ", ".join(model.joint_names)
            raise ArenaError(
                ErrorCode.UNKNOWN_JOINT, f"Unknown joint {goal.name!r}; this robot has {known}."
            )
        if spec.name in seen:
            raise ArenaError(ErrorCode.INVALID_VALUE, f"Joint {spec.name!r} is named twice.")
        seen.add(spec.name)
        requested = goal.value
        if not _is_finite_number(requested):
            raise ArenaError(
                ErrorCode.INVALID_VALUE,
                f"Joint {spec.name!r}: value must be a finite number of degrees.",
            )
        speed = spec.max_velocity
        if goal.speed is not None:
            if not _is_finite_number(goal.speed) or goal.speed <= 0:
                raise ArenaError(
                    ErrorCode.INVALID_VALUE,
                    f"Joint {spec.name!r}: speed must be a positive number (deg/s).",
                )
            speed = min(speed, float(goal.speed))
        requested = float(requested)
        value = spec.clamp(requested)
        if value != requested:
            clamps.append(Clamp(spec.name, requested, value))
        goals.append(ResolvedGoal(spec.name, value, speed))
    return goals, clamps


def _is_finite_number(value: object) -> bool:
    if type(value) is float:  # what the wire decodes to: one check, per command
        return math.isfinite(value)
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def min_jerk(fraction: float) -> float:
    """Smooth 0..1 progress with zero velocity and acceleration at both ends."""
    f = min(1.0, max(0.0, fraction))
    return f * f * f * (10.0 + f * (-15.0 + 6.0 * f))


class _JointMotion:
    """One joint's emitted position, goal and velocity budget.

    The budget refills lazily: `tokens` is what was left at `stamp`, and `refill` brings it up
    to date only for a joint that is about to spend or change it, so an idle joint costs nothing
    per command. Saturating refills add up exactly, so the budget is the same either way.
    """

    __slots__ = ("cap", "goal", "position", "profile", "speed", "stamp", "tokens")

    def __init__(self, position: float, limit: float, burst: float, now: float) -> None:
        self.position = position
        self.goal = position
        self.speed = limit  # effective cap for the current move (the joint's limit at first)
        self.cap = limit * burst  # the most degrees the budget can hold at `speed`
        self.tokens = self.cap  # degrees that may be emitted at `stamp`
        self.stamp = now
        self.profile: tuple[float, float, float] | None = None  # (start, t0, duration)

    def refill(self, now: float) -> None:
        if now > self.stamp:
            self.tokens = min(self.cap, self.tokens + self.speed * (now - self.stamp))
            self.stamp = now

    def desired(self, now: float) -> float:
        if self.profile is None:
            return self.goal
        start, t0, duration = self.profile
        if now >= t0 + duration:
            return self.goal
        return start + (self.goal - start) * min_jerk((now - t0) / duration)


class MotionLimiter:
    """Turns goals into a stream of velocity-limited targets for the slaves."""

    def __init__(
        self, model: RobotModel, now: float, initial: Mapping[str, float] | None = None
    ) -> None:
        self._burst = model.safety.velocity_burst
        self._clamps = {j.name: j.clamp for j in model.joints}
        start = dict(initial or {})
        self._joints = {
            j.name: _JointMotion(j.clamp(start.get(j.name, 0.0)), j.max_velocity, self._burst, now)
            for j in model.joints
        }
        # Every joint's goal, kept as the joints' change: the guard copies it for each command.
        self._goals = {name: m.goal for name, m in self._joints.items()}
        self._moving: bool | None = False  # None: not known since the goals last changed
        # Joints the last `set_goals` aimed that were at rest: what a command moves at once.
        self._fresh: list[_JointMotion] = []

    @property
    def positions(self) -> dict[str, float]:
        """The last emitted target of every joint (the virtual values)."""
        return {name: m.position for name, m in self._joints.items()}

    @property
    def goals(self) -> dict[str, float]:
        """Where every joint is heading."""
        return self._goals.copy()

    @property
    def moving(self) -> bool:
        """True while some joint has not reached its goal (ticks are needed)."""
        if self._moving is None:
            self._moving = any(
                m.position != m.goal or m.profile is not None for m in self._joints.values()
            )
        return self._moving

    def set_goals(self, goals: Iterable[ResolvedGoal], duration: float | None, now: float) -> None:
        """Aim joints at new goals; with `duration`, follow a smooth curve over that time.
        `advance(now, fresh=True)` then moves the joints that were at rest."""
        fresh = self._fresh = []
        for goal in goals:
            motion = self._joints[goal.name]
            if motion.position == motion.goal and motion.profile is None:
                fresh.append(motion)
            motion.refill(now)  # what was earned so far, at the old speed
            motion.goal = self._goals[goal.name] = goal.value
            motion.speed = goal.speed
            motion.cap = goal.speed * self._burst
            motion.tokens = min(motion.tokens, motion.cap)
            motion.profile = (motion.position, now, duration) if duration else None
        self._moving = None

    def advance(self, now: float, *, fresh: bool = False) -> dict[str, float] | None:
        """Move every joint as far toward its goal as its budget allows (with `fresh`, only
        the joints the last `set_goals` found at rest: a command's own step).

        Returns the full target vector if any joint moved, else None.
        """
        changed = moving = False
        for motion in self._fresh if fresh else self._joints.values():
            # (`desired` inlined for a move without a curve: this runs per joint and command)
            desired = motion.goal if motion.profile is None else motion.desired(now)
            delta = desired - motion.position
            if delta != 0.0:
                motion.refill(now)
                if abs(delta) <= motion.tokens:
                    motion.position = desired
                    motion.tokens -= abs(delta)
                else:
                    motion.position += math.copysign(motion.tokens, delta)
                    motion.tokens = 0.0
                changed = True
            if motion.profile is not None:
                if motion.position == motion.goal and now >= motion.profile[1] + motion.profile[2]:
                    motion.profile = None
                else:
                    moving = True
            elif motion.position != motion.goal:
                moving = True
        self._moving = None if fresh else moving  # `fresh` saw only some joints
        return self.positions if changed else None

    def stop_at(self, positions: Mapping[str, float]) -> None:
        """Stop every joint at `positions` (targets already sent): the way on was unsafe."""
        for name, motion in self._joints.items():
            motion.position = motion.goal = self._goals[name] = positions[name]
            motion.profile = None
        self._moving = False

    def adopt(self, pose: Mapping[str, float]) -> dict[str, float]:
        """Take `pose` (every joint, clamped to its limits) as where each joint is: the robot
        learns where its arm is. A joint at rest stays there (its goal becomes that value);
        a joint that a command is moving goes on to its goal from there, velocity-limited
        (the command asked for that joint to move; a curve it was on is dropped). Returns
        the pose taken."""
        for name, motion in self._joints.items():
            value = self._clamps[name](float(pose[name]))
            if motion.position == motion.goal and motion.profile is None:
                motion.goal = self._goals[name] = value
            motion.position = value
            motion.profile = None
        self._moving = None
        return self.positions

    def freeze(self) -> None:
        """Stop every joint where it is: goals become the current targets."""
        for name, motion in self._joints.items():
            motion.goal = self._goals[name] = motion.position
            motion.profile = None
        self._moving = False


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
