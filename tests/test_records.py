"""Records are derived from their events' fields, and come out as the files already hold them."""

from __future__ import annotations

import msgspec

from arena.protocol.errors import ErrorCode, Severity
from arena.protocol.messages import ClampInfo, JointValue
from arena.recording.records import RECORD_TYPES, Recorded, derive_record, record_of
from arena.robot.events import (
    Audited,
    CommandHandled,
    EpisodeChanged,
    FaultReported,
    InterventionChanged,
    JointStatesReceived,
    MotionStopped,
    Observed,
    PeerChanged,
    PolicyInferred,
    RobotEvent,
    StateChanged,
    TargetsSent,
)
from arena.robot.motion import Command, CommandResult
from arena.robot.safety import Mode


def test_every_kind_of_event_is_recorded_byte_for_byte_as_before() -> None:
    # What the hand-written records made of these events before records were derived: old
    # files and new ones must read alike (field order, names, enums as values, defaults).
    clamp = ClampInfo("Jaw", 900.0, 100.0)
    command = Command((JointValue("Rotation", 3.0, 10.0), JointValue("Jaw", 900.0)), 0.25, "ui")
    cases: list[tuple[RobotEvent, str, str]] = [
        (
            CommandHandled("a", "m1", command, CommandResult(True, None, "ok", (clamp,)), 3.0, 4.0),
            "command",
            '{"t":3.0,"source":"m1","joints":[{"name":"Rotation","value":3.0,"speed":10.0},'
            '{"name":"Jaw","value":900.0}],"duration":250.0,"label":"ui","accepted":true,'
            '"code":null,"message":"ok","clamped":[{"joint":"Jaw","requested":900.0,'
            '"applied":100.0}]}',
        ),
        (
            CommandHandled(
                "a", "m1", Command((JointValue("Jaw", 1.0),)),
                CommandResult.refused(ErrorCode.ESTOPPED, "no"), 3.0, 4.0,
            ),
            "command",
            '{"t":3.0,"source":"m1","joints":[{"name":"Jaw","value":1.0}],"duration":null,'
            '"label":null,"accepted":false,"code":"ESTOPPED","message":"no","clamped":[]}',
        ),
        (
            TargetsSent("a", {"Rotation": 1.5, "Jaw": -20.0}, 5.0, 6.0),
            "targets",
            '{"t":5.0,"joints":{"Rotation":1.5,"Jaw":-20.0}}',
        ),
        (
            JointStatesReceived("a", "s1", {"Rotation": 1.5}, 7.0, 8.0),
            "joint_states",
            '{"t":7.0,"slave_id":"s1","joints":{"Rotation":1.5}}',
        ),
        (
            StateChanged("a", Mode.ESTOPPED, "m1", "button", "estop", 1.0, 2.0),
            "state",
            '{"t":1.0,"mode":"estopped","owner":"m1","estop_reason":"button","cause":"estop"}',
        ),
        (
            FaultReported("a", "s1", "OVERHEAT", "hot", Severity.CRITICAL, None, 9.0, 10.0),
            "fault",
            '{"t":9.0,"peer_id":"s1","code":"OVERHEAT","message":"hot","severity":"critical",'
            '"joint":null,"cleared":false}',
        ),
        (
            FaultReported("a", "s1", "OVERHEAT", "over", Severity.INFO, "Elbow", 9.5, 10.0, True),
            "fault",
            '{"t":9.5,"peer_id":"s1","code":"OVERHEAT","message":"over","severity":"info",'
            '"joint":"Elbow","cleared":true}',
        ),
        (
            PeerChanged("a", "slave", "s1", "mock-slave", "lost", "gone", 11.0, 12.0),
            "peer",
            '{"t":11.0,"role":"slave","peer_id":"s1","kind":"mock-slave","change":"lost",'
            '"reason":"gone","autonomous":false,"code":null}',
        ),
        (
            PeerChanged(
                "a", "master", "m2", "ros2", "refused", "held", 11.0, 12.0, code="MASTER_ACTIVE"
            ),
            "peer",
            '{"t":11.0,"role":"master","peer_id":"m2","kind":"ros2","change":"refused",'
            '"reason":"held","autonomous":false,"code":"MASTER_ACTIVE"}',
        ),
        (
            EpisodeChanged("a", "start", 3, "pick", 1.0, 13.0, 14.0),
            "episode",
            '{"t":13.0,"change":"start","index":3,"task":"pick","started":1.0}',
        ),
        (
            Audited("a", "alice", "POST /api/robots/{robot_id}/estop", "200", 15.0, 16.0),
            "audit",
            '{"t":15.0,"user":"alice","action":"POST /api/robots/{robot_id}/estop",'
            '"detail":"200"}',
        ),
        (
            PolicyInferred("a", "policy:act:0123456789ab", 12, 10, 8, 0.04, 0.03, None, 17.0, 18.0),
            "policy",
            '{"t":17.0,"policy":"policy:act:0123456789ab","timestep":12,"chunk_size":10,"kept":8,'
            '"latency":0.04,"inference":0.03,"frame_age":null}',
        ),
        (
            InterventionChanged("a", "started", "leader", "policy:act:0123456789ab", 19.0, 20.0),
            "intervention",
            '{"t":19.0,"change":"started","master":"leader","paused":"policy:act:0123456789ab"}',
        ),
        (
            MotionStopped(
                "a", "manual", "COLLISION", "Stopped on the way", ("gripper", "floor"),
                {"Pitch": 25.4}, {"Pitch": 30.0}, 21.0, 22.0,
            ),
            "stop",
            '{"t":21.0,"source":"manual","code":"COLLISION","message":"Stopped on the way",'
            '"blocked":["gripper","floor"],"joints":{"Pitch":25.4},"goals":{"Pitch":30.0}}',
        ),
    ]  # fmt: skip
    assert {kind for _, kind, _ in cases} == set(RECORD_TYPES)
    for event, kind, text in cases:
        found_kind, record = record_of(event)
        assert (found_kind, msgspec.json.encode(record).decode()) == (kind, text)
        # ... and it reads back as the type the reader and specs/schemas name.
        assert msgspec.json.decode(text, type=RECORD_TYPES[kind]) == record


class Calibrated(Observed, frozen=True, gc=False):
    """A joint's offset measured (an event for this test only)."""

    robot_id: str
    joint: str
    offset: float
    severity: Severity
    time: float
    wall_time: float
    note: str | None = None


def test_a_new_event_is_recorded_with_its_own_fields_and_nothing_else() -> None:
    record_type, make = derive_record(
        Recorded("calibration", Calibrated, "CalibrationRecord", "A joint's offset measured.")
    )
    event = Calibrated("arm", "Jaw", -1.5, Severity.WARNING, 7.25, 1.7e9)
    assert msgspec.json.encode(make(event)) == (
        b'{"t":7.25,"joint":"Jaw","offset":-1.5,"severity":"warning","note":null}'
    )
    schema = msgspec.json.schema(record_type)["$defs"]["CalibrationRecord"]
    assert schema["title"] == "CalibrationRecord"
    assert schema["description"] == "A joint's offset measured."
    assert schema["required"] == ["t", "joint", "offset", "severity"]
    assert schema["properties"]["severity"] == {"type": "string"}  # a plain string, not an enum
    assert schema["properties"]["note"]["default"] is None
    assert "robot_id" not in schema["properties"] and "wall_time" not in schema["properties"]
