"""Drivers from their wire configs: `{"type": "mock-slave", ...}` -> a driver object."""

from __future__ import annotations

from arena.drivers.mock_slave import MockSlave, MockSlaveConfig
from arena.drivers.sequence_master import SequenceMaster
from arena.drivers.sequences import demo_sequences, get_sequence
from arena.protocol.errors import ArenaError, ErrorCode
from arena.protocol.rest import MasterBody, MockSlaveBody, SequenceMasterBody, SlaveBody
from arena.robot.actor import MasterDriver, SlaveDriver


def make_slave(body: SlaveBody) -> SlaveDriver:
    """Build a slave driver from its config."""
    if isinstance(body, MockSlaveBody):
        return MockSlave(
            MockSlaveConfig.from_wire(
                {
                    "simulateLatency": body.simulateLatency,
                    "responseDelay": body.responseDelay,
                    "simulateErrors": body.simulateErrors,
                    "errorRate": body.errorRate,
                    "seed": body.seed,
                }
            )
        )
    raise ArenaError(ErrorCode.INVALID_CONFIG, f"Unsupported slave type {body!r}.")


def make_master(body: MasterBody) -> MasterDriver:
    """Build a master driver from its config."""
    if isinstance(body, SequenceMasterBody):
        ids = body.sequences if body.sequences else list(demo_sequences())
        master = SequenceMaster(
            [get_sequence(i) for i in ids], loop=body.loop, auto_start=body.autoStart
        )
        master.takes_over = body.takeover
        return master
    raise ArenaError(ErrorCode.INVALID_CONFIG, f"Unsupported master type {body!r}.")
