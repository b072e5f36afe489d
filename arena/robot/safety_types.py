"""The safety state machine's words: its modes and state, the events it takes, the effects it
asks of the actor and the outcomes of a transition. Values only: the rules that decide are in
`arena.robot.safety`, which is where everyone else imports these names from."""

from __future__ import annotations

import enum
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import TypeAlias

from arena.protocol.errors import ErrorCode, Severity
from arena.robot.model import LossPolicy


class Mode(enum.StrEnum):
    """The safety modes of a robot."""

    IDLE = "idle"  # no master; manual control allowed
    MASTERED = "mastered"  # one master owns the robot
    PAUSED = "paused"  # its master is paused: it sends nothing, the robot holds
    INTERVENED = "intervened"  # an intervening master drives; the paused master waits
    ESTOPPED = "estopped"  # nothing moves until an explicit reset


@dataclass(frozen=True, slots=True)
class SafetyState:
    """The machine's whole state. `owner` may be set in ESTOPPED (a live master waiting).
    In INTERVENED `owner` is the intervening master and `waiting` the paused one."""

    mode: Mode = Mode.IDLE
    owner: str | None = None
    waiting: str | None = None  # the master an intervention paused (INTERVENED only)
    waiting_autonomous: bool = False  # `owner_autonomous` of the paused master
    owner_autonomous: bool = False  # plays a program (sequence, replay): ends on e-stop
    estop_reason: str | None = None
    loss_policy: LossPolicy = LossPolicy.ESTOP
    estop_severity: Severity = Severity.CRITICAL


# ---------------------------------------------------------------------------------------------
# Events


@dataclass(frozen=True, slots=True)
class MasterAttach:
    """A master asks to own the robot; `takeover` displaces the current one. `kind` and
    `description` say what it is (`mock-sequence`, "sequence 'gentle-wave'"): a master it
    displaces is told."""

    master_id: str
    autonomous: bool = False
    takeover: bool = False
    kind: str = ""
    description: str = ""


@dataclass(frozen=True, slots=True)
class MasterDetach:
    """A master leaves of its own accord: `hold` stops motion in progress where it is (an
    operator's stop); without it the last command completes (a sequence that finished)."""

    master_id: str
    hold: bool = True


@dataclass(frozen=True, slots=True)
class MasterLost:
    """A master's connection dropped or its driver failed."""

    master_id: str
    reason: str = "connection lost"


@dataclass(frozen=True, slots=True)
class MasterCommand:
    """A command from the master `source`."""

    source: str


@dataclass(frozen=True, slots=True)
class ManualCommand:
    """A command from manual control (sliders, REST joints)."""


@dataclass(frozen=True, slots=True)
class EStop:
    """Emergency stop."""

    reason: str = "emergency stop"


@dataclass(frozen=True, slots=True)
class Reset:
    """Leave the e-stop."""


@dataclass(frozen=True, slots=True)
class SlaveAttach:
    """A slave joins."""

    slave_id: str


@dataclass(frozen=True, slots=True)
class SlaveDetach:
    """A slave leaves of its own accord."""

    slave_id: str


@dataclass(frozen=True, slots=True)
class SlaveError:
    """A slave reports a fault."""

    slave_id: str
    severity: Severity
    message: str = ""


@dataclass(frozen=True, slots=True)
class SlaveLost:
    """A slave stopped answering or its driver failed."""

    slave_id: str
    reason: str = "connection lost"


@dataclass(frozen=True, slots=True)
class HeartbeatTimeout:
    """A peer was silent past its timeout (a master or a slave)."""

    peer_id: str


@dataclass(frozen=True, slots=True)
class MasterPause:
    """Pause the robot's master: it sends nothing, the robot holds where it is."""


@dataclass(frozen=True, slots=True)
class MasterResume:
    """Resume the paused master."""


@dataclass(frozen=True, slots=True)
class Intervene:
    """A master (`master_id`, as `MasterAttach` names one) intervenes: the running master is
    paused, not ended, and the intervening one drives until the intervention ends."""

    master_id: str
    autonomous: bool = False
    kind: str = ""
    description: str = ""


@dataclass(frozen=True, slots=True)
class InterventionEnd:
    """End the intervention: the intervening master goes; the paused master resumes unless
    `resume` is false (then it stays paused)."""

    resume: bool = True


Event: TypeAlias = (
    MasterAttach
    | MasterDetach
    | MasterLost
    | MasterCommand
    | ManualCommand
    | EStop
    | Reset
    | SlaveAttach
    | SlaveDetach
    | SlaveError
    | SlaveLost
    | HeartbeatTimeout
    | MasterPause
    | MasterResume
    | Intervene
    | InterventionEnd
)
EVENT_TYPES: tuple[type[Event], ...] = (
    MasterAttach,
    MasterDetach,
    MasterLost,
    MasterCommand,
    ManualCommand,
    EStop,
    Reset,
    SlaveAttach,
    SlaveDetach,
    SlaveError,
    SlaveLost,
    HeartbeatTimeout,
    MasterPause,
    MasterResume,
    Intervene,
    InterventionEnd,
)


# ---------------------------------------------------------------------------------------------
# Effects: what the actor must do when a transition is allowed


@dataclass(frozen=True, slots=True)
class ApplyCommand:
    """Pass the command on to the motion filter."""


@dataclass(frozen=True, slots=True)
class DetachMaster:
    """End a master's ownership and tell it why (`by`: the attach that took over)."""

    master_id: str
    code: ErrorCode
    message: str
    by: MasterAttach | None = None


@dataclass(frozen=True, slots=True)
class StopMotion:
    """Freeze every target where it is and tell the slaves to stop."""

    reason: str


@dataclass(frozen=True, slots=True)
class HoldPosition:
    """Freeze every target where it is; slaves keep holding the last target."""


@dataclass(frozen=True, slots=True)
class ResumeSlaves:
    """Tell the slaves the e-stop is over (no motion until a new command)."""


@dataclass(frozen=True, slots=True)
class PauseMaster:
    """Tell the master it is paused: it sends nothing until resumed (a policy keeps its worker
    loaded and drops the actions it computed)."""

    master_id: str


@dataclass(frozen=True, slots=True)
class ResumeMaster:
    """Tell the paused master it may command again (a policy from a fresh observation)."""

    master_id: str


@dataclass(frozen=True, slots=True)
class Intervention:
    """An intervention starts (`master_id`, the intervening master, drives; `paused` waits) or
    ends (`ended`; `code` None: the intervening master left by itself, else it is told why).
    The paused master is the robot's master again once it ends."""

    master_id: str
    paused: str
    ended: bool = False
    code: ErrorCode | None = None
    message: str = ""


Effect: TypeAlias = (
    ApplyCommand
    | DetachMaster
    | StopMotion
    | HoldPosition
    | ResumeSlaves
    | PauseMaster
    | ResumeMaster
    | Intervention
)


# ---------------------------------------------------------------------------------------------
# Outcomes


@dataclass(frozen=True, slots=True)
class Allowed:
    """The event is accepted: move to `state` and carry out `effects` in order."""

    state: SafetyState
    effects: tuple[Effect, ...] = ()


@dataclass(frozen=True, slots=True)
class Refused:
    """The event is refused; the sender gets `code` and `message`. State is unchanged."""

    code: ErrorCode
    message: str


@dataclass(frozen=True, slots=True)
class Ignored:
    """The event changes nothing and needs no answer beyond `reason`."""

    reason: str


Outcome: TypeAlias = Allowed | Refused | Ignored
Rule: TypeAlias = Callable[[SafetyState, Event], Outcome]


# ---------------------------------------------------------------------------------------------
# What several rules share


#: The effects of an allowed command, shared: effects are immutable values.
APPLY_COMMAND = (ApplyCommand(),)


def estop_state(state: SafetyState, reason: str) -> tuple[SafetyState, tuple[Effect, ...]]:
    """Enter ESTOPPED: autonomous masters end, live masters stay but may not move the robot;
    a paused master and an intervention end whole (an e-stop ends the correction and the
    policy alike)."""
    effects: list[Effect] = [StopMotion(reason)]
    told = f"Stopped by e-stop: {reason}."
    if state.waiting is not None:
        effects.append(DetachMaster(state.waiting, ErrorCode.ESTOPPED, told))
    owner = state.owner
    ends = state.owner_autonomous or state.mode in (Mode.PAUSED, Mode.INTERVENED)
    if owner is not None and ends:
        effects.append(DetachMaster(owner, ErrorCode.ESTOPPED, told))
        owner = None
    new = replace(
        state,
        mode=Mode.ESTOPPED,
        owner=owner,
        waiting=None,
        waiting_autonomous=False,
        owner_autonomous=state.owner_autonomous and owner is not None,
        estop_reason=reason,
    )
    return new, tuple(effects)
