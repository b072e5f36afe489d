"""The robot's decision core, pure: safety state machine + rate limits + motion limiter.

`RobotCore` holds everything that decides what a robot does, and nothing that does I/O. The
actor (arena.robot.actor) feeds it events with the current time and carries out what it returns:
targets to send to slaves and effects (detach a master, tell slaves to stop or resume).
Property tests drive this class directly.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

from arena.protocol.errors import ArenaError, ErrorCode
from arena.robot import collision, collision_inside
from arena.robot.model import RobotModel, SafetyPolicy
from arena.robot.motion import (
    Clamp,
    Command,
    CommandResult,
    JoinRamp,
    MotionLimiter,
    RateLimiter,
    ResolvedGoal,
    resolve_command,
)
from arena.robot.safety import (
    Allowed,
    DetachMaster,
    Effect,
    Event,
    HoldPosition,
    Intervention,
    ManualCommand,
    MasterCommand,
    Mode,
    Outcome,
    Refused,
    ResumeSlaves,
    SafetyState,
    StopMotion,
    transition,
)

#: Rate-limit key of manual control (sliders, REST joints), which has no master id.
MANUAL_SOURCE = "manual"
# Immutable values every command would otherwise build afresh.
_MANUAL = ManualCommand()
_ACCEPTED = CommandResult(True)


@dataclass(frozen=True, slots=True)
class GuardStop:
    """A motion the collision guard stopped on its way, after its command was accepted: who
    commanded it (`source`: a master id, None for manual control), what would have met
    (`hit`), where the arm holds (`held`: the targets already sent) and where it was going
    (`goals`)."""

    source: str | None
    hit: collision.Hit
    held: dict[str, float]
    goals: dict[str, float]


@dataclass(slots=True)
class Step:
    """What one input produced: the safety outcome, targets for the slaves, effects to carry out."""

    outcome: Outcome
    targets: dict[str, float] | None = None
    effects: tuple[Effect, ...] = field(default=())
    joins: tuple[JoinChange, ...] = field(default=())


@dataclass(slots=True)
class _Join:
    """A measuring slave that does not follow the robot's targets yet (see `RobotCore`)."""

    speed: float  # deg/s of its way to the robot's pose
    measured: dict[str, float] = field(default_factory=dict)  # its newest values, by joint
    ramp: JoinRamp | None = None  # its own targets once on its way; None: waiting
    # An e-stop came since it attached: its way starts with the next accepted command, not
    # by itself (leaving an e-stop moves nothing).
    held: bool = False
    adopted: bool = False  # the robot took its pose while e-stopped (once is enough)


@dataclass(frozen=True, slots=True)
class JoinChange:
    """What joining did to one slave: `change` is "adopted" (the robot took this slave's
    measured pose as its own), "joining" (the slave is on its way to the robot's pose) or
    "joined" (it follows the robot's targets from now on); `targets` are the slave's own
    targets to send it (None: none now), `robot_targets` the robot's, for every slave that
    follows (an adopted pose), or None."""

    slave_id: str
    change: str | None  # None: only new targets
    reason: str
    targets: dict[str, float] | None = None
    robot_targets: dict[str, float] | None = None


#: Poses checked in full that later poses are compared with (see `_references`).
REFERENCES = 2
#: Degrees past a checked goal a stream's trajectory may end up (its line carried on a
#: little after the stream slowed to a stop): a collision found there ends on the goal.
GOAL_DUST = 0.05


class RobotCore:
    """Pure decision state of one robot. All methods take `now` (trio time, seconds)."""

    def __init__(self, model: RobotModel, now: float, policy: SafetyPolicy | None = None) -> None:
        self.model = model
        self.policy = policy or model.safety
        self.state = SafetyState(
            loss_policy=self.policy.loss_policy, estop_severity=self.policy.estop_severity
        )
        self.motion = MotionLimiter(model, now)
        #: The collision guard (None for a robot type without meshes) and its workspace.
        self.guard = collision.for_model(model)
        self.workspace = model.workspace
        #: Moves stopped on the way because an emitted target would have collided.
        self.collision_stops = 0
        #: The last such stop, until the actor takes it to report (`take_stop`).
        self._stop: GuardStop | None = None
        self._mover: str | None = None  # whose accepted command set the goals (None: manual)
        self._to_urdf = tuple((j.name, j.urdf_name, j.to_urdf) for j in model.joints)
        # Per joint of the model, its place in the guard's kinematics (None if not there): the
        # references are kept in the model's order and wire degrees, as the limiter lists its
        # goals and positions, so a pose is compared with them as it is, unconverted.
        kinematics = self.guard.kinematics.joints if self.guard is not None else ()
        place = {joint.name: k for k, joint in enumerate(kinematics)}
        self._guard_index = tuple(place.get(j.urdf_name) for j in model.joints)
        self._guard_scales = tuple(j.radians_per_unit for j in model.joints)  # URDF per wire unit
        self._checked: dict[str, float] | None = None  # the last goal pose found safe
        #: The last command's way out of a collision in the model, if it was one (`_guard`).
        self._escaping: collision_inside.Escape | None = None
        # The last poses checked in full with their clearances (metres), newest first: a pose
        # whose joints are so close to one that no part of the arm can have moved that far
        # is safe without a check (a stream of small steps is checked now and then, not
        # always). Two: while the motion limiter lags behind a fast master, the goals and the
        # targets on their way are two streams, each near its own last check.
        self._references: list[collision.Reference] = []
        self._reference_workspace = self.workspace  # a changed workspace voids the references
        self._sent = self.motion.positions  # the last targets emitted (where the arm goes)
        self._rates: dict[str, RateLimiter] = {}
        self._last_master_event: MasterCommand | None = None  # reused while one master commands
        # The last command's (state, event, outcome) of the safety machine (see `command`).
        self._last_transition: tuple[SafetyState, Event, Outcome] | None = None
        # Slaves that measure (a real arm, which is wherever it is): those that do not follow
        # the robot's targets yet, and those that do, with their joining speed should they
        # have to join again. See `slave_attached`.
        self._joins: dict[str, _Join] = {}
        self._measuring: dict[str, float] = {}
        #: Slaves not known to measure yet (connected over the network): what each has
        #: reported so far, by joint. See `slave_attached`.
        self.unsure: dict[str, dict[str, float]] = {}
        #: Ids of the slaves that must not be sent the robot's targets (they are joining).
        self.joining: set[str] = set()
        #: A master whose commands move no joint faster than the joining speed until the arm
        #: is where they command (a handover without a jerk: the leader arm in the human's
        #: hand is wherever it is; `ease_in`). None: none.
        self.easing: str | None = None
        self._eased = False  # a command of the easing master has been taken

    @property
    def tick_interval(self) -> float:
        """Seconds between control ticks while a joint is moving."""
        return 1.0 / self.policy.control_rate

    def handle(self, event: Event, now: float) -> Step:
        """Apply a non-command event (attach, detach, loss, e-stop, reset, slave events)."""
        outcome = transition(self.state, event)
        if not isinstance(outcome, Allowed):
            return Step(outcome)
        self.state = outcome.state
        joins: list[JoinChange] = []
        for effect in outcome.effects:
            if isinstance(effect, StopMotion | HoldPosition):
                self.motion.freeze()
                if isinstance(effect, StopMotion):
                    self._pause_joins()
            elif isinstance(effect, DetachMaster):
                self._rates.pop(effect.master_id, None)
            elif isinstance(effect, ResumeSlaves):
                for slave_id, join in list(self._joins.items()):
                    joins += self._decide(slave_id, join, now)  # held: moves nothing
            elif isinstance(effect, Intervention):
                self.ease_in(None if effect.ended else effect.master_id)
        return Step(outcome, None, outcome.effects, tuple(joins))

    # -- slaves that join ---------------------------------------------------------------------
    #
    # A slave that measures reports a real arm's pose, which no target of ours has set: it gets
    # none of the robot's targets until it has joined. Its first complete report decides how:
    # a robot that no master drives and no other measuring slave holds takes that pose as its
    # own (the twins move to it, the arm does not); otherwise the slave gets targets of its
    # own, from its measured pose toward the robot's targets at the joining speed, until it
    # is there. An e-stop stops a join where it is; after the reset the slave's way starts
    # again from the pose it measures then, with the next accepted command (a reset moves
    # nothing). Rules and reasons: specs/robot-model.md, "Slaves that join".

    def slave_attached(
        self, slave_id: str, *, measures: bool | None, join_speed: float | None = None
    ) -> None:
        """A slave attached; one that `measures` joins (see above) at `join_speed` deg/s
        (default: the robot's `join_speed`). `measures` None: not known (a slave connected
        over the network, which may be an arm or a twin): it follows the robot's targets until
        it has reported every joint, and from that report on it is an arm that measures and
        joins from there (`slave_measured`); one that never reports follows as a twin."""
        if measures is None:
            self.unsure[slave_id] = {}
        elif measures:
            self._wait(slave_id, self.policy.join_speed if join_speed is None else join_speed)

    def slave_detached(self, slave_id: str) -> None:
        """A slave left: it holds nothing any more."""
        self._joins.pop(slave_id, None)
        self._measuring.pop(slave_id, None)
        self.unsure.pop(slave_id, None)
        self.joining.discard(slave_id)

    def slave_rejoins(self, slave_id: str) -> None:
        """A measuring slave's arm was out of reach (its bus was lost) and answers again: it
        may have been moved meanwhile, so it joins again, from its next report, as at its
        attach."""
        speed = self._measuring.pop(slave_id, None)
        if speed is None and (join := self._joins.get(slave_id)) is not None:
            speed = join.speed  # it was joining: it starts again
        if speed is not None:
            self._wait(slave_id, speed)

    def slave_measured(
        self, slave_id: str, joints: Mapping[str, float], now: float
    ) -> list[JoinChange]:
        """A slave's report (protocol names, degrees): what it changes in a join, if any."""
        join = self._joins.get(slave_id)
        if join is None:
            return self._reported(slave_id, joints, now)
        join.measured.update(joints)
        if join.ramp is not None or len(join.measured) < len(self.model.joints):
            return []
        if join.adopted:  # decided already; while e-stopped, again at the reset
            if self.state.mode is Mode.ESTOPPED and self.state.owner is None:
                self._take_pose(join)  # a limp arm moved by hand: the robot's pose follows
            return []
        return self._decide(slave_id, join, now)

    def _reported(self, slave_id: str, joints: Mapping[str, float], now: float) -> list[JoinChange]:
        """A report of a slave not known to measure: once it has named every joint, the pose
        is its own (a twin would only say what it was told), so it joins from there, as an
        arm that measures does from its first report."""
        heard = self.unsure.get(slave_id)
        if heard is None:
            return []
        heard.update(joints)
        if len(heard) < len(self.model.joints):
            return []
        del self.unsure[slave_id]
        self._wait(slave_id, self.policy.join_speed)
        join = self._joins[slave_id]
        join.measured = heard
        return self._decide(slave_id, join, now)

    def _release_held(self, now: float) -> list[JoinChange]:
        """An accepted command: the joins an e-stop held start their way (the robot's pose
        is the command's business now: no adoption here)."""
        changes = []
        for slave_id, join in list(self._joins.items()):
            if join.held and join.ramp is None and len(join.measured) == len(self.model.joints):
                join.held = False
                changes += self._start_way(slave_id, join, now)
        return changes

    def advance_joins(self, now: float) -> list[JoinChange]:
        """The joining slaves' next targets (a control tick); those that arrive join."""
        if not self.joining:  # (while e-stopped no join has a way: `_pause_joins`)
            return []
        goal = self.motion.positions
        changes = []
        for slave_id, join in list(self._joins.items()):
            if join.ramp is None:
                continue
            targets = join.ramp.advance(goal, now)
            if join.ramp.arrived(goal):
                self._follow(slave_id, join)
                changes.append(JoinChange(slave_id, "joined", "at the robot's pose", targets))
            elif targets is not None:
                changes.append(JoinChange(slave_id, None, "", targets))
        return changes

    def _wait(self, slave_id: str, speed: float) -> None:
        self._joins[slave_id] = _Join(speed, held=self.state.mode is Mode.ESTOPPED)
        self.joining.add(slave_id)

    def _follow(self, slave_id: str, join: _Join) -> None:
        del self._joins[slave_id]
        self.joining.discard(slave_id)
        self._measuring[slave_id] = join.speed

    def _pause_joins(self) -> None:
        for join in self._joins.values():
            join.ramp = None
            join.held = True
            join.adopted = False

    def _decide(self, slave_id: str, join: _Join, now: float) -> list[JoinChange]:
        """A waiting slave with a complete report: adopt its pose, and start its way."""
        if join.ramp is not None or len(join.measured) < len(self.model.joints):
            return []
        changes = []
        stopped = self.state.mode is Mode.ESTOPPED
        holds = self._measuring or any(
            other.ramp is not None or other.adopted
            for other in self._joins.values()
            if other is not join
        )
        if self.state.owner is None and not holds:
            pose = self._take_pose(join)
            join.adopted = True
            quiet = stopped or join.held  # no target may go out now
            reason = "the robot takes the pose this slave measures"
            changes.append(JoinChange(slave_id, "adopted", reason, None, None if quiet else pose))
        if not stopped:  # (stopped: the reset decides again)
            changes += self._start_way(slave_id, join, now)
        return changes

    def _take_pose(self, join: _Join) -> dict[str, float]:
        """The robot takes the pose `join` measures (`MotionLimiter.adopt`)."""
        pose = self.motion.adopt(join.measured)
        self._sent = pose  # where the arm is: the guard checks the way on from here
        self._checked = None
        return pose

    def _start_way(self, slave_id: str, join: _Join, now: float) -> list[JoinChange]:
        """The slave follows if it is at the robot's pose; else its way starts (unless an
        e-stop holds it)."""
        ramp = JoinRamp(self.model, join.measured, join.speed, now)
        if ramp.arrived(self.motion.positions):
            self._follow(slave_id, join)
            return [JoinChange(slave_id, "joined", "at the robot's pose")]
        if join.held:
            return []  # its way starts with the next accepted command
        join.ramp = ramp
        reason = f"from the pose it measures to the robot's, at {join.speed:g} deg/s"
        return [JoinChange(slave_id, "joining", reason)]

    def forget_master(self, master_id: str) -> None:
        """Drop per-master bookkeeping once a master is gone for good."""
        self._rates.pop(master_id, None)
        if self.easing == master_id:
            self.easing = None

    def ease_in(self, master_id: str | None) -> None:
        """Ease `master_id`'s commands in at the joining speed (`easing`); None: none's."""
        self.easing, self._eased = master_id, False

    def command(
        self, source: str | None, command: Command, now: float, *, in_burst: bool = False
    ) -> tuple[CommandResult, Step]:
        """A command from master `source` (None: manual control). Returns the answer and step.

        `in_burst`: more of this master's commands are already in hand. The joints at rest
        still move at once, but a joint still on its way to an earlier goal is left to the
        control ticks (`MotionLimiter.advance`'s `fresh`): a master flooding commands faster
        than the arm may move would otherwise cause a sliver of motion per command, each
        checked, recorded and offered to the slaves, which get only the newest anyway."""
        last = self._last_master_event
        if source is None:
            event: Event = _MANUAL
        elif last is not None and last.source == source:
            event = last  # immutable: a command from the same master allocates less
        else:
            event = self._last_master_event = MasterCommand(source)
        # The machine is pure: the same state (an immutable object, replaced on every change)
        # and event give the same outcome, so a master's stream reuses the last one.
        state, memo = self.state, self._last_transition
        if memo is not None and memo[0] is state and memo[1] is event:
            outcome = memo[2]
        else:
            outcome = transition(state, event)
            self._last_transition = (state, event, outcome)
        if isinstance(outcome, Refused):
            return CommandResult.refused(outcome.code, outcome.message), Step(outcome)
        key = MANUAL_SOURCE if source is None else source
        limiter = self._rates.get(key)
        if limiter is None:
            limiter = RateLimiter(self.policy.command_rate, self.policy.command_burst, now)
            self._rates[key] = limiter
        if not limiter.allow(now):
            message = f"More than {self.policy.command_rate:g} commands/s; command dropped."
            refusal = Refused(ErrorCode.RATE_LIMITED, message)
            return CommandResult.refused(refusal.code, message), Step(refusal)
        try:
            goals, clamps = resolve_command(self.model, command)
        except ArenaError as exc:
            refusal = Refused(exc.code, exc.message)
            return CommandResult.refused(exc.code, exc.message), Step(refusal)
        message = "clamped to the joint limits" if clamps else ""
        if self.easing is not None and source == self.easing:
            goals = self._ease(goals)
        if self.guard is not None:
            goals, unsafe, short = self._guard(goals)
            if unsafe is not None:
                return CommandResult.refused(unsafe.code, unsafe.message), Step(unsafe)
            if short:
                clamps = [*clamps, *short]
                message = "stopped short of a collision"
            elif self._escaping is not None:
                way_out = f"out of a collision in the model: {self._escaping.describe()}"
                message = f"{message}; {way_out}" if message else way_out
        self.motion.set_goals(goals, command.duration, now, command.stamp)
        self._mover = source
        targets = self._advance(now, fresh=in_burst)
        if self.easing is not None:
            self._eased_in()
        result = CommandResult(True, None, message, tuple(clamps)) if message else _ACCEPTED
        if self.joining:  # (rare: one check per command otherwise)
            return result, Step(outcome, targets, (), tuple(self._release_held(now)))
        return result, Step(outcome, targets)

    def _ease(self, goals: list[ResolvedGoal]) -> list[ResolvedGoal]:
        """An intervening master's goals at the joining speed at most (see `easing`)."""
        self._eased = True
        speed = self.policy.join_speed
        return [
            goal if goal.speed <= speed else ResolvedGoal(goal.name, goal.value, speed)
            for goal in goals
        ]

    def _eased_in(self) -> None:
        """The arm is where the easing master commands: its commands pass as they are now."""
        if self._eased and not self.motion.moving:
            self.easing = None

    def _urdf(self, degrees: Mapping[str, float]) -> dict[str, float]:
        """Wire degrees by joint name to URDF radians by URDF joint (`JointSpec.to_urdf`)."""
        return {urdf: to_urdf(degrees[name]) for name, urdf, to_urdf in self._to_urdf}

    def _guard(
        self, goals: list[ResolvedGoal]
    ) -> tuple[list[ResolvedGoal], Refused | None, list[Clamp]]:
        """Check the way from the current targets to the new goals: the goals (or, stopping
        short, the last safe ones with what was cut as clamps), or a refusal."""
        assert self.guard is not None
        self._escaping = None
        start = self._sent
        end = self.motion.goals
        for goal in goals:
            end[goal.name] = goal.value
        if self._near_reference(end):
            self._checked = end
            return goals, None, []
        target = self._urdf(end)
        hit, safe, clearance = self.guard.path_hit(self._urdf(start), target, self.workspace)
        if hit is None:
            self._checked = end
            self._remember(end, target, clearance)
            return goals, None, []
        names = ", ".join(goal.name for goal in goals)
        escape = None
        if safe <= 0.0:
            escape = collision_inside.escape(self.guard, self._urdf(start), target, self.workspace)
        if escape is not None:
            # The arm is where the model says it collides (a measured pose, a model a little
            # off the arm): a move that takes no part deeper in, nor any into something new,
            # is let out; one that does is refused, saying which clearance it would shrink.
            if escape.allowed:
                self._checked = end
                self._escaping = escape
                return goals, None, []
            message = (
                f"The arm already collides in the model; moving {names} there would bring the "
                f"clearance of {escape.describe()}: it decreases, and only motion that "
                "increases it is accepted; command refused."
            )
            return goals, Refused(ErrorCode.COLLISION, message), []
        if self.workspace.policy != "stop-short" or safe <= 0.0:
            message = f"Moving {names} there would bring {hit} together; command refused."
            return goals, Refused(ErrorCode.COLLISION, message), []
        short, clamps = [], []
        for goal in goals:
            value = start[goal.name] + (goal.value - start[goal.name]) * safe
            short.append(ResolvedGoal(goal.name, value, goal.speed))
            if value != goal.value:
                clamps.append(Clamp(goal.name, goal.value, value))
        self._checked = {**end, **{goal.name: goal.value for goal in short}}
        return short, None, clamps

    def _advance(
        self, now: float, *, fresh: bool = False, tick: bool = False
    ) -> dict[str, float] | None:
        """The limiter's next targets (`fresh`: a command's own step, see `MotionLimiter`),
        unless they would collide: then the motion stops at the targets already sent (a
        joint-space path checked at its goal can still bend into something while joints of
        different speeds move)."""
        if self.guard is None:
            return self.motion.advance(now, fresh=fresh, tick=tick)
        targets = self.motion.advance(now, fresh=fresh, tick=tick)
        if targets is None:
            return None
        if targets != self._checked and not self._near_reference(targets):
            pose = self._urdf(targets)
            hit, clearance = self.guard.assess(pose, self.workspace)
            if hit is not None:
                escape = collision_inside.escape(
                    self.guard, self._urdf(self._sent), pose, self.workspace
                )
                if escape is None or not escape.allowed:
                    goals = self.motion.goals
                    if _within(targets, goals, GOAL_DUST):
                        # A stream's last few thousandths past its goal (the goal itself
                        # was checked when it was commanded): end on the goal.
                        self.motion.stop_at(goals)
                        self._sent = goals
                        return goals
                    self.motion.stop_at(self._sent)
                    self.collision_stops += 1
                    self._stop = GuardStop(self._mover, hit, dict(self._sent), goals)
                    return None
            else:  # (a pose on its way out of a collision is no reference)
                self._remember(targets, pose, clearance)
        self._sent = targets
        return targets

    def _near_reference(self, degrees: dict[str, float]) -> bool:
        """True when no part of the arm can have moved from a pose checked in full as far as
        its clearance (so `degrees`, every joint's in the model's order, and the way to it
        are safe without a check)."""
        if self.workspace is not self._reference_workspace:
            self._references.clear()
            return False
        pose = degrees.values()
        near = collision.CollisionModel.near
        for reference in self._references:  # noqa: SIM110 (a generator costs more, per command)
            if near(reference, pose):
                return True
        return False

    def _remember(
        self, degrees: dict[str, float], urdf: dict[str, float], clearance: tuple[float, ...]
    ) -> None:
        """Keep a pose checked in full (`degrees` as the limiter lists them; `urdf` as the
        guard took it), with its clearance, as a reference."""
        if self.workspace is not self._reference_workspace:
            self._references.clear()
            self._reference_workspace = self.workspace
        assert self.guard is not None
        reference = self.guard.reference(urdf, clearance)
        values = tuple(degrees.values())
        ordered = reference.in_order(values, self._guard_index, self._guard_scales)
        self._references.insert(0, ordered)
        del self._references[REFERENCES:]

    def take_stop(self) -> GuardStop | None:
        """The motion the guard stopped since the last call, if any (the actor reports it)."""
        stop, self._stop = self._stop, None
        return stop

    def tick(self, now: float) -> dict[str, float] | None:
        """Advance interpolation; returns new targets, or None if nothing moved."""
        if self.state.mode is Mode.ESTOPPED:
            return None
        targets = self._advance(now, tick=True)
        if self.easing is not None:
            self._eased_in()
        return targets

    def next_tick(self, now: float) -> float | None:
        """When the next control tick is due, or None while nothing is moving. A stream on
        time ticks only when it goes overdue: its commands move it on."""
        if self.state.mode is Mode.ESTOPPED:
            return None
        joining = self.joining
        if joining and any(join.ramp is not None for join in self._joins.values()):
            return now + self.tick_interval
        motion = self.motion
        if not motion.moving:  # (first: an arm at rest, the fleet's, asks nothing more)
            return None
        if not joining and self.easing is None and (quiet := motion.quiet_until) is not None:
            return max(quiet, now + self.tick_interval)
        return now + self.tick_interval

    def reschedule(self, planned: float | None, now: float) -> float | None:
        """The next tick after a step taken at `now`, given the one `planned` before it: the
        core's (`next_tick`) where it is sooner, or where a stream runs on time (then, and
        only then, it is more than a tick away: a tick planned sooner would send nothing);
        else the one planned (a tick early is harmless)."""
        due = self.next_tick(now)
        if planned is None or (
            due is not None and (due < planned or due > now + self.tick_interval)
        ):
            return due
        return planned


def _within(a: Mapping[str, float], b: Mapping[str, float], tolerance: float) -> bool:
    """Whether every joint of `a` is within `tolerance` of `b`'s."""
    return all(abs(value - b[name]) <= tolerance for name, value in a.items())
