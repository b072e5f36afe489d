"""The curated recordings in recordings/golden: replayed now, they must behave as recorded."""

from __future__ import annotations

from pathlib import Path

import pytest
from trio.testing import MockClock

from arena.recording.mcap_file import read_recording
from tests.golden import GOLDEN, SCENARIOS
from tests.scenarios import behaviour, replay_session


@pytest.mark.parametrize("name", sorted(SCENARIOS))
async def test_golden_recording_replays_identically(autojump_clock: MockClock, name: str) -> None:
    path: Path = GOLDEN / f"{name}.mcap"
    golden = read_recording(path)
    assert not golden.truncated and golden.messages
    replayed = await replay_session(golden, "arm")
    expected, actual = behaviour(golden, "arm"), behaviour(replayed, "arm")
    assert expected, "the golden file holds no behaviour"
    # A difference here means the robot now decides differently than when the file was made.
    assert actual == expected
