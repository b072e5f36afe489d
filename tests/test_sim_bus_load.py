"""`arena sim-bus` as users run it, a process of its own, answers a server's arm within its
timeouts however loaded the machine: no SERVO_TIMEOUT, no lost bus, no e-stop, with busy
processes on every core (specs/servo-bus.md, "The simulated buses")."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from arena.drivers.usb_slave import UsbSlave
from arena.protocol.errors import ErrorCode
from arena.protocol.rest import UsbSlaveBody
from arena.robot.events import FaultReported, PeerChanged
from arena.robot.manager import RobotManager
from arena.robot.model import load_robot_model
from arena.robot.safety import Mode
from arena.server.drivers import usb_slave_config
from arena.servo import sim_pace
from tests.conftest import eventually

MODEL = load_robot_model("so-arm100")
#: Control cycles watched under load (at 250 Hz: 3 s on an idle machine).
CYCLES = 750
#: Busy processes per core: a load of 3 a core and more (the report: load 7 on 2 cores).
BUSY_PER_CORE = 3


@contextlib.contextmanager
def busy_processes(count: int) -> Iterator[None]:
    """`count` processes that spin on the CPU until the block ends."""
    spinning = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(count)]
    try:
        yield
    finally:
        for process in spinning:
            process.kill()
        for process in spinning:
            process.wait()


@contextlib.contextmanager
def sim_bus_process(link: Path) -> Iterator[subprocess.Popen[str]]:
    """`arena sim-bus --link LINK` in a process of its own, as a user starts it."""
    code = "import sys; from arena.cli import main; sys.exit(main())"
    process = subprocess.Popen(
        [sys.executable, "-c", code, "sim-bus", "--link", str(link)],
        stdout=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parent.parent)},
    )
    try:
        assert process.stdout is not None
        assert "simulated feetech bus" in process.stdout.readline()  # the link is there
        yield process
    finally:
        process.terminate()
        process.wait(timeout=30)


@pytest.mark.real_io
async def test_the_simulated_bus_in_its_own_process_answers_under_cpu_load(
    manager: RobotManager, tmp_path: Path
) -> None:
    link = tmp_path / "arm"
    with sim_bus_process(link):
        robot = await manager.create_robot("so-arm100", robot_id="arm")
        # The production driver, bus and timeouts: nothing here knows it is a simulator.
        slave = UsbSlave(usb_slave_config(UsbSlaveBody(port=str(link))), MODEL)
        with robot.subscribe(kinds=[FaultReported, PeerChanged]) as events:
            await robot.attach_slave(slave, slave_id="arm-1")
            await eventually(lambda: slave.running, what="the bus open")
            worker = slave.worker
            assert worker is not None
            with busy_processes(BUSY_PER_CORE * (os.cpu_count() or 2)):
                start = worker.stats.cycles
                await eventually(
                    lambda: worker.stats.cycles >= start + CYCLES,
                    timeout=600,
                    what=f"{CYCLES} control cycles under load",
                )
            seen = events.drain()
    timeouts = [e for e in seen if isinstance(e, FaultReported) and not e.cleared]
    timeouts = [e for e in timeouts if e.code == ErrorCode.SERVO_TIMEOUT]
    lost = [e for e in seen if isinstance(e, PeerChanged) and e.change == "disconnected"]
    assert (len(timeouts), lost) == (0, []), timeouts[:3]
    assert robot.snapshot().mode is not Mode.ESTOPPED


def test_only_a_running_simulator_is_found_by_its_port(tmp_path: Path) -> None:
    # A real adapter is never a pty: its bus keeps its own timeouts.
    assert sim_pace.find("/dev/null") is None
    assert sim_pace.find(str(tmp_path / "nothing")) is None
    link = tmp_path / "arm"
    with sim_bus_process(link) as process:
        found = sim_pace.find(str(link))
        assert found is not None and found.pid == process.pid
        tty = os.path.realpath(link)
    assert not sim_pace.pace_path(tty).exists()  # the simulator took its counters away
    # A file left by a simulator that was killed is no simulator (the pid has exited).
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    stale = sim_pace.pace_path("/dev/pts/999999")
    stale.parent.mkdir(parents=True, exist_ok=True)
    stale.write_bytes(gone.pid.to_bytes(8, "little") + bytes(24))
    try:
        assert sim_pace.find("/dev/pts/999999") is None
    finally:
        stale.unlink()
