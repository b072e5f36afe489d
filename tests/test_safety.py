"""The pure safety state machine: the table, each rule, the spec, and random event sequences."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from arena.protocol.errors import ErrorCode, Severity
from arena.robot import safety as sm
from arena.robot.model import LossPolicy

SPEC = Path(__file__).resolve().parent.parent / "specs" / "safety-state-machine.md"

IDLE = sm.SafetyState()
MASTERED = sm.SafetyState(mode=sm.Mode.MASTERED, owner="alice")
MASTERED_BY_SEQUENCE = sm.SafetyState(mode=sm.Mode.MASTERED, owner="seq", owner_autonomous=True)
ESTOPPED = sm.SafetyState(mode=sm.Mode.ESTOPPED, estop_reason="button")


def test_every_mode_and_event_has_a_rule() -> None:
    for mode in sm.Mode:
        for event in sm.EVENT_TYPES:
            assert (mode, event) in sm.TABLE, (mode, event)
    assert len(sm.TABLE) == len(sm.Mode) * len(sm.EVENT_TYPES)


def test_spec_table_agrees_with_the_code() -> None:
    lines = SPEC.read_text().split("## The table", 1)[1].splitlines()
    rows = [line for line in lines if line.startswith("| ") and not line.startswith("| event")]
    documented: dict[tuple[str, str], str] = {}
    for row in rows:
        event, *cells = [c.strip() for c in row.strip().strip("|").split("|")]
        for mode, cell in zip(sm.Mode, cells, strict=True):
            documented[(mode.value, event)] = cell
    assert documented == sm.describe_table()


def test_first_master_claims_the_robot() -> None:
    outcome = sm.transition(IDLE, sm.MasterAttach("alice"))
    assert isinstance(outcome, sm.Allowed)
    assert outcome.state.mode is sm.Mode.MASTERED and outcome.state.owner == "alice"


def test_second_master_is_refused_without_takeover() -> None:
    outcome = sm.transition(MASTERED, sm.MasterAttach("bob"))
    assert isinstance(outcome, sm.Refused) and outcome.code is ErrorCode.MASTER_ACTIVE
    assert "alice" in outcome.message


def test_takeover_detaches_the_previous_master_and_tells_it_why() -> None:
    attach = sm.MasterAttach("bob", takeover=True, kind="replay", description="replay of 'x.mcap'")
    outcome = sm.transition(MASTERED, attach)
    assert isinstance(outcome, sm.Allowed)
    assert outcome.state.owner == "bob"
    (effect,) = outcome.effects
    # who took over, by label and by kind, in the words and in `by`
    assert effect == sm.DetachMaster("alice", ErrorCode.TAKEN_OVER, effect.message, attach)
    assert "'bob'" in effect.message and "replay of 'x.mcap'" in effect.message


def test_a_second_connection_under_the_owners_id_is_another_master() -> None:
    # An id is a label, not a credential: never two connections on one link.
    for state in (MASTERED, replace(MASTERED, mode=sm.Mode.ESTOPPED)):
        refused = sm.transition(state, sm.MasterAttach("alice"))
        assert isinstance(refused, sm.Refused) and refused.code is ErrorCode.MASTER_ACTIVE
        taken = sm.transition(state, sm.MasterAttach("alice", takeover=True))
        assert isinstance(taken, sm.Allowed) and taken.state.owner == "alice"
        (effect,) = taken.effects
        assert isinstance(effect, sm.DetachMaster) and effect.code is ErrorCode.TAKEN_OVER


def test_manual_control_only_without_master() -> None:
    assert isinstance(sm.transition(IDLE, sm.ManualCommand()), sm.Allowed)
    refused = sm.transition(MASTERED, sm.ManualCommand())
    assert isinstance(refused, sm.Refused) and refused.code is ErrorCode.MASTER_ACTIVE
    refused = sm.transition(ESTOPPED, sm.ManualCommand())
    assert isinstance(refused, sm.Refused) and refused.code is ErrorCode.ESTOPPED


def test_only_the_owner_commands() -> None:
    assert sm.transition(MASTERED, sm.MasterCommand("alice")) == sm.Allowed(
        MASTERED, (sm.ApplyCommand(),)
    )
    refused = sm.transition(MASTERED, sm.MasterCommand("mallory"))
    assert isinstance(refused, sm.Refused) and refused.code is ErrorCode.NOT_OWNER
    refused = sm.transition(IDLE, sm.MasterCommand("alice"))
    assert isinstance(refused, sm.Refused) and refused.code is ErrorCode.NOT_OWNER


@pytest.mark.parametrize("state", [IDLE, MASTERED, MASTERED_BY_SEQUENCE])
def test_estop_works_from_every_moving_state(state: sm.SafetyState) -> None:
    outcome = sm.transition(state, sm.EStop("operator"))
    assert isinstance(outcome, sm.Allowed)
    assert outcome.state.mode is sm.Mode.ESTOPPED
    assert outcome.state.estop_reason == "operator"
    assert sm.StopMotion("operator") in outcome.effects


def test_estop_while_estopped_is_ignored() -> None:
    assert isinstance(sm.transition(ESTOPPED, sm.EStop("again")), sm.Ignored)


def test_estop_ends_a_sequence_for_good_but_keeps_a_live_master() -> None:
    outcome = sm.transition(MASTERED_BY_SEQUENCE, sm.EStop())
    assert isinstance(outcome, sm.Allowed)
    assert outcome.state.owner is None
    assert any(
        isinstance(e, sm.DetachMaster) and e.code is ErrorCode.ESTOPPED for e in outcome.effects
    )
    reset = sm.transition(outcome.state, sm.Reset())
    assert isinstance(reset, sm.Allowed) and reset.state.mode is sm.Mode.IDLE

    live = sm.transition(MASTERED, sm.EStop())
    assert isinstance(live, sm.Allowed) and live.state.owner == "alice"
    assert not any(isinstance(e, sm.DetachMaster) for e in live.effects)
    reset = sm.transition(live.state, sm.Reset())
    assert isinstance(reset, sm.Allowed)
    assert reset.state.mode is sm.Mode.MASTERED and reset.state.owner == "alice"


def test_everything_is_refused_while_estopped() -> None:
    state = replace(ESTOPPED, owner="alice")
    for event in (sm.MasterCommand("alice"), sm.ManualCommand()):
        outcome = sm.transition(state, event)
        assert isinstance(outcome, sm.Refused) and outcome.code is ErrorCode.ESTOPPED
        assert "button" in outcome.message
    refused = sm.transition(ESTOPPED, sm.MasterAttach("seq", autonomous=True))
    assert isinstance(refused, sm.Refused) and refused.code is ErrorCode.ESTOPPED


def test_reset_moves_nothing() -> None:
    outcome = sm.transition(ESTOPPED, sm.Reset())
    assert isinstance(outcome, sm.Allowed)
    assert outcome.effects == (sm.ResumeSlaves(),)
    assert outcome.state.estop_reason is None
    assert isinstance(sm.transition(IDLE, sm.Reset()), sm.Ignored)


def test_live_master_may_attach_while_estopped_but_not_command() -> None:
    outcome = sm.transition(ESTOPPED, sm.MasterAttach("alice"))
    assert isinstance(outcome, sm.Allowed)
    assert outcome.state.mode is sm.Mode.ESTOPPED and outcome.state.owner == "alice"
    second = sm.transition(outcome.state, sm.MasterAttach("bob"))
    assert isinstance(second, sm.Refused) and second.code is ErrorCode.MASTER_ACTIVE


@pytest.mark.parametrize(
    "event", [sm.MasterLost("alice", "socket closed"), sm.HeartbeatTimeout("alice")]
)
def test_losing_the_master_estops_by_default(event: sm.Event) -> None:
    outcome = sm.transition(MASTERED, event)
    assert isinstance(outcome, sm.Allowed)
    assert outcome.state.mode is sm.Mode.ESTOPPED and outcome.state.owner is None
    assert "alice" in (outcome.state.estop_reason or "")


def test_losing_the_master_holds_position_under_the_hold_policy() -> None:
    state = replace(MASTERED, loss_policy=LossPolicy.HOLD)
    outcome = sm.transition(state, sm.MasterLost("alice"))
    assert isinstance(outcome, sm.Allowed)
    assert outcome.state.mode is sm.Mode.IDLE and outcome.state.owner is None
    assert outcome.effects == (sm.HoldPosition(),)


def test_losing_someone_else_changes_nothing() -> None:
    assert isinstance(sm.transition(MASTERED, sm.MasterLost("bob")), sm.Ignored)
    assert isinstance(sm.transition(MASTERED, sm.MasterDetach("bob")), sm.Ignored)
    assert isinstance(sm.transition(IDLE, sm.HeartbeatTimeout("bob")), sm.Ignored)


def test_voluntary_detach_holds_position() -> None:
    outcome = sm.transition(MASTERED, sm.MasterDetach("alice"))
    assert outcome == sm.Allowed(
        replace(MASTERED, mode=sm.Mode.IDLE, owner=None), (sm.HoldPosition(),)
    )


@pytest.mark.parametrize("severity", list(Severity))
def test_slave_errors_estop_at_the_configured_severity(severity: Severity) -> None:
    outcome = sm.transition(MASTERED, sm.SlaveError("arm", severity, "overheat"))
    assert isinstance(outcome, sm.Allowed)
    expect_stop = severity is Severity.CRITICAL
    assert (outcome.state.mode is sm.Mode.ESTOPPED) is expect_stop
    strict = replace(MASTERED, estop_severity=Severity.WARNING)
    strict_outcome = sm.transition(strict, sm.SlaveError("arm", severity, "overheat"))
    assert isinstance(strict_outcome, sm.Allowed)
    assert (strict_outcome.state.mode is sm.Mode.ESTOPPED) is (severity.rank >= 1)


def test_losing_a_slave_applies_the_loss_policy() -> None:
    outcome = sm.transition(IDLE, sm.SlaveLost("arm", "unplugged"))
    assert isinstance(outcome, sm.Allowed) and outcome.state.mode is sm.Mode.ESTOPPED
    held = sm.transition(replace(IDLE, loss_policy=LossPolicy.HOLD), sm.SlaveLost("arm"))
    assert isinstance(held, sm.Allowed) and held.state.mode is sm.Mode.IDLE
    assert held.effects == (sm.HoldPosition(),)


def _is_sentence(text: object) -> bool:
    """A message for a person: a non-empty sentence that ends with a full stop."""
    return isinstance(text, str) and len(text) > 1 and text.endswith(".")


STATES = [
    IDLE,
    MASTERED,
    MASTERED_BY_SEQUENCE,
    ESTOPPED,
    replace(ESTOPPED, owner="alice"),
]
REQUESTS = [
    sm.MasterAttach("bob"),
    sm.MasterAttach("alice"),
    sm.MasterAttach("bob", autonomous=True),
    sm.MasterCommand("bob"),
    sm.MasterCommand("alice"),
    sm.ManualCommand(),
]


def test_every_refusal_tells_the_sender_why_and_names_who_is_in_the_way() -> None:
    codes = set()
    for state in STATES:
        for event in REQUESTS:
            outcome = sm.transition(state, event)
            if not isinstance(outcome, sm.Refused):
                continue
            codes.add(outcome.code)
            assert _is_sentence(outcome.message), (state, event, outcome)
            if outcome.code is ErrorCode.NOT_OWNER:
                assert isinstance(event, sm.MasterCommand)
                assert repr(event.source) in outcome.message
            if outcome.code is ErrorCode.MASTER_ACTIVE:
                assert repr(state.owner) in outcome.message
            if outcome.code is ErrorCode.ESTOPPED:
                assert "e-stopped" in outcome.message
    assert codes == {ErrorCode.NOT_OWNER, ErrorCode.MASTER_ACTIVE, ErrorCode.ESTOPPED}


def test_a_master_detached_by_an_estop_is_told_the_reason() -> None:
    outcome = sm.transition(MASTERED_BY_SEQUENCE, sm.EStop("operator pressed stop"))
    assert isinstance(outcome, sm.Allowed)
    (detach,) = [e for e in outcome.effects if isinstance(e, sm.DetachMaster)]
    assert detach.master_id == "seq"
    assert _is_sentence(detach.message) and "operator pressed stop" in detach.message


def test_a_live_master_taking_over_while_estopped_stays_live() -> None:
    # Taking over from a live master while e-stopped gives a live master: after the reset, the
    # next e-stop keeps it (only programs end for good).
    taken = sm.transition(replace(ESTOPPED, owner="alice"), sm.MasterAttach("bob", takeover=True))
    assert isinstance(taken, sm.Allowed) and taken.state.owner == "bob"
    reset = sm.transition(taken.state, sm.Reset())
    assert isinstance(reset, sm.Allowed) and reset.state.owner == "bob"
    stopped = sm.transition(reset.state, sm.EStop("again"))
    assert isinstance(stopped, sm.Allowed)
    assert stopped.state.owner == "bob"
    assert not any(isinstance(e, sm.DetachMaster) for e in stopped.effects)


@pytest.mark.parametrize("state", [IDLE, MASTERED])
def test_losing_a_slave_stops_motion_and_says_which_and_why(state: sm.SafetyState) -> None:
    outcome = sm.transition(state, sm.SlaveLost("arm", "unplugged"))
    assert isinstance(outcome, sm.Allowed)
    (stop,) = [e for e in outcome.effects if isinstance(e, sm.StopMotion)]
    assert "'arm'" in stop.reason and "unplugged" in stop.reason
    assert outcome.state.estop_reason == stop.reason


def test_a_critical_slave_fault_stops_motion_and_says_which_and_why() -> None:
    outcome = sm.transition(MASTERED, sm.SlaveError("arm", Severity.CRITICAL, "overheat"))
    assert isinstance(outcome, sm.Allowed)
    (stop,) = [e for e in outcome.effects if isinstance(e, sm.StopMotion)]
    assert "'arm'" in stop.reason and "overheat" in stop.reason
    assert outcome.state.estop_reason == stop.reason


def test_a_program_that_detaches_leaves_no_program_behind() -> None:
    outcome = sm.transition(MASTERED_BY_SEQUENCE, sm.MasterDetach("seq"))
    assert isinstance(outcome, sm.Allowed)
    assert outcome.state.owner is None and not outcome.state.owner_autonomous


def test_a_second_connection_under_the_owners_id_is_told_so() -> None:
    same = sm.transition(MASTERED, sm.MasterAttach("alice"))
    other = sm.transition(MASTERED, sm.MasterAttach("bob"))
    assert isinstance(same, sm.Refused) and isinstance(other, sm.Refused)
    assert "connected already" in same.message
    assert "connected already" not in other.message


def test_a_heartbeat_timeout_is_named_in_the_estop_reason() -> None:
    outcome = sm.transition(MASTERED, sm.HeartbeatTimeout("alice"))
    assert isinstance(outcome, sm.Allowed)
    assert "'alice'" in (outcome.state.estop_reason or "")
    assert (outcome.state.estop_reason or "").endswith(": heartbeat timeout")


# --- random sequences -------------------------------------------------------------------------

PEERS = st.sampled_from(["alice", "bob", "seq"])
EVENTS = st.one_of(
    st.builds(sm.MasterAttach, PEERS, st.booleans(), st.booleans()),
    st.builds(sm.MasterDetach, PEERS),
    st.builds(sm.MasterLost, PEERS),
    st.builds(sm.MasterCommand, PEERS),
    st.just(sm.ManualCommand()),
    st.builds(sm.EStop, st.sampled_from(["a", "b"])),
    st.just(sm.Reset()),
    st.builds(sm.SlaveAttach, PEERS),
    st.builds(sm.SlaveDetach, PEERS),
    st.builds(sm.SlaveError, PEERS, st.sampled_from(list(Severity))),
    st.builds(sm.SlaveLost, PEERS),
    st.builds(sm.HeartbeatTimeout, PEERS),
)


@settings(max_examples=400)
@given(st.sampled_from(list(LossPolicy)), st.lists(EVENTS, max_size=40))
def test_random_event_sequences_keep_the_invariants(
    policy: LossPolicy, events: list[sm.Event]
) -> None:
    state = sm.SafetyState(loss_policy=policy)
    for event in events:
        before = state
        outcome = sm.transition(state, event)
        assert sm.transition(before, event) == outcome  # pure: same input, same answer
        if isinstance(outcome, sm.Allowed):
            state = outcome.state
        # Ownership is consistent with the mode.
        assert (state.mode is sm.Mode.MASTERED) == (
            state.owner is not None and state.mode is not sm.Mode.ESTOPPED
        )
        assert state.mode is not sm.Mode.IDLE or state.owner is None
        assert state.owner is not None or not state.owner_autonomous
        # An autonomous owner never survives into the e-stop.
        assert not (state.mode is sm.Mode.ESTOPPED and state.owner_autonomous)
        # A command is applied only for the owner of a robot that is not e-stopped.
        if isinstance(event, sm.MasterCommand | sm.ManualCommand) and isinstance(
            outcome, sm.Allowed
        ):
            assert before.mode is not sm.Mode.ESTOPPED
            if isinstance(event, sm.MasterCommand):
                assert event.source == before.owner
            else:
                assert before.owner is None
        # The owner changes only through attach (with takeover when owned) or loss/detach/estop.
        if state.owner != before.owner and state.owner is not None:
            assert isinstance(event, sm.MasterAttach) and event.master_id == state.owner
            if before.owner is not None:
                assert event.takeover
                assert isinstance(outcome, sm.Allowed)
                assert any(
                    isinstance(e, sm.DetachMaster) and e.master_id == before.owner
                    for e in outcome.effects
                )
        # Only Reset leaves the e-stop.
        if before.mode is sm.Mode.ESTOPPED and state.mode is not sm.Mode.ESTOPPED:
            assert isinstance(event, sm.Reset)
