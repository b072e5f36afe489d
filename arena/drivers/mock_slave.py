"""The mock slave: a simulated arm that follows its targets exactly, after configured delays.

With `simulate_errors` on it drops some updates and reports faults of every severity, drawn
from a seeded random generator so that a test sees the same faults every run.
"""

from __future__ import annotations

import random
from dataclasses import dataclass

import trio

from arena.protocol.errors import ErrorCode, Severity
from arena.robot.events import SlaveNotice
from arena.robot.links import SlaveLink


@dataclass(frozen=True, slots=True)
class MockSlaveConfig:
    """Delays in milliseconds, as the seed's `mock-slave` config gives them."""

    simulate_latency: float = 0.0  # one-way network delay before a target arrives
    response_delay: float = 0.0  # execution time before the new state is reported
    simulate_errors: bool = False
    error_rate: float = 0.1  # chance per update of an injected fault (when errors are on)
    seed: int = 0


class MockSlave:
    """A simulated arm: real value = target value, `latency + response_delay` later."""

    kind = "mock-slave"
    measures = False  # a twin: where it is, it was told to be

    def __init__(self, config: MockSlaveConfig | None = None) -> None:
        self.config = config or MockSlaveConfig()
        self.positions: dict[str, float] = {}
        self.received = 0
        self.dropped_updates = 0
        self.injected_faults: list[Severity] = []
        self.notices: list[SlaveNotice] = []
        #: True while `run` runs (a robot going away ends it: at its shutdown notice, or
        #: cancelled wherever it is).
        self.running = False

    async def run(self, link: SlaveLink) -> None:
        """Follow targets until detached."""
        rng = random.Random(self.config.seed)
        delay = (self.config.simulate_latency + self.config.response_delay) / 1000.0
        self.running = True
        try:
            await self._follow(link, rng, delay)
        finally:
            self.running = False

    async def _follow(self, link: SlaveLink, rng: random.Random, delay: float) -> None:
        # A simulated arm starts at rest in its neutral pose, and says so.
        self.positions = dict.fromkeys(link.robot.model.joint_names, 0.0)
        await link.report_joint_states(self.positions)
        async for message in link.messages():
            if isinstance(message, SlaveNotice):
                self.notices.append(message)
                continue
            self.received += 1
            if delay:
                await trio.sleep(delay)
            self.positions.update(message.joints)
            if self.config.simulate_errors and rng.random() < self.config.error_rate:
                await self._inject_fault(link, rng)
                continue
            await link.report_joint_states(self.positions)

    async def _inject_fault(self, link: SlaveLink, rng: random.Random) -> None:
        choice = rng.randrange(len(Severity) + 1)
        if choice == len(Severity):
            self.dropped_updates += 1  # the update is lost on the way
            return
        severity = list(Severity)[choice]
        self.injected_faults.append(severity)
        joint = rng.choice(sorted(self.positions)) if self.positions else None
        await link.report_fault(
            ErrorCode.SIMULATED_FAULT, f"injected {severity} fault", severity, joint
        )
