"""Shared fixtures: a robot manager on trio's MockClock, and a slave that records its targets."""

from __future__ import annotations

from collections.abc import AsyncIterator
from dataclasses import dataclass, field

import pytest
import trio

from arena.robot.actor import SlaveLink
from arena.robot.events import SlaveNotice, SlaveTarget
from arena.robot.manager import RobotManager, open_manager


@pytest.fixture
async def manager() -> AsyncIterator[RobotManager]:
    """A robot manager. Tests take `autojump_clock` too, so that its time is virtual."""
    async with open_manager() as opened:
        yield opened


@dataclass
class RecordingSlave:
    """A slave driver that keeps every target and notice it takes, with trio times."""

    kind: str = "recording-slave"
    targets: list[tuple[float, dict[str, float]]] = field(default_factory=list)
    notices: list[tuple[float, SlaveNotice]] = field(default_factory=list)
    fail_after: int | None = None  # raise after this many targets (a crashing driver)

    async def run(self, link: SlaveLink) -> None:
        while True:
            try:
                message = await link.receive()
            except trio.EndOfChannel:
                return
            if isinstance(message, SlaveTarget):
                self.targets.append((trio.current_time(), dict(message.joints)))
                if self.fail_after is not None and len(self.targets) >= self.fail_after:
                    raise RuntimeError("simulated driver crash")
                await link.report_joint_states(message.joints)
            else:
                self.notices.append((trio.current_time(), message))
