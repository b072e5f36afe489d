"""The robot's ownership and safety state machine: one table, one pure function.

`transition(state, event)` looks up the rule for (state.mode, type(event)) in `TABLE` and
returns what happens: `Allowed` (a new state and the effects the actor must carry out),
`Refused` (an error code and a sentence for the sender) or `Ignored`. Everything that affects
who may command the robot lives in this file and its two halves kept apart for length: the
values it speaks of (`safety_types`: modes, state, events, effects, outcomes, re-exported here)
and the rules of pause, resume and intervention (`safety_pause`). No trio, no I/O, no clock.

The same table is written out in specs/safety-state-machine.md; a test keeps the two in step.
"""

from __future__ import annotations

from dataclasses import replace

from arena.protocol.errors import ErrorCode
from arena.robot.model import LossPolicy
from arena.robot.safety_pause import (
    already_paused,
    attach_while_intervened,
    detach_while_intervened,
    end_intervention,
    estop_intervened,
    estop_paused,
    intervene,
    intervened_command,
    lose_while_intervened,
    not_paused,
    pause,
    paused_command,
    refuse_intervention_active,
    refuse_no_intervention,
    refuse_no_master,
    resume,
)
from arena.robot.safety_types import (
    APPLY_COMMAND,
    EVENT_TYPES,
    Allowed,
    ApplyCommand,
    DetachMaster,
    Effect,
    EStop,
    Event,
    HeartbeatTimeout,
    HoldPosition,
    Ignored,
    Intervene,
    Intervention,
    InterventionEnd,
    ManualCommand,
    MasterAttach,
    MasterCommand,
    MasterDetach,
    MasterLost,
    MasterPause,
    MasterResume,
    Mode,
    Outcome,
    PauseMaster,
    Refused,
    Reset,
    ResumeMaster,
    ResumeSlaves,
    Rule,
    SafetyState,
    SlaveAttach,
    SlaveDetach,
    SlaveError,
    SlaveLost,
    StopMotion,
    estop_state,
)

__all__ = [
    "EVENT_TYPES",
    "TABLE",
    "Allowed",
    "ApplyCommand",
    "DetachMaster",
    "EStop",
    "Effect",
    "Event",
    "HeartbeatTimeout",
    "HoldPosition",
    "Ignored",
    "Intervene",
    "Intervention",
    "InterventionEnd",
    "ManualCommand",
    "MasterAttach",
    "MasterCommand",
    "MasterDetach",
    "MasterLost",
    "MasterPause",
    "MasterResume",
    "Mode",
    "Outcome",
    "PauseMaster",
    "Refused",
    "Reset",
    "ResumeMaster",
    "ResumeSlaves",
    "Rule",
    "SafetyState",
    "SlaveAttach",
    "SlaveDetach",
    "SlaveError",
    "SlaveLost",
    "StopMotion",
    "describe_table",
    "transition",
]


# ---------------------------------------------------------------------------------------------
# Rules. Each one's docstring is its summary: the text of its cell in the spec table. (A
# docstring, not a registering decorator, so that `make mutants` can mutate the rules: mutmut
# leaves decorated functions alone.)


def _apply_loss_policy(state: SafetyState, why: str) -> Outcome:
    if state.loss_policy is LossPolicy.HOLD:
        return Allowed(
            replace(state, mode=Mode.IDLE, owner=None, owner_autonomous=False), (HoldPosition(),)
        )
    new, effects = estop_state(replace(state, owner=None, owner_autonomous=False), why)
    return Allowed(new, effects)


def _claim(state: SafetyState, event: Event) -> Outcome:
    """allowed: becomes owner -> mastered"""
    assert isinstance(event, MasterAttach)
    return Allowed(
        replace(state, mode=Mode.MASTERED, owner=event.master_id, owner_autonomous=event.autonomous)
    )


def _refuse_or_take_over(state: SafetyState, event: MasterAttach) -> Refused | DetachMaster:
    """A master attaching while another holds the robot (an id is a label, not a credential:
    a second connection under the owner's id is another master): refused, or with takeover
    the previous one is detached."""
    assert state.owner is not None
    if not event.takeover:
        if event.master_id == state.owner:
            return Refused(
                ErrorCode.MASTER_ACTIVE,
                f"A master called {state.owner!r} is connected already; a second connection "
                "under that id is another master: ask for takeover to replace it.",
            )
        return Refused(
            ErrorCode.MASTER_ACTIVE,
            f"Robot is controlled by master {state.owner!r}; ask for takeover to replace it.",
        )
    what = f" ({event.description})" if event.description else ""
    return DetachMaster(
        state.owner,
        ErrorCode.TAKEN_OVER,
        f"Master {event.master_id!r}{what} took over the robot.",
        event,
    )


def _claim_or_takeover(state: SafetyState, event: Event) -> Outcome:
    """takeover: previous master detached (TAKEN_OVER, told who took over), even under the same id;
    else refused
    """
    assert isinstance(event, MasterAttach)
    answer = _refuse_or_take_over(state, event)
    if isinstance(answer, Refused):
        return answer
    new = replace(
        state, mode=Mode.MASTERED, owner=event.master_id, owner_autonomous=event.autonomous
    )
    return Allowed(new, (answer,))


def _claim_while_estopped(state: SafetyState, event: Event) -> Outcome:
    """live master: becomes owner, stays estopped (takeover needed if owned, even under the same
    id); autonomous: refused ESTOPPED
    """
    assert isinstance(event, MasterAttach)
    if event.autonomous:
        return Refused(
            ErrorCode.ESTOPPED, "Robot is e-stopped; reset it before starting a sequence or replay."
        )
    if state.owner is None:
        return Allowed(replace(state, owner=event.master_id, owner_autonomous=False))
    answer = _refuse_or_take_over(state, event)
    if isinstance(answer, Refused):
        return answer
    return Allowed(replace(state, owner=event.master_id, owner_autonomous=False), (answer,))


def _no_master(state: SafetyState, event: Event) -> Outcome:
    """ignored: no master"""
    return Ignored("the robot has no master")


def _release(state: SafetyState, event: Event) -> Outcome:
    """owner: allowed -> idle (hold position if asked, else the last move completes); others:
    ignored
    """
    assert isinstance(event, MasterDetach)
    if event.master_id != state.owner:
        return Ignored("not the owner")
    effects: tuple[Effect, ...] = (HoldPosition(),) if event.hold else ()
    return Allowed(replace(state, mode=Mode.IDLE, owner=None, owner_autonomous=False), effects)


def _release_while_estopped(state: SafetyState, event: Event) -> Outcome:
    """owner: allowed, ownership ends, stays estopped; others: ignored"""
    assert isinstance(event, MasterDetach | MasterLost | HeartbeatTimeout)
    peer = event.peer_id if isinstance(event, HeartbeatTimeout) else event.master_id
    if peer != state.owner:
        return Ignored("not the owner")
    return Allowed(replace(state, owner=None, owner_autonomous=False))


def _lose_master(state: SafetyState, event: Event) -> Outcome:
    """owner: loss policy (estop: e-stop -> estopped; hold: hold position -> idle);
    others: ignored"""
    assert isinstance(event, MasterLost | HeartbeatTimeout)
    if isinstance(event, HeartbeatTimeout):
        peer, why = event.peer_id, "heartbeat timeout"
    else:
        peer, why = event.master_id, event.reason
    if peer != state.owner:
        return Ignored("not the owner")
    return _apply_loss_policy(state, f"master {peer!r} lost: {why}")


def _command_without_master(state: SafetyState, event: Event) -> Outcome:
    """refused NOT_OWNER"""
    assert isinstance(event, MasterCommand)
    return Refused(
        ErrorCode.NOT_OWNER, f"{event.source!r} is not this robot's master; attach as master first."
    )


def _owner_command(state: SafetyState, event: Event) -> Outcome:
    """owner: allowed, apply; others: refused NOT_OWNER"""
    assert isinstance(event, MasterCommand)
    if event.source != state.owner:
        return Refused(
            ErrorCode.NOT_OWNER,
            f"Robot is controlled by master {state.owner!r}, not {event.source!r}.",
        )
    return Allowed(state, APPLY_COMMAND)


def _refuse_estopped(state: SafetyState, event: Event) -> Outcome:
    """refused ESTOPPED"""
    return Refused(
        ErrorCode.ESTOPPED, f"Robot is e-stopped ({state.estop_reason}); reset it first."
    )


def _manual_command(state: SafetyState, event: Event) -> Outcome:
    """allowed, apply"""
    return Allowed(state, APPLY_COMMAND)


def _manual_refused(state: SafetyState, event: Event) -> Outcome:
    """refused MASTER_ACTIVE"""
    return Refused(
        ErrorCode.MASTER_ACTIVE,
        f"Manual control is off while master {state.owner!r} controls the robot.",
    )


def _estop(state: SafetyState, event: Event) -> Outcome:
    """allowed: stop motion, autonomous master detached -> estopped"""
    assert isinstance(event, EStop)
    new, effects = estop_state(state, event.reason)
    return Allowed(new, effects)


def _already_estopped(state: SafetyState, event: Event) -> Outcome:
    """ignored: already estopped"""
    return Ignored("already e-stopped")


def _reset(state: SafetyState, event: Event) -> Outcome:
    """allowed: slaves resumed, no motion -> mastered if owner else idle"""
    mode = Mode.MASTERED if state.owner is not None else Mode.IDLE
    return Allowed(replace(state, mode=mode, estop_reason=None), (ResumeSlaves(),))


def _not_estopped(state: SafetyState, event: Event) -> Outcome:
    """ignored: not estopped"""
    return Ignored("not e-stopped")


def _slave_membership(state: SafetyState, event: Event) -> Outcome:
    """allowed"""
    return Allowed(state)


def _slave_error(state: SafetyState, event: Event) -> Outcome:
    """severity >= estop_severity: e-stop -> estopped; else allowed"""
    assert isinstance(event, SlaveError)
    if event.severity.rank < state.estop_severity.rank:
        return Allowed(state)
    reason = f"slave {event.slave_id!r} reported a {event.severity} fault: {event.message}"
    new, effects = estop_state(state, reason)
    return Allowed(new, effects)


def _slave_error_while_estopped(state: SafetyState, event: Event) -> Outcome:
    """allowed: stays estopped"""
    return Allowed(state)


def _lose_slave(state: SafetyState, event: Event) -> Outcome:
    """loss policy (estop: e-stop -> estopped; hold: hold position)"""
    assert isinstance(event, SlaveLost)
    why = f"slave {event.slave_id!r} lost: {event.reason}"
    if state.loss_policy is LossPolicy.HOLD:
        return Allowed(state, (HoldPosition(),))
    new, effects = estop_state(state, why)
    return Allowed(new, effects)


_I, _M, _E = Mode.IDLE, Mode.MASTERED, Mode.ESTOPPED
_P, _N = Mode.PAUSED, Mode.INTERVENED

#: Every (mode, event type) pair and its rule. Heartbeat timeouts name the peer; a timed-out
#: slave is reported by the actor as SlaveLost, so here a timeout concerns masters only.
TABLE: dict[tuple[Mode, type[Event]], Rule] = {
    (_I, MasterAttach): _claim,
    (_M, MasterAttach): _claim_or_takeover,
    (_E, MasterAttach): _claim_while_estopped,
    (_I, MasterDetach): _no_master,
    (_M, MasterDetach): _release,
    (_E, MasterDetach): _release_while_estopped,
    (_I, MasterLost): _no_master,
    (_M, MasterLost): _lose_master,
    (_E, MasterLost): _release_while_estopped,
    (_I, HeartbeatTimeout): _no_master,
    (_M, HeartbeatTimeout): _lose_master,
    (_E, HeartbeatTimeout): _release_while_estopped,
    (_I, MasterCommand): _command_without_master,
    (_M, MasterCommand): _owner_command,
    (_E, MasterCommand): _refuse_estopped,
    (_I, ManualCommand): _manual_command,
    (_M, ManualCommand): _manual_refused,
    (_E, ManualCommand): _refuse_estopped,
    (_I, EStop): _estop,
    (_M, EStop): _estop,
    (_E, EStop): _already_estopped,
    (_I, Reset): _not_estopped,
    (_M, Reset): _not_estopped,
    (_E, Reset): _reset,
    (_I, SlaveAttach): _slave_membership,
    (_M, SlaveAttach): _slave_membership,
    (_E, SlaveAttach): _slave_membership,
    (_I, SlaveDetach): _slave_membership,
    (_M, SlaveDetach): _slave_membership,
    (_E, SlaveDetach): _slave_membership,
    (_I, SlaveError): _slave_error,
    (_M, SlaveError): _slave_error,
    (_E, SlaveError): _slave_error_while_estopped,
    (_I, SlaveLost): _lose_slave,
    (_M, SlaveLost): _lose_slave,
    (_E, SlaveLost): _slave_error_while_estopped,
    # A paused master still owns the robot: the rules of a mastered robot, but for commands.
    (_P, MasterAttach): _claim_or_takeover,
    (_P, MasterDetach): _release,
    (_P, MasterLost): _lose_master,
    (_P, HeartbeatTimeout): _lose_master,
    (_P, MasterCommand): paused_command,
    (_P, ManualCommand): _manual_refused,
    (_P, EStop): estop_paused,
    (_P, Reset): _not_estopped,
    (_P, SlaveAttach): _slave_membership,
    (_P, SlaveDetach): _slave_membership,
    (_P, SlaveError): _slave_error,
    (_P, SlaveLost): _lose_slave,
    (_N, MasterAttach): attach_while_intervened,
    (_N, MasterDetach): detach_while_intervened,
    (_N, MasterLost): lose_while_intervened,
    (_N, HeartbeatTimeout): lose_while_intervened,
    (_N, MasterCommand): intervened_command,
    (_N, ManualCommand): _manual_refused,
    (_N, EStop): estop_intervened,
    (_N, Reset): _not_estopped,
    (_N, SlaveAttach): _slave_membership,
    (_N, SlaveDetach): _slave_membership,
    (_N, SlaveError): _slave_error,
    (_N, SlaveLost): _lose_slave,
    (_I, MasterPause): refuse_no_master,
    (_M, MasterPause): pause,
    (_P, MasterPause): already_paused,
    (_N, MasterPause): refuse_intervention_active,
    (_E, MasterPause): _refuse_estopped,
    (_I, MasterResume): refuse_no_master,
    (_M, MasterResume): not_paused,
    (_P, MasterResume): resume,
    (_N, MasterResume): refuse_intervention_active,
    (_E, MasterResume): _refuse_estopped,
    (_I, Intervene): refuse_no_master,
    (_M, Intervene): intervene,
    (_P, Intervene): intervene,
    (_N, Intervene): refuse_intervention_active,
    (_E, Intervene): _refuse_estopped,
    (_I, InterventionEnd): refuse_no_intervention,
    (_M, InterventionEnd): refuse_no_intervention,
    (_P, InterventionEnd): refuse_no_intervention,
    (_N, InterventionEnd): end_intervention,
    (_E, InterventionEnd): refuse_no_intervention,
}


def transition(state: SafetyState, event: Event) -> Outcome:
    """The outcome of `event` in `state`. Pure: same inputs, same answer."""
    return TABLE[(state.mode, type(event))](state, event)


def describe_table() -> dict[tuple[str, str], str]:
    """The table as text: (mode, event name) -> rule summary, as in the spec document."""
    return {(mode.value, event.__name__): _summary(rule) for (mode, event), rule in TABLE.items()}


def _summary(rule: Rule) -> str:
    """A rule's docstring on one line (a rule without one reads "None": the spec test fails)."""
    return " ".join(str(rule.__doc__).split())
