"""`arena calibrate` and `arena sim-bus`: the terminal workflow, in process and as commands."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from arena.feetech import registers as reg
from arena.feetech import terminal
from arena.feetech.calibration import Calibration
from arena.feetech.sim_pty import PtySimBus
from arena.feetech.terminal import calibrate_interactively, read_positions
from tests.hardware import open_test_bus, running_sim

JOINTS = {"Rotation": 1, "Pitch": 2, "Elbow": 3, "Wrist_Pitch": 4, "Wrist_Roll": 5, "Jaw": 6}


@pytest.fixture
def sim(tmp_path: Path) -> Iterator[PtySimBus]:
    yield from running_sim(tmp_path)


def test_calibrate_interactively(
    sim: PtySimBus, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    with sim.paused() as bus:
        bus.servo(1).poke(reg.TORQUE_ENABLE, 1)
    prompts: list[str] = []
    said: list[str] = []
    # The range watcher's reads, counted: each pose of the sweep is held until the watcher
    # has read the bus twice since (however slow the machine), never for a fixed time.
    reads = threading.Condition()
    count = [0]

    def counted_read(*args: Any) -> Any:
        positions = read_positions(*args)
        with reads:
            count[0] += 1
            reads.notify_all()
        return positions

    monkeypatch.setattr(terminal, "read_positions", counted_read)

    def ask(prompt: str) -> str:
        prompts.append(prompt)
        if len(prompts) == 1:  # pose the arm at rest
            with sim.paused() as bus:
                for sid in JOINTS.values():
                    bus.servo(sid).move_by_hand(1000 + 200 * sid)
        else:  # sweep the elbow through its range
            for delta in (-500, 0, 700, 0):
                with sim.paused() as bus:
                    bus.servo(3).move_by_hand(1600 + delta)
                with reads:
                    seen = count[0]
                    assert reads.wait_for(lambda seen=seen: count[0] >= seen + 2, timeout=30)
        return ""

    bus = open_test_bus(str(sim.link))
    bus.open()
    try:
        out = tmp_path / "cal" / "arm.json"
        result = calibrate_interactively(bus, JOINTS, out, ask=ask, say=said.append)
    finally:
        bus.close()
    assert len(prompts) == 2
    with sim.paused() as simulated:
        assert all(s.peek(reg.TORQUE_ENABLE) == 0 for s in simulated.servos.values())
    assert Calibration.load(out) == result
    assert result.to_degrees({1: 1200, 3: 1600}) == pytest.approx(
        {"Rotation": 0.0, "Elbow": 0.0}, abs=0.05
    )
    elbow = result.joints["Elbow"]
    assert elbow.min_degrees == pytest.approx(-500 * 360 / 4096, abs=0.01)
    assert elbow.max_degrees == pytest.approx(700 * 360 / 4096, abs=0.01)
    assert result.joints["Jaw"].min_degrees is None
    assert any("Saved" in line for line in said)


def test_sim_bus_and_calibrate_commands(tmp_path: Path) -> None:
    link = tmp_path / "ttySIM"
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    server = subprocess.Popen(
        [sys.executable, "-m", "arena.cli", "sim-bus", "--link", str(link), "--wire-time"],
        stdout=subprocess.PIPE,
        text=True,
        env=env,
    )
    try:
        assert server.stdout is not None
        banner = server.stdout.readline()
        assert str(link) in banner and "wire time" in banner
        out = tmp_path / "arm.json"
        done = subprocess.run(
            [
                sys.executable,
                "-m",
                "arena.cli",
                "calibrate",
                "--port",
                str(link),
                "--out",
                str(out),
            ],
            input="\n\n",
            capture_output=True,
            text=True,
            timeout=60,
            env=env,
        )
        assert done.returncode == 0, done.stderr
        assert "Saved" in done.stdout
        assert set(Calibration.load(out).joints) == set(JOINTS)
        missing = subprocess.run(
            [sys.executable, "-m", "arena.cli", "calibrate", "--port", str(tmp_path / "nope")],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert missing.returncode == 2
        assert "does not exist" in missing.stderr
    finally:
        server.terminate()
        server.wait(timeout=10)
    assert server.returncode == 0
    assert not link.exists()
