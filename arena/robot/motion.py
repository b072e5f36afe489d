"""Motion safety, pure: jerk-limited trajectories (command validation: `commands`; the rate
limit and the join ramp: `ramps`; their names are here too, where callers import them).

Every target that reaches a slave comes out of `MotionLimiter.advance`: a sample of one online
trajectory (Ruckig) limited per joint in velocity, acceleration and jerk, planned afresh from
where the joints are and how fast they move whenever a goal changes. Tested on the targets
emitted at the control rate: no finite-difference acceleration or jerk above its limit (within
the tolerance tests/test_motion_trajectory.py states). See specs/motion.md.
Time is an argument everywhere (seconds, any monotonic origin): nothing here reads a clock.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable, Mapping

from ruckig import (
    InputParameter,
    Ruckig,
    RuckigError,
    Synchronization,
    Trajectory,
)

from arena.robot import steps
from arena.robot.commands import Clamp as Clamp
from arena.robot.commands import Command as Command
from arena.robot.commands import CommandResult as CommandResult
from arena.robot.commands import JointGoal as JointGoal
from arena.robot.commands import ResolvedGoal as ResolvedGoal
from arena.robot.commands import resolve_command as resolve_command
from arena.robot.model import RobotModel
from arena.robot.ramps import JoinRamp as JoinRamp
from arena.robot.ramps import RateLimiter as RateLimiter

#: Seconds within which a trajectory counts as at its end: a tick that falls on the end in
#: real arithmetic lands on either side of it in floating point (a replay's times are the
#: recording's, rounded), and must arrive all the same.
EPSILON = 1e-9
#: Seconds by which two times on the same grid (ticks, a stream's goals) that tie in real
#: arithmetic are taken as tied: on a clock a million seconds on, rounding alone puts them
#: 1e-10 either side, and a choice made on that would differ from one episode to the next.
TIME_DUST = 1e-6
#: Seconds between two goals of a joint up to which they are taken as one stream (a leader arm,
#: a policy, a slider dragged), followed through them at the stream's own velocity; goals
#: further apart are steps, reached at rest.
STREAM_WINDOW = 0.1
#: A stream's next goal is overdue this many of its intervals after its last: the trajectory,
#: coasting at the stream's velocity since it met the last goal, then comes to rest on it.
OVERDUE = 1.5
#: Stamped goals of a stream kept: the newest two give the stream's velocity (`_played`).
STAMPED_KEPT = 2
#: Seconds between the points of a history at rest (`_rest_times`): small against a tick,
#: large against float rounding of the divided differences over it.
REST_SPACING = 1e-4
#: The oldest a command's `stamp` is taken to be (seconds before it arrived): a master's
#: clock that is off cannot throw the stream's line further than this.
MAX_AGE = 0.05


class MotionLimiter:
    """Turns goals into a jerk-limited trajectory for the slaves (Ruckig; specs/motion.md).

    Every joint's targets are limited per joint in velocity (the joint's limit, or a command's
    lower `speed`), acceleration and jerk (`JointSpec.max_acceleration`, `max_jerk`), and the
    limits hold on the targets as they are emitted: every target is checked against the last
    three by divided differences (the velocity, acceleration and jerk a slave's servo is asked
    for, whatever the times between them) and moved into the interval they allow (`_emit`).

    A step (a goal after a pause) is a Ruckig trajectory to rest on the goal, planned from
    where the joints are and how fast they move: a new goal mid-motion bends it, the velocity
    never steps, and all joints arrive together on the straight line in joint space the
    collision guard checked (phase synchronization). A stream of goals (each within
    `STREAM_WINDOW` of the last: a leader arm, a policy) is tracked goal by goal: a goal that
    the limits allow next is the target itself (a person's hand, a policy's smooth actions:
    passed on as they come, no lag added, no line carried on past where the hand stops);
    one they do not is approached on a trajectory to rest on it, as far as one step goes.
    A stream whose next goal is overdue (`OVERDUE`) comes to rest on its last. A stream's
    targets go out when its goals arrive, none between: a guess of where a hand goes next is
    a lag removed at the price of an overshoot where it stops. A stamped stream (a leader's
    reads) is measured at the times its goals were true, a tick on (`_label`): its targets
    then have the hand's own derivatives, however unevenly its goals arrive.

    Costs: a robot at rest costs nothing per tick (no tick is asked for), and a move small
    enough to be made within one tick from rest (`reach`) is one target without planning; a
    step is one Ruckig plan per new goal and one sample per tick; a stream passed on costs
    no plan.

    Targets lead the clock by one control tick: what is emitted at `now` is the trajectory at
    `now + 1 / control_rate` (a stamped goal's: at its stamp's), so a command's first step
    goes out with the command. `freeze`
    and `stop_at` stop at once (an e-stop's hold, a collision ahead): nothing is smoother
    than safe. Time is an argument everywhere (seconds, any monotonic origin).
    """

    # (slots: past 30 attributes an instance's dict is its own, every `self._x` a lookup
    # in it: 3 % of the fleet's commands)
    # fmt: off
    __slots__ = (
        "_accel", "_behind", "_clamps", "_due", "_duration", "_fresh", "_goals",
        "_history_p", "_history_t", "_index", "_input", "_jerk", "_label", "_lead",
        "_names", "_new_goal", "_otg", "_pair", "_planned", "_position", "_reach",
        "_reaches", "_sampled", "_speeds", "_stamped", "_stamps", "_stream", "_t0",
        "_tracking", "_trajectory", "_velocity", "_which", "_zeros", "clipped",
        "fallbacks", "jumps", "plans",
    )
    # fmt: on

    def __init__(
        self, model: RobotModel, now: float, initial: Mapping[str, float] | None = None
    ) -> None:
        self._names = tuple(j.name for j in model.joints)
        self._index = {name: k for k, name in enumerate(self._names)}
        self._clamps = {j.name: j.clamp for j in model.joints}
        self._lead = lead = 1.0 / model.safety.control_rate
        dofs = len(self._names)
        self._otg = Ruckig(dofs)
        self._input = InputParameter(dofs)
        self._input.synchronization = Synchronization.Phase  # the straight line in joint space
        self._input.max_acceleration = [j.max_acceleration for j in model.joints]
        self._input.max_jerk = [j.max_jerk for j in model.joints]
        self._velocity = tuple(j.max_velocity for j in model.joints)
        self._accel = tuple(j.max_acceleration for j in model.joints)
        self._jerk = tuple(j.max_jerk for j in model.joints)
        #: Per joint, the distance a move from rest covers in one tick within every limit
        #: by divided differences (jerk j T^3/32 keeps a continuous move's too): a move no
        #: longer than this is made in one target, without a plan (`_jump`).
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
        self._speeds = list(self._velocity)  # caps of the move under way
        self._stamps = [-math.inf] * dofs  # when each joint's goal was last set
        self._duration: float | None = None  # a timed move's least duration, until planned
        self._stream = False  # the newest goals continue a stream
        self._due = 0.0  # sample time at which the stream's next goal is overdue
        self._planned = True  # the trajectory (or the tracking) meets the newest goals
        self._trajectory: Trajectory | None = None  # a step's; None: tracking or at rest
        self._tracking = False  # a stream is tracked (`_track`)
        # A stream whose goals carry when they were true (`stamp`): its newest goals by
        # that time (`_played`), and the sample time the newest stands for (a tick after
        # it was true), on which its targets are measured.
        self._stamped: deque[tuple[float, list[float]]] = deque(maxlen=STAMPED_KEPT)
        self._label: float | None = None
        self._new_goal = False  # a goal came since the last targets
        self._behind = False  # the last targets were held short of their candidates
        # The last three emitted targets, oldest first, and the sample times they stand for
        # (`_emit`): what the limits are measured on.
        self._history_t = _rest_times(now)
        first = [self._position[name] for name in self._names]
        self._history_p = [first, first, first]
        # Two trajectories, planned into in turn: the one in use is never overwritten (its
        # state is where the next plan starts), and a plan allocates none.
        self._pair = (Trajectory(dofs), Trajectory(dofs))
        self._which = 0
        self._t0 = 0.0  # sample time at which the trajectory starts
        self._sampled = -math.inf  # sample time of the last emitted targets
        self._fresh = False  # the last `set_goals` found every joint at rest
        #: Trajectories planned (benchmarks and tests count them), and how many of them
        #: Ruckig failed at first, planned again; moves made in one target; targets the
        #: limits moved off their candidate (seams, a state over a limit).
        self.plans = 0
        self.fallbacks = 0
        self.jumps = 0
        self.clipped = 0

    @property
    def sampled(self) -> float:
        """The trajectory time the last targets stand for (seconds; what the limits are
        measured on)."""
        return self._sampled

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
        """True while some joint has not reached its goal at rest (ticks are needed)."""
        return (
            self._trajectory is not None
            or self._tracking
            or not self._planned
            or self._position != self._goals
        )

    @property
    def quiet_until(self) -> float | None:
        """While a stream runs on time (its next goal moves it on, a tick sends nothing): the
        time of the first tick that does something, the one that finds the stream overdue
        (it then comes to rest on its last goal). None otherwise: every tick may."""
        quiet = self._tracking and self._stream and self._planned
        return self._due - self._lead if quiet and not (self._new_goal or self._behind) else None

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
        the goals were true (a leader's read; at most `MAX_AGE` before `now`): a stream of
        stamped goals is measured at those times, not at their arrival (a loop's jitter
        would otherwise read as accelerations the hand never made)."""
        self._fresh = not self.moving
        targets = self._goals
        index, stamps, speeds = self._index, self._stamps, self._speeds
        stream = duration is None
        interval = 0.0
        window = STREAM_WINDOW + TIME_DUST
        for goal in goals:
            name = goal.name
            k = index[name]
            elapsed = now - stamps[k]
            stamps[k] = now
            targets[name] = goal.value
            speeds[k] = goal.speed
            if 0.0 < elapsed <= window:
                if elapsed > interval:
                    interval = elapsed
            else:
                stream = False
        self._stream = stream and interval > 0.0
        if self._stream:
            self._due = now + self._lead + OVERDUE * interval
        stamped = self._stamped
        if stamp is None or not self._stream:
            stamped.clear()
        self._label = None
        if stamp is not None:
            true_at = min(now, max(now - MAX_AGE, stamp))
            if not stamped or true_at > stamped[-1][0]:  # (one that overtook: dropped)
                if self._stream and stamped:
                    # a tick after it was true, or as far after the last targets as it is
                    # after the last stamped goal (half a tick at least), whichever is later
                    spacing = max(true_at - stamped[-1][0], 0.5 * self._lead + EPSILON)
                    self._label = max(true_at + self._lead, self._sampled + spacing)
                stamped.append((true_at, [targets[name] for name in self._names]))
        self._duration = duration
        self._planned = False
        self._new_goal = True

    def advance(
        self, now: float, *, fresh: bool = False, tick: bool = False
    ) -> dict[str, float] | None:
        """The targets for `now` (see the class docstring); with `fresh` (a command in the
        middle of a burst) only if the robot was at rest: a robot already on its way takes
        the newest goals at its next tick. A `tick` within half a tick of the last targets
        (a command's) sends none: a stream's targets stay about a tick apart instead of a
        command's and a tick's a few milliseconds apart.

        Returns the full target vector if any joint moved, else None.
        """
        if fresh and not self._fresh:
            return None
        sample = now + self._lead
        label, self._label = self._label, None
        if label is not None:
            sample = label  # (a stamped stream's goal: at the time it stands for)
        if sample <= self._sampled or (
            (tick or self._tracking) and sample - self._sampled < 0.5 * self._lead
        ):
            return None  # (a step this short measures rounding: the next tick takes it)
        if not self._planned:
            if self._trajectory is None and not self._tracking and self._jump():
                return self._jumped(sample)
            self._settle_history(sample)
            self._plan(max(self._sampled, now))
        else:
            self._settle_history(sample)
        if self._tracking:
            if self._stream and sample >= self._due - TIME_DUST:
                self._stream = False  # overdue: it ended; to rest on its last goal
            if not self._new_goal and self._stream and not self._behind:
                return None  # (a stream on time: its next goal, not a guess, moves it on)
            candidates, bounds = self._track(sample)
            return self._emit(sample, candidates, bounds)  # (bounds None: within them)
        if self._trajectory is not None:
            candidates = self._sample(sample)
        elif self._position != self._goals:  # at rest on a plan's end, or clipped short
            candidates = [self._goals[name] for name in self._names]
        else:
            return None
        return self._emit(sample, candidates, self._allowed(sample))

    def _settle_history(self, sample: float) -> None:
        """A history at rest is at rest until now: at rest a tick before `sample`, velocity
        and acceleration zero there (`REST_SPACING`: a step from rest is measured as a
        continuous move from rest would be, jerk first)."""
        p2, p1, p0 = self._history_p
        if p0 == p1 == p2 and self._history_t[2] < sample - self._lead - TIME_DUST:
            self._history_t = _rest_times(sample - self._lead)

    def _allowed(self, at: float) -> list[tuple[float, float]]:
        """Each joint's interval of step velocity at sample time `at` (`steps.allowed`)."""
        return steps.allowed(
            self._history_t, self._history_p, at, self._accel, self._jerk, self._speeds
        )

    def _emit(
        self,
        sample: float,
        candidates: list[float],
        bounds: list[tuple[float, float]] | None,
    ) -> dict[str, float] | None:
        """Emit the targets for `sample`: the candidates, or, where the limits after the last
        three targets (`bounds`, `_allowed`; None: candidates known to be within them) do not
        allow them, held back on the line toward them (`steps.held`)."""
        t0 = self._history_t[2]
        p0 = self._history_p[2]
        out = None if bounds is None else steps.held(p0, candidates, bounds, sample - t0)
        self._behind = out is not None
        if out is None:
            out = candidates
        else:
            self.clipped += sum(a != b for a, b in zip(out, candidates, strict=True))
        position = dict(zip(self._names, out, strict=True))
        changed = position != self._position
        self._position = position
        self._history_t = [self._history_t[1], t0, sample]
        self._history_p = [self._history_p[1], p0, out]
        self._sampled = sample
        self._new_goal = False
        if self._tracking and not self._stream and self._at_rest_on_goals():
            self._tracking = False
        return position.copy() if changed else None

    def _jumped(self, sample: float) -> dict[str, float] | None:
        """The targets of a move made in one (`_jump`), at rest on its goals after it. From a
        history at rest (one list three times: set so by every rest) a move within `reach` is
        within the limits by construction: the goals go out as they are, unchecked (the
        fleet's commands: half of their cost was the check), if it has rested a tick."""
        history = self._history_p
        if history[0] is history[1] is history[2] and (
            self._history_t[2] <= sample - self._lead + TIME_DUST
        ):
            goals = self._goals
            out = list(goals.values())  # (in the joints' order: keys are never added)
            self._position.update(goals)  # (`_jump`: some joint moves)
            self._sampled = sample
            self._new_goal = False
            targets: dict[str, float] | None = goals.copy()
        else:
            self._settle_history(sample)
            targets = self._emit(
                sample, [self._goals[name] for name in self._names], self._allowed(sample)
            )
            out = self._history_p[2]
        self._history_p = [out] * 3  # (a whole move: at rest there)
        self._history_t = _rest_times(sample)
        return targets

    def _at_rest_on_goals(self) -> bool:
        p2, p1, p0 = self._history_p
        return p0 == p1 == p2 and all(
            p0[k] == self._goals[name] for k, name in enumerate(self._names)
        )

    def _state(self) -> tuple[list[float], list[float], list[float]]:
        """Position, velocity and acceleration of every joint at the last target, by the
        parabola through the last three (what a plan from there starts with)."""
        t2, t1, t0 = self._history_t
        p2, p1, p0 = self._history_p
        velocity, acceleration = [], []
        for k in range(len(self._names)):
            d1 = (p0[k] - p1[k]) / (t0 - t1)
            f2 = (d1 - (p1[k] - p2[k]) / (t1 - t2)) / (t0 - t2)
            cap, limit = self._velocity[k], self._accel[k]
            velocity.append(max(-cap, min(cap, d1 + f2 * (t0 - t1))))
            acceleration.append(max(-limit, min(limit, 2.0 * f2)) * (1.0 - 1e-6))
        return list(p0), velocity, acceleration

    def _track(self, at: float) -> tuple[list[float], list[tuple[float, float]] | None]:
        """A stream's candidates at sample time `at`: each joint's goal itself when the
        limits allow it there and the joint could still keep under its velocity cap after
        it (a hand's move, a policy's smooth actions: passed on, no lag added); otherwise a
        step toward it no faster than stopping on it allows (a stream that jumps is
        approached without overshoot; one that stops dead is braked as the limits allow,
        past its goal and back if it must), which `_emit` keeps within the limits. Joints
        held back hold every joint to the line to the goals (`steps.on_line`): the way the
        guard checked. Returns them and the limits' intervals at `at` (`_emit`'s too), None
        when every candidate is its goal within them (the common case: nothing to hold)."""
        t1, t0 = self._history_t[1], self._history_t[2]
        p1, p0 = self._history_p[1], self._history_p[2]
        h = at - t0
        goals, velocity = self._played()
        known = len(self._stamped) > 1 and self._stream
        speeds, limits = self._speeds, self._accel
        if steps.passes(
            self._history_t,
            self._history_p,
            at,
            goals,
            velocity if known else None,
            limits,
            self._jerk,
            speeds,
        ):
            return goals, None  # (the common case, its comparisons without the intervals)
        span, h1 = t0 - t1, at - t1
        candidates = []
        bounds = self._allowed(at)
        for k, (low, high) in enumerate(bounds):
            goal, fast = goals[k], speeds[k]
            step = (goal - p0[k]) / h
            was = (p0[k] - p1[k]) / span
            # (the same rules as `steps.passes`, joint by joint: within the limits, the jerk's
            # ramp under the cap, and not onto the goals much faster than they move, where
            # that is known: an arm catching up on a hand that stops would overshoot it)
            if (
                low <= step <= high
                and not steps.ramp_over(step, was, h, h1, fast, self._jerk[k])
                and (not known or abs(step - velocity[k]) <= limits[k] * h)
            ):
                candidates.append(goal)
                continue
            candidates.append(steps.toward(goal, p0[k], step, was, velocity[k], limits[k], h, fast))
        return steps.on_line(p0, goals, candidates), bounds

    def _played(self) -> tuple[list[float], list[float]]:
        """The stream's newest goals and their velocity: a stamped stream's by its newest two
        goals' read times (the hand's own speed, whatever their arrival's jitter); unstamped,
        taken as still."""
        newest = [self._goals[name] for name in self._names]
        stamped = self._stamped
        if len(stamped) < 2 or not self._stream:
            return newest, self._zeros
        (t1, earlier), (t0, later) = stamped[-2], stamped[-1]
        spacing = t0 - t1
        return newest, [(b - a) / spacing for a, b in zip(earlier, later, strict=True)]

    def _jump(self) -> bool:
        """From rest, goals within one tick's `reach` of every joint's target: taken in one
        target (what a full plan would give within a tick), planned no further. The
        fleet's tiny moves and a stream's last creep cost no plan and no tick."""
        self._planned = True
        position, goals = self._position, self._goals
        if position == goals:
            return False  # (nothing to move: at rest on the goals already)
        for name, reach in self._reaches:
            delta = goals[name] - position[name]
            if delta > reach or -delta > reach:
                self._planned = False
                return False
        self._duration = None
        self.jumps += 1
        return True

    def _plan(self, start: float) -> None:
        """Plan from the last targets' state to the goals: a stream is tracked, a step is a
        trajectory to rest on them."""
        self._planned = True
        if self._fresh and self._history_t[2] < start - self._lead - TIME_DUST:
            # At rest since its last targets, over a tick ago: the plan (or the stream) starts
            # at rest there now, not from the divided differences of a move long ended (from
            # those, dated then, a step began in the past and was sampled past its end, and a
            # stream's first goals measured across the rest passed as slow: jumps both).
            self._history_p = [self._history_p[2]] * 3
            self._history_t = _rest_times(start)
        if self._stream:
            self._tracking = True
            self._trajectory = None
            return
        self._tracking = False
        p, v, a = self._state()
        goals = [self._goals[name] for name in self._names]
        if _settled(p, v, a, goals):
            self._trajectory = None  # (`advance` puts the targets exactly on the goals)
            self._duration = None
            return
        self._which ^= 1
        trajectory = self._pair[self._which]
        duration, self._duration = self._duration, None
        if not self._solve(trajectory, p, v, a, goals, duration):
            self.stop_at(self._position)  # (never seen: every retry failed) safe, if abrupt
            return
        self._trajectory = trajectory
        self._t0 = self._history_t[2]

    def _solve(
        self,
        trajectory: Trajectory,
        p: list[float],
        v: list[float],
        a: list[float],
        goals: list[float],
        duration: float | None,
    ) -> bool:
        """Ruckig from (p, v, a) to rest on `goals`, retried when it finds no profile:
        Ruckig 0.19 fails now and then on a state near its acceleration limit (seen: -5760
        of 6016 deg/s^2), which the same state with the acceleration a little lower solves.
        Each retry is counted (`fallbacks`)."""
        inp = self._input
        inp.current_position = p
        inp.current_velocity = v
        inp.current_acceleration = a
        inp.max_velocity = self._speeds
        inp.target_position = goals
        inp.target_velocity = self._zeros
        inp.minimum_duration = duration
        self.plans += 1
        for attempt in range(4):
            try:
                self._otg.calculate(inp, trajectory)
                return True
            except RuckigError:
                self.fallbacks += 1
                scale = 1.0 - (1e-6 if attempt == 0 else 1e-3 * attempt)
                inp.current_acceleration = [x * scale for x in inp.current_acceleration]
                inp.minimum_duration = None
        return False

    def _sample(self, at: float) -> list[float]:
        """Every joint's candidate at sample time `at`: on the trajectory; past its end,
        exactly on its goals (and the trajectory done)."""
        trajectory = self._trajectory
        assert trajectory is not None
        local = at - self._t0
        if local < trajectory.duration - EPSILON:
            position: list[float] = trajectory.at_time(local)[0]
            return position
        self._trajectory = None  # arrived: exactly on the goals (clipped: on them soon)
        return [self._goals[name] for name in self._names]

    def stop_at(self, positions: Mapping[str, float]) -> None:
        """Stop every joint at `positions` (targets already sent): the way on was unsafe."""
        for name in self._names:
            self._position[name] = self._goals[name] = positions[name]
        self._rest()

    def _rest(self) -> None:
        """Every joint rests where its last target put it (a hold: the history with it)."""
        self._trajectory = None
        self._tracking = False
        self._stream = False
        self._stamped.clear()
        self._label = None
        self._behind = False
        self._planned = True
        self._duration = None
        here = [self._position[name] for name in self._names]
        self._history_p = [here, here, here]
        self._history_t = _rest_times(self._history_t[2])

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


def _rest_times(at: float) -> list[float]:
    """The times of a history at rest at `at`: three points `REST_SPACING` apart, so that
    its divided differences are a standstill's derivatives there."""
    return [at - 2 * REST_SPACING, at - REST_SPACING, at]


def _settled(p: list[float], v: list[float], a: list[float], goals: list[float]) -> bool:
    """Whether a state is at rest on `goals`, but for float dust (Ruckig finds no profile for
    a move of 1e-14 degrees at 1e-14 deg/s, seen at the end of a burst)."""
    for x, u, w, g in zip(p, v, a, goals, strict=True):
        if abs(x - g) > 1e-9 or abs(u) > 1e-9 or abs(w) > 1e-6:
            return False
    return True
