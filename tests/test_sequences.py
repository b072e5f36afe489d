"""Sequences as data: the three demos, parsing of the wire format, auto start and loop mode."""

from __future__ import annotations

from typing import Any

import pytest
import trio
from trio.testing import MockClock

from arena.drivers.refusals import KEPT, Refusals
from arena.drivers.sequence_master import MIN_LOOP_PERIOD, SequenceMaster
from arena.drivers.sequences import demo_sequences, get_sequence, parse_sequence
from arena.protocol.errors import ArenaError, ErrorCode
from arena.robot.manager import RobotManager
from arena.robot.model import load_robot_model
from tests.conftest import RecordingSlave

MODEL = load_robot_model("so-arm100")


def test_the_three_demo_sequences() -> None:
    summaries = {s.id: s.summary() for s in demo_sequences().values()}
    assert {k: (v["name"], v["duration"]) for k, v in summaries.items()} == {
        "gentle-wave": ("Gentle Wave Pattern", 6000),
        "small-scan": ("Small Scanning Pattern", 8000),
        "tiny-flex": ("Tiny Flex Pattern", 8000),
    }


@pytest.mark.parametrize("sequence_id", ["gentle-wave", "small-scan", "tiny-flex"])
def test_demo_sequences_are_safe_by_construction(sequence_id: str) -> None:
    sequence = get_sequence(sequence_id)
    sequence.check_against(MODEL)
    for keyframe in sequence.keyframes:
        assert keyframe.command.duration
        for goal in keyframe.command.joints:
            assert abs(goal.value) <= 25.0
    # Peak speed of a minimum-jerk move is 1.875 * distance / duration: stay under the limit.
    positions = dict.fromkeys(MODEL.joint_names, 0.0)
    for keyframe in sequence.keyframes:
        duration = keyframe.command.duration or 0.0
        for goal in keyframe.command.joints:
            peak = 1.875 * abs(goal.value - positions[goal.name]) / duration
            assert peak < MODEL.joints[0].max_velocity
            positions[goal.name] = goal.value
    assert sequence.keyframes[-1].at + (sequence.keyframes[-1].command.duration or 0) <= (
        sequence.total_duration
    )


def test_unknown_sequence() -> None:
    with pytest.raises(ArenaError) as info:
        get_sequence("moonwalk")
    assert info.value.code is ErrorCode.UNKNOWN_SEQUENCE
    assert "gentle-wave" in info.value.message


GOOD = {"id": "x", "commands": [{"timestamp": 0, "joints": [{"name": "Rotation", "value": 1}]}]}


@pytest.mark.parametrize(
    "data",
    [
        [],
        {"id": "x"},
        {"commands": []},
        {"commands": ["nope"]},
        {"commands": [{"timestamp": -1, "joints": [{"name": "Rotation", "value": 1}]}]},
        {"commands": [{"timestamp": 0, "joints": []}]},
        {"commands": [{"timestamp": 0, "joints": [{"value": 1}]}]},
        {"commands": [{"timestamp": 0, "joints": [{"name": "Rotation", "value": "1"}]}]},
        {"commands": [{"timestamp": 0, "joints": [{"name": "Rotation", "value": 1e400}]}]},
        {
            "commands": [
                {"timestamp": 0, "duration": "long", "joints": [{"name": "Rotation", "value": 1}]}
            ]
        },
        {
            "commands": [
                {"timestamp": 500, "joints": [{"name": "Rotation", "value": 1}]},
                {"timestamp": 100, "joints": [{"name": "Rotation", "value": 1}]},
            ]
        },
        {**GOOD, "total_duration": -5},
        {
            "commands": [{"timestamp": 900, "joints": [{"name": "Rotation", "value": 1}]}],
            "total_duration": 100,
        },
    ],
)
def test_malformed_sequences_are_refused(data: Any) -> None:
    with pytest.raises(ArenaError) as info:
        parse_sequence(data)
    assert info.value.code is ErrorCode.INVALID_VALUE
    assert info.value.message.startswith("Invalid sequence")


def test_the_wire_example_parses() -> None:
    sequence = parse_sequence(
        {
            "id": "custom-dance",
            "name": "Custom Dance Sequence",
            "commands": [
                {"timestamp": 0, "joints": [{"name": "Rotation", "value": -30}], "duration": 1000},
                {
                    "timestamp": 1000,
                    "joints": [{"name": "Rotation", "value": 30}],
                    "duration": 1000,
                },
            ],
            "total_duration": 2000,
            "loop": False,
        }
    )
    assert [k.at for k in sequence.keyframes] == [0.0, 1.0]
    assert sequence.total_duration == 2.0 and not sequence.loop


async def test_auto_start_off_waits_for_start(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot = await manager.create_robot("so-arm100", robot_id="arm")
    recorder = RecordingSlave()
    await robot.attach_slave(recorder)
    master = SequenceMaster([get_sequence("gentle-wave")], auto_start=False)
    await robot.attach_master(master)
    await trio.sleep(10)
    assert robot.snapshot().owner is not None and not recorder.targets
    master.start()
    await trio.sleep(7)
    assert recorder.targets and robot.snapshot().owner is None


async def test_loop_mode_repeats_until_detached(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot = await manager.create_robot("so-arm100", robot_id="arm")
    recorder = RecordingSlave()
    await robot.attach_slave(recorder)
    sequence = get_sequence("small-scan")
    start = trio.current_time()
    master_id = await robot.attach_master(SequenceMaster([sequence], loop=True))
    await trio.sleep(3 * sequence.total_duration + 2.0)
    assert robot.snapshot().owner == master_id
    at_left_end = [t - start for t, targets in recorder.targets if targets["Rotation"] == -25.0]
    # The sweep reaches its left end once per pass: three passes, and a fourth has begun.
    passes = {int(t // sequence.total_duration) for t in at_left_end}
    assert passes == {0, 1, 2, 3}
    await robot.detach_master(master_id)
    count = len(recorder.targets)
    await trio.sleep(10)
    assert len(recorder.targets) == count and robot.snapshot().owner is None


def test_a_looping_sequence_of_no_duration_is_refused() -> None:
    at_zero = {
        "id": "spin",
        "commands": [{"timestamp": 0, "joints": [{"name": "Jaw", "value": 1}]}],
    }
    parse_sequence(at_zero)  # once: fine
    with pytest.raises(ArenaError) as refused:
        parse_sequence({**at_zero, "loop": True})
    assert refused.value.code is ErrorCode.INVALID_VALUE
    assert "duration above zero" in refused.value.message
    looping = parse_sequence({**at_zero, "loop": True, "total_duration": 500})
    assert looping.loop and looping.total_duration == 0.5


async def test_a_loop_that_takes_no_time_is_paced(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    # Built directly from a sequence of no duration (parsing refuses it looping). Unpaced,
    # it would never let virtual time move on (and take a core in real time).
    robot = await manager.create_robot("so-arm100", robot_id="arm")
    spin = parse_sequence(
        {"id": "spin", "commands": [{"timestamp": 0, "joints": [{"name": "Jaw", "value": 1}]}]}
    )
    await robot.attach_master(SequenceMaster([spin], loop=True))
    await trio.sleep(60.0)
    sent = sum(robot.command_counts.values())
    assert 60.0 / MIN_LOOP_PERIOD * 0.9 <= sent <= 60.0 / MIN_LOOP_PERIOD + 1


def test_a_masters_refusals_are_counted_and_only_the_newest_kept() -> None:
    refusals = Refusals()
    for n in range(10_000):
        refusals.append((ErrorCode.RATE_LIMITED, f"refusal {n}"))
    assert refusals.total == 10_000 and len(refusals) == KEPT
    assert refusals[-1] == (ErrorCode.RATE_LIMITED, "refusal 9999")
    assert next(iter(refusals))[1] == f"refusal {10_000 - KEPT}"
