"""Against LeRobot 0.6 itself (`make compat`, which builds its Python with tools/compat.sh and
runs these; `make test` leaves them out: marker `compat`).

Policies saved by LeRobot 0.6 and by Arena's own 0.4.4 are run by a real server whose worker is
either, and the two workers answer one observation with the same actions.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import pytest
import trio

from arena.policy.process import PolicyProcess, worker_command
from arena.policy.wire import Observe
from arena.robot.events import CommandHandled
from arena.sensors.sources import JpegEncoder, pattern_image
from tests.conftest import REPOSITORY, missing, need
from tests.test_policy_server import Start, attach, make_policy, next_event, ready

pytestmark = pytest.mark.compat

#: The LeRobot 0.6 Python tools/compat.sh makes (or another, named by ARENA_COMPAT_PYTHON).
COMPAT_PYTHON = Path(os.environ.get("ARENA_COMPAT_PYTHON", REPOSITORY / ".compat" / "python"))


@pytest.fixture(scope="module")
def newer() -> str:
    """The LeRobot 0.6 Python."""
    need("lerobot", "lerobot")
    if not COMPAT_PYTHON.exists():
        missing(f"no {COMPAT_PYTHON}: `make compat` builds it")
    return str(COMPAT_PYTHON)


@pytest.fixture(scope="module")
def saved(newer: str, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The same tiny ACT saved by Arena's LeRobot (0.4.4) and by LeRobot 0.6."""
    folder = tmp_path_factory.mktemp("saved")
    return {
        "0.4": make_policy(folder / "act04"),
        "0.6": make_policy(folder / "act06", python=newer),
    }


@pytest.mark.parametrize("by", ["0.4", "0.6"])
@pytest.mark.parametrize("worker", ["0.4", "0.6"])
async def test_a_policy_either_lerobot_saved_runs_in_a_worker_of_either(
    start_server: Start, saved: dict[str, Path], newer: str, by: str, worker: str
) -> None:
    server = await start_server(demo=True, policy_python=newer if worker == "0.6" else None)
    robot = await ready(server)
    with robot.subscribe(kinds=[CommandHandled]) as events:
        answer = await attach(server, saved[by])
        assert answer.status_code == 201, answer.text
        handled = await next_event(events, lambda e: isinstance(e, CommandHandled))
    assert handled.result.accepted


async def test_both_workers_answer_an_observation_with_the_same_actions(
    saved: dict[str, Path], newer: str
) -> None:
    jpeg = JpegEncoder(32, 32, 30).encode_rgb(pattern_image(7, 32, 32))  # the policy's size
    observation = Observe(0, (10.0, -20.0, 30.0, 5.0, -5.0, 40.0), {"front": jpeg}, "")
    chunks = []
    for python in (None, newer):
        worker = await PolicyProcess.start(worker_command(python))
        try:
            with trio.fail_after(120):
                loaded = await worker.load(saved["0.6"])
                chunks.append((loaded.lerobot, (await worker.act(observation)).actions))
        finally:
            await worker.close()
    (old, ours), (new, theirs) = chunks
    assert old.startswith("0.4") and new.startswith("0.6")
    assert len(ours) == len(theirs) == loaded.chunk_size
    # JPEG decoded by FFmpeg (0.4.4's worker has PyAV) and by Pillow (0.6's): a pixel's worth
    # of difference at most, far below an action's scale (about 30 degrees a unit here)
    for a, b in zip(ours, theirs, strict=True):
        for x, y in zip(a, b, strict=True):
            assert math.isclose(x, y, abs_tol=0.5), (ours, theirs)
