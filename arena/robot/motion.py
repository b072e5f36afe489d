"""Motion safety, pure: command validation, clamping, jerk-limited trajectories, rate limits.

Every target that reaches a slave comes out of `MotionLimiter.advance`: a sample of one online
trajectory (Ruckig) limited per joint in velocity, acceleration and jerk, planned afresh from
where the joints are and how fast they move whenever a goal changes. Tested on the targets
emitted at the control rate: no finite-difference acceleration or jerk above its limit (within
the tolerance tests/test_motion_trajectory.py states). See specs/motion.md.
Time is an argument everywhere (seconds, any monotonic origin): nothing here reads a clock.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping

import msgspec
from ruckig import (
    InputParameter,
    Ruckig,
    RuckigError,
    Synchronization,
    Trajectory,
)

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
    #: When the values were true, on the robot's clock, if the master knows it (a leader
    #: arm: its bus read, before the command arrived by the bus's and the loop's delays):
    #: a stream's velocity and line are taken from it (`MotionLimiter.set_goals`).
    stamp: float | None = None

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


#: Seconds within which a trajectory counts as at its end: a tick that falls on the end in
#: real arithmetic lands on either side of it in floating point (a replay's times are the
#: recording's, rounded), and must arrive all the same.
EPSILON = 1e-9
#: Seconds between two goals of a joint up to which they are taken as one stream (a leader arm,
#: a policy, a slider dragged), followed through them at the stream's own velocity; goals
#: further apart are steps, reached at rest.
STREAM_WINDOW = 0.1
#: A stream is followed at up to this share of the joint's speed cap (Ruckig refuses a target
#: velocity at the cap itself; the headroom lets a joint that trails catch up).
STREAM_SHARE = 0.9
#: A stream's next goal is overdue this many of its intervals after its last: the trajectory,
#: coasting at the stream's velocity since it met the last goal, then comes to rest on it.
OVERDUE = 1.5
#: Control ticks within which a stream's trajectory is planned to be back on the stream's
#: line (its last goal, carried on at its velocity): short, so the lag stays small; long
#: enough that a correction keeps inside the acceleration and jerk limits (`_follow`).
HORIZON_TICKS = 2
#: The oldest a command's `stamp` is taken to be (seconds before it arrived): a master's
#: clock that is off cannot throw the stream's line further than this.
MAX_AGE = 0.05


class MotionLimiter:
    """Turns goals into a jerk-limited trajectory for the slaves (Ruckig; specs/motion.md).

    Every joint's targets follow one trajectory limited per joint in velocity (the joint's
    limit, or a command's lower `speed`), acceleration and jerk (`JointSpec.max_acceleration`,
    `max_jerk`), planned from where the trajectory is and how fast it moves there: a new goal
    mid-motion bends it, and the velocity never steps. A step (a goal after a pause) is reached
    at rest, all joints arriving together on the straight line in joint space the collision
    guard checked (Ruckig's phase synchronization). A stream of goals (each within
    `STREAM_WINDOW` of the last: a leader arm, a policy) is followed, not stopped at: each goal
    is met as soon as the limits allow at the stream's own velocity (from the last two goals),
    the trajectory coasts on at that velocity until the next goal bends it, and comes to rest
    on the last goal when the stream's next is overdue (`OVERDUE`).

    Costs: a robot at rest costs nothing per tick (no tick is asked for), and a move small
    enough to be made within one tick from rest (`reach`: the jerk-limited distance of one
    tick) is one target without planning; everything else is one Ruckig plan per new goal
    and one sample per tick.

    Targets lead the clock by one control tick: what is emitted at `now` is the trajectory at
    `now + 1 / control_rate`, so a command's first step goes out with the command. `freeze`
    and `stop_at` stop at once (an e-stop's hold, a collision ahead): nothing is smoother
    than safe. Time is an argument everywhere (seconds, any monotonic origin).
    """

    def __init__(
        self, model: RobotModel, now: float, initial: Mapping[str, float] | None = None
    ) -> None:
        self._names = tuple(j.name for j in model.joints)
        self._index = {name: k for k, name in enumerate(self._names)}
        self._clamps = {j.name: j.clamp for j in model.joints}
        self._bounds = tuple((j.lower, j.upper) for j in model.joints)
        self._lead = lead = 1.0 / model.safety.control_rate
        dofs = len(self._names)
        self._otg = Ruckig(dofs)
        self._input = InputParameter(dofs)
        self._input.synchronization = Synchronization.Phase  # the straight line in joint space
        self._input.max_acceleration = [j.max_acceleration for j in model.joints]
        self._input.max_jerk = [j.max_jerk for j in model.joints]
        self._accel = tuple(j.max_acceleration for j in model.joints)
        self._jerk = tuple(j.max_jerk for j in model.joints)
        #: Per joint, the distance a jerk-limited move from rest to rest covers in one tick
        #: (jerk j T^3/32, peak acceleration j T/4 <= a, peak velocity j T^2/16 <= v): a
        #: move no longer than this is made in one target, without a plan (`_jump`).
        self._reach = tuple(
            min(
                j.max_jerk * lead**3 / 32,
                j.max_acceleration * lead**2 / 8,
                j.max_velocity * lead / 2,
            )
            for j in model.joints
        )
        self._reaches = tuple(zip(self._names, self._reach, strict=True))
        self._zeros = [0.0] * dofs
        start = dict(initial or {})
        self._position = {j.name: j.clamp(float(start.get(j.name, 0.0))) for j in model.joints}
        self._goals = self._position.copy()
        self._speeds = [j.max_velocity for j in model.joints]  # caps of the move under way
        self._stamps = [-math.inf] * dofs  # when each joint's goal was last set
        self._duration: float | None = None  # a timed move's least duration, until planned
        # The stream being followed: the goals before the newest (`_origin`, None when the
        # goals are steps), the time between them, and the sample time at which the stream's
        # next goal is overdue.
        self._origin: list[float] | None = None
        self._interval = 0.0
        self._stamp = 0.0  # when the stream's newest goal was true
        self._true_at = -math.inf  # when the newest goals were true
        self._due = 0.0
        self._planned = True  # the trajectory meets the newest goals
        self._trajectory: Trajectory | None = None  # None: every joint rests at its target
        # A stream tracked (`_track`): the last emitted targets' sample time, and every
        # joint's position, velocity and acceleration there.
        self._tracking = False
        self._new_goal = False  # a goal came since the last targets
        self._tt = 0.0
        self._th = (0.0, 0.0)  # the last two steps' lengths (seconds)
        self._tp = [0.0] * dofs
        self._tv = [0.0] * dofs
        self._ta = [0.0] * dofs
        # Two trajectories, planned into in turn: the one in use is never overwritten (its
        # state is where the next plan starts), and a plan allocates none.
        self._pair = (Trajectory(dofs), Trajectory(dofs))
        self._which = 0
        self._t0 = 0.0  # sample time at which the trajectory starts
        self._sampled = -math.inf  # sample time of the last emitted targets
        self._fresh = False  # the last `set_goals` found every joint at rest
        #: Trajectories planned (benchmarks and tests count them), and how many of them a
        #: stream's timing made Ruckig fail, planned again as steps; moves made in one target.
        self.plans = 0
        self.fallbacks = 0
        self.jumps = 0

    @property
    def positions(self) -> dict[str, float]:
        """The last emitted target of every joint (the virtual values)."""
        return self._position.copy()

    @property
    def goals(self) -> dict[str, float]:
        """Where every joint is heading."""
        return self._goals.copy()

    @property
    def moving(self) -> bool:
        """True while some joint has not reached its goal (ticks are needed)."""
        return self._trajectory is not None or self._tracking or not self._planned

    def set_goals(
        self,
        goals: Iterable[ResolvedGoal],
        duration: float | None,
        now: float,
        stamp: float | None = None,
    ) -> None:
        """Aim joints at new goals (with `duration`, reached in no less than that time). The
        trajectory is planned by the next `advance`: a burst of commands plans once.
        `advance(now, fresh=True)` moves at once only a robot that was at rest. `stamp`: when
        the goals were true (a leader's read; at most `MAX_AGE` before `now`), else `now`."""
        self._fresh = self._trajectory is None and not self._tracking and self._planned
        targets = self._goals
        origin = list(targets.values())  # (the goals before these, in the joints' order)
        index, stamps, speeds = self._index, self._stamps, self._speeds
        stream = duration is None
        interval = 0.0
        for goal in goals:
            k = index[goal.name]
            elapsed = now - stamps[k]
            stamps[k] = now
            targets[goal.name] = goal.value
            speeds[k] = goal.speed
            if 0.0 < elapsed <= STREAM_WINDOW:
                if elapsed > interval:
                    interval = elapsed
            else:
                stream = False
        true_at = now if stamp is None else min(now, max(now - MAX_AGE, stamp))
        if stream and interval > 0.0:
            self._origin = origin
            # the stream's pace by when its goals were true, where it is known
            between = true_at - self._true_at
            self._interval = between if stamp is not None and between > 0.0 else interval
            self._stamp = true_at
            self._due = now + self._lead + OVERDUE * interval
        else:
            self._origin = None
        self._true_at = true_at
        self._duration = duration
        self._planned = False
        self._new_goal = True

    def advance(
        self, now: float, *, fresh: bool = False, tick: bool = False
    ) -> dict[str, float] | None:
        """The trajectory's targets for `now` (see the class docstring); with `fresh` (a
        command in the middle of a burst) only if the robot was at rest: a robot already on
        its way takes the newest goals at its next tick. A `tick` within half a tick of the
        last targets (a command's) sends none: a stream's targets stay about a tick apart
        instead of a command's and a tick's a few milliseconds apart (a third fewer targets
        for a 50 Hz stream, at no cost in lag).

        Returns the full target vector if any joint moved, else None.
        """
        if fresh and not self._fresh:
            return None
        sample = now + self._lead
        if not self._planned:
            if self._trajectory is None and not self._tracking and self._jump():
                self._sampled = max(self._sampled, sample)
                return self._position.copy()
            if not self._planned:
                self._plan(max(self._sampled, now))
        if sample <= self._sampled or (tick and sample - self._sampled < 0.5 * self._lead):
            return None
        if self._tracking:
            if not self._new_goal and self._origin is not None and sample < self._due:
                return None  # (a stream on time: its next goal, not a guess, moves it on)
            if sample - self._tt < 0.5 * self._lead:
                return None  # (a step this short measures rounding: the next tick takes it)
            targets = self._track(sample)
        elif self._trajectory is None:  # at rest: on the goals (a plan found it there)
            if self._position == self._goals:
                return None
            self._position.update(self._goals)
            self._sampled = sample
            return self._position.copy()
        else:
            targets = self._sample(sample)
        self._sampled = sample
        position = self._position
        changed = False
        for name, value in zip(self._names, targets, strict=True):
            if position[name] != value:
                position[name] = value
                changed = True
        return position.copy() if changed else None

    def _track(self, at: float) -> list[float]:
        """A stream's targets at sample time `at`: each joint's goal itself when reaching it
        there keeps the joint within its velocity, acceleration and jerk limits (a person's
        hand on a leader, a policy's smooth actions: passed on as they come, no lag added);
        otherwise as close as the limits allow, never faster than stopping on the goal allows
        (a stream that jumps is approached without overshoot; one that stops dead is braked
        at the acceleration limit, past its goal and back). Rests, and the tracking ends, once
        every joint is on its goal at rest."""
        h = at - self._tt
        p, v, a = self._tp, self._tv, self._ta
        h1, h0 = self._th  # the last two steps' lengths
        speeds, accel, jerk = self._speeds, self._accel, self._jerk
        rest = True
        for k, name in enumerate(self._names):
            goal = self._goals[name]
            x, u, w = p[k], v[k], a[k]
            cap, limit = speeds[k], accel[k]
            # The limits as the divided differences of the targets measure them: linear in
            # the new target, so an interval of velocities for this step.
            spread = jerk[k] * (h0 + h1 + h) / 3.0
            low_a, high_a = max(-limit, w - spread), min(limit, w + spread)
            half = (h1 + h) / 2.0
            low = max(-cap, u + low_a * half)
            high = min(cap, u + high_a * half)
            if low > high:  # (over the cap at once: the acceleration bound wins)
                low = high = max(u + low_a * half, min(u + high_a * half, 0.0))
            want = (goal - x) / h
            if not low <= want <= high:
                d = goal - x
                brake = limit * h
                stop = brake * (math.sqrt(0.25 + 2.0 * abs(d) / (brake * h)) - 0.5)
                want = max(low, min(high, math.copysign(min(cap, stop), d)))
            p[k] = goal if want == (goal - x) / h else x + want * h
            a[k] = (want - u) / half
            v[k] = want
            if p[k] != goal or v[k] != 0.0 or a[k] != 0.0:
                rest = False
        self._th = (h, h1)
        self._tt = at
        self._new_goal = False
        if rest:
            self._tracking = False
            self._origin = None
        return list(p)

    def _jump(self) -> bool:
        """From rest, goals within one tick's `reach` of every joint's target: taken in one
        target (what a full plan would give within a tick), planned no further. The
        fleet's tiny moves and a stream's last creep cost no plan and no tick."""
        self._planned = True
        position, goals = self._position, self._goals
        if position == goals:
            self._origin = None
            return False  # (nothing to move: at rest on the goals already)
        for name, reach in self._reaches:
            delta = goals[name] - position[name]
            if delta > reach or -delta > reach:
                self._planned = False
                return False
        position.update(goals)
        self._origin = None
        self._duration = None
        self.jumps += 1
        return True

    def _state(self, at: float) -> tuple[list[float], list[float], list[float]]:
        """Position, velocity and acceleration of every joint at sample time `at`."""
        if self._tracking:  # (as of the last targets: a tick or less ago)
            return list(self._tp), list(self._tv), list(self._ta)
        trajectory = self._trajectory
        if trajectory is None:
            return [self._position[name] for name in self._names], self._zeros, self._zeros
        p, v, a = trajectory.at_time(at - self._t0)  # (past its end: coasting, see `_sample`)
        return p, v, a

    def _plan(self, start: float) -> None:
        """Plan from the trajectory's state at sample time `start` to the goals: at rest, or,
        following a stream, onto the stream's line (see `_follow`)."""
        p, v, a = self._state(start)
        self._planned = True
        goals = [self._goals[name] for name in self._names]
        if self._origin is not None:  # a stream: tracked, target by target (`_track`)
            if not self._tracking:
                self._tracking = True
                self._trajectory = None
                self._tt, self._tp, self._tv, self._ta = start, list(p), list(v), list(a)
                self._th = (self._lead, self._lead)
            return
        self._tracking = False
        velocity = self._zeros
        if not any(velocity) and _settled(p, v, a, goals):
            self._trajectory = None  # (`advance` puts the targets exactly on the goals)
            self._duration = None
            return
        inp = self._input
        inp.current_position = p
        inp.current_velocity = v
        inp.current_acceleration = a
        inp.max_velocity = self._speeds
        self._which ^= 1
        trajectory = self._pair[self._which]
        if self._origin is not None and self._follow(trajectory, start, goals, velocity):
            self._trajectory = trajectory
            self._t0 = start
            return
        inp.target_position = goals
        inp.target_velocity = self._zeros
        inp.minimum_duration = self._duration
        self._duration = None
        self.plans += 1
        if not self._solve(trajectory):
            self.stop_at(self._position)  # (never seen: every retry failed) safe, if abrupt
            return
        self._trajectory = trajectory
        self._t0 = start

    def _follow(
        self, trajectory: Trajectory, start: float, goals: list[float], velocity: list[float]
    ) -> bool:
        """Plan onto the stream's line (its newest goal carried on at its velocity; the goal
        set at `_stamp` stands for sample time `_stamp + lead`), meeting it `HORIZON_TICKS`
        ahead, or twice or four times that when the nearer meeting is out of reach: Ruckig
        then gives a long detour (seen: 0.13 s, backing up, for a joint 1.2 degrees ahead
        of the line at 105 deg/s). False when no horizon is met (the caller plans to rest on
        the goals)."""
        inp = self._input
        inp.target_velocity = velocity
        bounds = self._bounds
        for ticks in (HORIZON_TICKS, 2 * HORIZON_TICKS, 4 * HORIZON_TICKS):
            horizon = ticks * self._lead
            ahead = start + horizon - self._stamp - self._lead
            inp.target_position = [
                min(upper, max(lower, g + u * ahead))
                for g, u, (lower, upper) in zip(goals, velocity, bounds, strict=True)
            ]
            inp.minimum_duration = horizon
            self.plans += 1
            try:
                self._otg.calculate(inp, trajectory)
            except RuckigError:
                self.fallbacks += 1
                continue
            if trajectory.duration <= horizon + self._lead:
                return True
        self.fallbacks += 1
        return False

    def _solve(self, trajectory: Trajectory) -> bool:
        """Ruckig on the input as set, retried when it finds no profile: Ruckig 0.19 fails
        now and then on a state near its acceleration limit (seen: -5760 of 6016 deg/s^2),
        which the same state with the acceleration a millionth lower solves; a stream's
        target velocity that still fails is planned as a step. Each retry is counted
        (`fallbacks`)."""
        inp = self._input
        for attempt in range(4):
            try:
                self._otg.calculate(inp, trajectory)
                return True
            except RuckigError:
                self.fallbacks += 1
                inp.current_acceleration = [x * (1.0 - 1e-6) for x in inp.current_acceleration]
                if attempt >= 1:
                    self._origin = None
                    inp.target_velocity = self._zeros
                    inp.minimum_duration = None
                if attempt >= 2:
                    inp.current_acceleration = [x * 0.999 for x in inp.current_acceleration]
        return False

    def _stream_velocity(self) -> list[float]:
        """The stream's velocity, per joint: inside the joint's cap, and none where coasting
        until the stream is overdue and braking from there could pass a limit."""
        assert self._origin is not None
        span = self._interval
        coast = OVERDUE * span + self._lead
        velocity = []
        for k, name in enumerate(self._names):
            goal = self._goals[name]
            cap = STREAM_SHARE * self._speeds[k]
            v = max(-cap, min(cap, (goal - self._origin[k]) / span))
            a = self._accel[k]
            # coasting, then braking (jerk included)
            reach = abs(v) * coast + v * v / (2.0 * a) + abs(v) * a / self._jerk[k]
            lower, upper = self._bounds[k]
            velocity.append(v if lower <= goal + math.copysign(reach, v) <= upper else 0.0)
        return velocity

    def _sample(self, at: float) -> list[float]:
        """Every joint's target at sample time `at`: on the trajectory; past its end, a stream
        not yet overdue coasts on at its velocity, an overdue one comes to rest on its last
        goal, and a step has arrived, exactly on its goals."""
        trajectory = self._trajectory
        assert trajectory is not None
        local = at - self._t0
        coasting = self._origin is not None and at <= self._due
        if local < trajectory.duration - EPSILON or coasting:
            # (past its end Ruckig extrapolates at the end's velocity: a stream coasts on)
            position: list[float] = trajectory.at_time(local)[0]
            return position
        if self._origin is not None:
            self._origin = None  # the stream ended (or is late): to rest on its last goal
            self._plan(max(self._due, self._t0 + trajectory.duration))
            if self._trajectory is None:
                return [self._goals[name] for name in self._names]
            return self._sample(at)
        self._trajectory = None  # arrived: exactly on the goals, at rest
        return [self._goals[name] for name in self._names]

    def stop_at(self, positions: Mapping[str, float]) -> None:
        """Stop every joint at `positions` (targets already sent): the way on was unsafe."""
        for name in self._names:
            self._position[name] = self._goals[name] = positions[name]
        self._rest()

    def _rest(self) -> None:
        """Every joint rests where its last target put it."""
        self._trajectory = None
        self._tracking = False
        self._origin = None
        self._planned = True
        self._duration = None

    def adopt(self, pose: Mapping[str, float]) -> dict[str, float]:
        """Take `pose` (every joint, clamped to its limits) as where each joint is, at rest:
        the robot learns where its arm is. A joint at rest stays there (its goal becomes that
        value); a joint that a command is moving goes on to its goal from there. Returns the
        pose taken."""
        moving = self.moving
        for name in self._names:
            value = self._clamps[name](float(pose[name]))
            if not moving or self._position[name] == self._goals[name]:
                self._goals[name] = value
            self._position[name] = value
        self._rest()
        self._sampled = -math.inf
        self._planned = self._position == self._goals
        return self.positions

    def freeze(self) -> None:
        """Stop every joint where it is: goals become the current targets."""
        self._goals.update(self._position)
        self._rest()


def _settled(p: list[float], v: list[float], a: list[float], goals: list[float]) -> bool:
    """Whether a state is at rest on `goals`, but for float dust (Ruckig finds no profile for
    a move of 1e-14 degrees at 1e-14 deg/s, seen at the end of a burst)."""
    for x, u, w, g in zip(p, v, a, goals, strict=True):
        if abs(x - g) > 1e-9 or abs(u) > 1e-9 or abs(w) > 1e-6:
            return False
    return True


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
