"""The curated sample recordings in recordings/golden: how they are made.

Regenerate with `python -m tests.golden` (only when behaviour is meant to change; the golden
test then shows the difference first).
"""

from __future__ import annotations

from pathlib import Path

import trio
from trio.testing import MockClock

from arena.drivers.sequence_master import SequenceMaster
from arena.drivers.sequences import get_sequence
from arena.robot.motion import Command
from tests.scenarios import record_scenario

GOLDEN = Path(__file__).resolve().parent.parent / "recordings" / "golden"


async def manual_estop_reset(robot: object) -> None:
    """Manual moves, a smooth move, an e-stop in the middle of a move, a reset, a clamp."""
    await robot.command(Command.of({"Rotation": 45.0, "Pitch": -30.0}))  # type: ignore[attr-defined]
    await trio.sleep(0.6)
    await robot.command(Command.of({"Elbow": -40.0}, duration=1.0))  # type: ignore[attr-defined]
    await trio.sleep(0.4)
    await robot.estop("golden e-stop")  # type: ignore[attr-defined]
    await trio.sleep(0.3)
    await robot.reset()  # type: ignore[attr-defined]
    await robot.command(Command.of({"Jaw": 500.0}))  # type: ignore[attr-defined]
    await trio.sleep(0.6)


async def gentle_wave(robot: object) -> None:
    """The gentle-wave demo from start to end."""
    await robot.attach_master(SequenceMaster([get_sequence("gentle-wave")]))  # type: ignore[attr-defined]
    await trio.sleep(6.5)


SCENARIOS = {"manual-estop-reset": manual_estop_reset, "gentle-wave": gentle_wave}


async def make(name: str, folder: Path) -> Path:
    """Record one scenario into `folder/NAME.mcap` (virtual time)."""
    (made,) = await record_scenario(folder, SCENARIOS[name])
    target = folder / f"{name}.mcap"
    made.replace(target)
    return target


if __name__ == "__main__":
    GOLDEN.mkdir(parents=True, exist_ok=True)
    for scenario in SCENARIOS:
        print(trio.run(make, scenario, GOLDEN, clock=MockClock(autojump_threshold=0)))
