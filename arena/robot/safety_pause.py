"""The rules of the safety table for pause, resume and intervention (the table itself, with
every other rule, is `arena.robot.safety.TABLE`; this module only keeps that file within its
length). Pure: no trio, no I/O, no clock. Each rule's docstring is its cell in the spec table."""

from __future__ import annotations

from dataclasses import replace

from arena.protocol.errors import ErrorCode
from arena.robot.model import LossPolicy
from arena.robot.safety_types import (
    APPLY_COMMAND,
    Allowed,
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
    MasterAttach,
    MasterCommand,
    MasterDetach,
    MasterLost,
    Mode,
    Outcome,
    PauseMaster,
    Refused,
    ResumeMaster,
    SafetyState,
    estop_state,
)


def _hand_back(state: SafetyState, resume: bool, code: ErrorCode | None, message: str) -> Allowed:
    """The intervention ends: the intervening master goes, the robot holds, and the paused
    master resumes (else stays paused)."""
    assert state.owner is not None and state.waiting is not None
    waiting = state.waiting
    ended = Intervention(state.owner, waiting, True, code, message)
    autonomous = state.waiting_autonomous
    new = replace(
        state, owner=waiting, waiting=None, owner_autonomous=autonomous, waiting_autonomous=False
    )
    if resume:
        effects = (HoldPosition(), ended, ResumeMaster(waiting))
        return Allowed(replace(new, mode=Mode.MASTERED), effects)
    return Allowed(replace(new, mode=Mode.PAUSED), (HoldPosition(), ended))


def refuse_no_master(state: SafetyState, event: Event) -> Outcome:
    """refused NO_MASTER"""
    return Refused(ErrorCode.NO_MASTER, "The robot has no master to pause, resume or correct.")


def refuse_intervention_active(state: SafetyState, event: Event) -> Outcome:
    """refused INTERVENTION_ACTIVE"""
    return Refused(
        ErrorCode.INTERVENTION_ACTIVE,
        f"Master {state.owner!r} is intervening while {state.waiting!r} waits: end the "
        "intervention first.",
    )


def refuse_no_intervention(state: SafetyState, event: Event) -> Outcome:
    """refused NO_INTERVENTION"""
    return Refused(ErrorCode.NO_INTERVENTION, "No intervention is running on this robot.")


def pause(state: SafetyState, event: Event) -> Outcome:
    """allowed: master paused, hold position -> paused"""
    assert state.owner is not None
    return Allowed(replace(state, mode=Mode.PAUSED), (HoldPosition(), PauseMaster(state.owner)))


def already_paused(state: SafetyState, event: Event) -> Outcome:
    """ignored: already paused"""
    return Ignored("already paused")


def not_paused(state: SafetyState, event: Event) -> Outcome:
    """ignored: not paused"""
    return Ignored("not paused")


def resume(state: SafetyState, event: Event) -> Outcome:
    """allowed: master resumed -> mastered"""
    assert state.owner is not None
    return Allowed(replace(state, mode=Mode.MASTERED), (ResumeMaster(state.owner),))


def intervene(state: SafetyState, event: Event) -> Outcome:
    """allowed: master paused (if running), hold position, intervening master drives ->
    intervened; under the master's own id: refused MASTER_ACTIVE"""
    assert isinstance(event, Intervene) and state.owner is not None
    if event.master_id == state.owner:
        return Refused(
            ErrorCode.MASTER_ACTIVE,
            f"{event.master_id!r} is the robot's master already; intervene under another id.",
        )
    effects: list[Effect] = [HoldPosition()]
    if state.mode is Mode.MASTERED:
        effects.append(PauseMaster(state.owner))
    effects.append(Intervention(event.master_id, state.owner))
    new = replace(
        state,
        mode=Mode.INTERVENED,
        owner=event.master_id,
        owner_autonomous=event.autonomous,
        waiting=state.owner,
        waiting_autonomous=state.owner_autonomous,
    )
    return Allowed(new, tuple(effects))


def end_intervention(state: SafetyState, event: Event) -> Outcome:
    """allowed: intervening master detached (INTERVENTION_ENDED), hold position; the paused
    master resumes -> mastered (resume false: it stays paused -> paused)"""
    assert isinstance(event, InterventionEnd)
    message = "The intervention was ended; the robot is handed back to its master."
    return _hand_back(state, event.resume, ErrorCode.INTERVENTION_ENDED, message)


def attach_while_intervened(state: SafetyState, event: Event) -> Outcome:
    """takeover: the intervening and the paused master detached (TAKEN_OVER) -> mastered;
    else refused INTERVENTION_ACTIVE"""
    assert isinstance(event, MasterAttach)
    if not event.takeover:
        return refuse_intervention_active(state, event)
    assert state.owner is not None and state.waiting is not None
    what = f" ({event.description})" if event.description else ""
    told = f"Master {event.master_id!r}{what} took over the robot."
    effects = (
        DetachMaster(state.waiting, ErrorCode.TAKEN_OVER, told, event),
        DetachMaster(state.owner, ErrorCode.TAKEN_OVER, told, event),
    )
    new = replace(
        state,
        mode=Mode.MASTERED,
        owner=event.master_id,
        owner_autonomous=event.autonomous,
        waiting=None,
        waiting_autonomous=False,
    )
    return Allowed(new, effects)


def _waiting_ends(state: SafetyState, why: str) -> Outcome:
    """The paused master of an intervention ends: the intervening one is the master now."""
    assert state.waiting is not None
    gone = DetachMaster(state.waiting, ErrorCode.MASTER_LOST, why)
    new = replace(state, mode=Mode.MASTERED, waiting=None, waiting_autonomous=False)
    return Allowed(new, (gone,))


def detach_while_intervened(state: SafetyState, event: Event) -> Outcome:
    """intervening master: the intervention ends, hold position, the paused master resumes ->
    mastered; paused master: it ends, the intervening one stays -> mastered; others: ignored"""
    assert isinstance(event, MasterDetach)
    if event.master_id == state.owner:
        return _hand_back(state, True, None, "")
    if event.master_id == state.waiting:
        return _waiting_ends(state, "The paused master left.")
    return Ignored("not a master of this robot")


def lose_while_intervened(state: SafetyState, event: Event) -> Outcome:
    """intervening master: loss policy (estop: e-stop, both end -> estopped; hold: hold
    position, the paused master stays paused -> paused); paused master: it ends, the
    intervening one stays -> mastered; others: ignored"""
    assert isinstance(event, MasterLost | HeartbeatTimeout)
    if isinstance(event, HeartbeatTimeout):
        peer, why = event.peer_id, "heartbeat timeout"
    else:
        peer, why = event.master_id, event.reason
    if peer == state.waiting:
        return _waiting_ends(state, f"The paused master was lost: {why}.")
    if peer != state.owner:
        return Ignored("not a master of this robot")
    if state.loss_policy is LossPolicy.HOLD:
        return _hand_back(state, False, None, "")
    new, effects = estop_state(state, f"intervening master {peer!r} lost: {why}")
    return Allowed(new, effects)


def paused_command(state: SafetyState, event: Event) -> Outcome:
    """owner: refused MASTER_PAUSED; others: refused NOT_OWNER"""
    assert isinstance(event, MasterCommand)
    if event.source == state.owner:
        return _refuse_paused(event.source)
    return Refused(
        ErrorCode.NOT_OWNER, f"Robot is controlled by master {state.owner!r}, not {event.source!r}."
    )


def _refuse_paused(source: str) -> Refused:
    return Refused(
        ErrorCode.MASTER_PAUSED, f"Master {source!r} is paused; it may command once resumed."
    )


def intervened_command(state: SafetyState, event: Event) -> Outcome:
    """intervening master: allowed, apply; paused master: refused MASTER_PAUSED; others:
    refused NOT_OWNER"""
    assert isinstance(event, MasterCommand)
    if event.source == state.owner:
        return Allowed(state, APPLY_COMMAND)
    if event.source == state.waiting:
        return _refuse_paused(event.source)
    return Refused(
        ErrorCode.NOT_OWNER,
        f"Master {state.owner!r} is intervening on this robot, not {event.source!r}.",
    )


def estop_paused(state: SafetyState, event: Event) -> Outcome:
    """allowed: stop motion, the paused master detached -> estopped"""
    assert isinstance(event, EStop)
    new, effects = estop_state(state, event.reason)
    return Allowed(new, effects)


def estop_intervened(state: SafetyState, event: Event) -> Outcome:
    """allowed: stop motion, the intervening and the paused master detached -> estopped"""
    assert isinstance(event, EStop)
    new, effects = estop_state(state, event.reason)
    return Allowed(new, effects)
