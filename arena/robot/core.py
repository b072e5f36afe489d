"""The robot's decision core, pure: safety state machine + rate limits + motion limiter.

`RobotCore` holds everything that decides what a robot does, and nothing that does I/O. The
actor (arena.robot.actor) feeds it events with the current time and carries out what it returns:
targets to send to slaves and effects (detach a master, tell slaves to stop or resume).
Property tests drive this class directly.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from arena.protocol.errors import ArenaError, ErrorCode
from arena.robot.model import RobotModel, SafetyPolicy
from arena.robot.motion import Command, CommandResult, MotionLimiter, RateLimiter, resolve_command
from arena.robot.safety import (
    Allowed,
    DetachMaster,
    Effect,
    Event,
    HoldPosition,
    ManualCommand,
    MasterCommand,
    Mode,
    Outcome,
    Refused,
    SafetyState,
    StopMotion,
    transition,
)

#: Rate-limit key of manual control (sliders, REST joints), which has no master id.
MANUAL_SOURCE = "manual"
# Immutable values every command would otherwise build afresh.
_MANUAL = ManualCommand()
_ACCEPTED = CommandResult(True)


@dataclass(slots=True)
class Step:
    """What one input produced: the safety outcome, targets for the slaves, effects to carry out."""

    outcome: Outcome
    targets: dict[str, float] | None = None
    effects: tuple[Effect, ...] = field(default=())


class RobotCore:
    """Pure decision state of one robot. All methods take `now` (trio time, seconds)."""

    def __init__(self, model: RobotModel, now: float, policy: SafetyPolicy | None = None) -> None:
        self.model = model
        self.policy = policy or model.safety
        self.state = SafetyState(
            loss_policy=self.policy.loss_policy, estop_severity=self.policy.estop_severity
        )
        self.motion = MotionLimiter(model, now)
        self._rates: dict[str, RateLimiter] = {}
        self._last_master_event: MasterCommand | None = None  # reused while one master commands

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
        for effect in outcome.effects:
            if isinstance(effect, StopMotion | HoldPosition):
                self.motion.freeze()
            elif isinstance(effect, DetachMaster):
                self._rates.pop(effect.master_id, None)
        return Step(outcome, None, outcome.effects)

    def forget_master(self, master_id: str) -> None:
        """Drop per-master bookkeeping once a master is gone for good."""
        self._rates.pop(master_id, None)

    def command(
        self, source: str | None, command: Command, now: float
    ) -> tuple[CommandResult, Step]:
        """A command from master `source` (None: manual control). Returns the answer and step."""
        last = self._last_master_event
        if source is None:
            event: Event = _MANUAL
        elif last is not None and last.source == source:
            event = last  # immutable: a command from the same master allocates less
        else:
            event = self._last_master_event = MasterCommand(source)
        outcome = transition(self.state, event)
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
        self.motion.set_goals(goals, command.duration, now)
        targets = self.motion.advance(now)
        message = "clamped to the joint limits" if clamps else ""
        result = CommandResult(True, None, message, tuple(clamps)) if clamps else _ACCEPTED
        return result, Step(outcome, targets)

    def tick(self, now: float) -> dict[str, float] | None:
        """Advance interpolation; returns new targets, or None if nothing moved."""
        if self.state.mode is Mode.ESTOPPED:
            return None
        return self.motion.advance(now)

    def next_tick(self, now: float) -> float | None:
        """When the next control tick is due, or None while nothing is moving."""
        if self.state.mode is Mode.ESTOPPED or not self.motion.moving:
            return None
        return now + self.tick_interval
