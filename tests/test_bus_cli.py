"""`arena calibrate` and `arena sim-bus`: the terminal workflow, in process and as commands."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from arena.feetech import registers as reg
from arena.protocol.errors import ArenaError, ErrorCode
from arena.servo import terminal
from arena.servo.calibration import Calibration
from arena.servo.sim_pty import PtySimBus
from arena.servo.terminal import calibrate_interactively, read_positions
from tests.hardware import TEST_TIMEOUT_MARGIN, open_test_bus, running_sim

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
    # Only the elbow was swept: the others are named as not moved.
    warning = next(line for line in said if line.startswith("Warning"))
    assert "Rotation, Pitch, Wrist_Pitch, Wrist_Roll, Jaw." in warning


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


def test_sim_bus_simulates_the_servos_of_a_robot_type(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`--robot-type` takes the type's servo ids (here a type of servos 11-16, added from
    files); an unknown type is refused before any pty is made."""
    from arena import cli
    from arena.robot.model import BUILTIN_TYPES_DIR

    types = tmp_path / "types"
    shutil.copytree(BUILTIN_TYPES_DIR / "so-arm100", types / "far-arm")
    toml = types / "far-arm" / "robot.toml"
    toml.write_text(
        "".join(
            f"servo_id = {int(line.split('=')[1]) + 10}\n" if line.startswith("servo_id") else line
            for line in toml.read_text().splitlines(keepends=True)
        )
    )
    link = tmp_path / "ttySIM"
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "ARENA_ROBOT_TYPES": str(types)}
    command = [sys.executable, "-m", "arena.cli", "sim-bus", "--link", str(link)]
    server = subprocess.Popen(
        [*command, "--robot-type", "far-arm"], stdout=subprocess.PIPE, text=True, env=env
    )
    try:
        assert server.stdout is not None
        assert "servos 11,12,13,14,15,16" in server.stdout.readline()
    finally:
        server.terminate()
        server.wait(timeout=10)
    assert cli.main(["sim-bus", "--link", str(link), "--robot-type", "nosuch"]) == 2
    assert "nosuch" in capsys.readouterr().err
    assert not link.exists()


def test_sim_bus_leaves_a_link_in_use_alone(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A second bus on a live link is refused (as a command: exit 2 and why) and the first
    keeps its link; a bus removes the link at exit only while it still points to its own pty;
    a stale link (its pty gone) is taken over."""
    from arena import cli
    from arena.feetech.sim import SimBus

    link = tmp_path / "x" / "koch"
    with PtySimBus(link, SimBus((1,))) as first:
        ours = os.readlink(link)
        with pytest.raises(ArenaError) as taken:
            PtySimBus(link, SimBus((1,))).start()
        assert taken.value.code is ErrorCode.PORT_BUSY
        assert str(link) in taken.value.message and "another simulated bus" in taken.value.message
        assert cli.main(["sim-bus", "--link", str(link)]) == 2
        assert "another simulated bus" in capsys.readouterr().err
        assert os.readlink(link) == ours
        bus = first.servo_bus(TEST_TIMEOUT_MARGIN)  # the first bus still answers on it
        bus.open()
        try:
            assert bus.ping(1)
        finally:
            bus.close()
    assert not os.path.lexists(link)
    link.symlink_to(tmp_path / "gone")  # stale: a bus killed without cleaning up
    with PtySimBus(link, SimBus((1,))) as second:
        assert link.resolve() != tmp_path / "gone"
        other = tmp_path / "other"
        other.write_text("")
        link.unlink()
        link.symlink_to(other)  # someone else's now
    assert os.readlink(link) == str(other)
    assert second.link == link


class LateBus:
    """A bus whose servos miss the first `late` position reads (a busy computer)."""

    def __init__(self, late: int) -> None:
        self.late = late
        self.reads = 0

    def read_positions(self, ids: Any) -> tuple[dict[int, int], Any]:
        from arena.servo.interface import SyncReadResult

        self.reads += 1
        if self.reads <= self.late:
            return {}, SyncReadResult(missing=list(ids))
        return dict.fromkeys(ids, 2048), SyncReadResult()


def test_calibration_reads_again_while_servos_are_late_then_says_which() -> None:
    ids = (1, 2, 3)
    late = LateBus(terminal.READ_ATTEMPTS - 1)
    assert terminal.read_patiently(late, ids) == dict.fromkeys(ids, 2048)  # type: ignore[arg-type]
    assert late.reads == terminal.READ_ATTEMPTS
    silent = LateBus(terminal.READ_ATTEMPTS)
    with pytest.raises(ArenaError) as error:
        terminal.read_patiently(silent, ids)  # type: ignore[arg-type]
    assert error.value.code is ErrorCode.SERVO_TIMEOUT and "[1, 2, 3]" in error.value.message
    assert silent.reads == terminal.READ_ATTEMPTS


def test_the_bus_commands_help_names_the_robot_types(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    # A type added from files alone is offered too.
    own = tmp_path / "my-arm"
    own.mkdir()
    (own / "robot.toml").write_text("")
    monkeypatch.setenv("ARENA_ROBOT_TYPES", str(tmp_path))
    monkeypatch.setenv("COLUMNS", "300")  # no line breaks inside a name
    from arena.cli import main

    for command in ("sim-bus", "calibrate"):
        with pytest.raises(SystemExit):
            main([command, "--help"])
        shown = " ".join(capsys.readouterr().out.split())
        assert "koch, my-arm, so-101, so-arm100 (default so-arm100" in shown, command
