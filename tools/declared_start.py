"""How long a lab server takes from process start to every declared arm held.

    python tools/declared_start.py [--runs 3] [--camera]

Two arms on simulated Feetech buses (in this process, shared with the server's as
`arena sim-bus` shares them), declared in a configuration file; `arena serve --config` started
in a process of its own, which is killed once both arms are held: every servo's torque on, as
the buses see it. Prints each run's time to held and to listening (specs/declared-setup.md).
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from arena.feetech import registers as reg
from arena.feetech.sim import SimBus
from arena.servo.sim_pty import PtySimBus

ROOT = Path(__file__).resolve().parent.parent
ARM = """
[[robots]]
id = "{name}"

[[robots.slaves]]
type = "usb-slave"
port = "{port}"
"""
CAMERA = '\n[[robots.cameras]]\nname = "top"\nsource = "test-pattern"\n'


def held(sim: PtySimBus) -> bool:
    """Every servo of the bus has its torque on."""
    with sim.paused() as bus:
        return all(servo.peek(reg.TORQUE_ENABLE) for servo in bus.servos.values())


def run_once(config: Path, sims: list[PtySimBus], folder: Path) -> tuple[float, float]:
    """(seconds to every arm held, seconds to listening) of one start."""
    for sim in sims:  # as after a power cut: limp
        with sim.paused() as bus:
            for servo in bus.servos.values():
                servo.poke(reg.TORQUE_ENABLE, 0)
    env = {**os.environ, "PYTHONPATH": str(ROOT), "LOG_LEVEL": "INFO"}
    command = [sys.executable, "-m", "arena", "serve", "--config", str(config), "--no-record"]
    started = time.monotonic()
    server = subprocess.Popen(command, env=env, cwd=folder, stderr=subprocess.PIPE, text=True)
    try:
        waiting = set(range(len(sims)))
        while waiting:
            waiting = {i for i in waiting if not held(sims[i])}
            if server.poll() is not None:
                raise SystemExit(f"arena serve ended ({server.returncode})")
            time.sleep(0.005)
        all_held = time.monotonic() - started
        assert server.stderr is not None
        for line in server.stderr:
            if "listening on" in line:
                break
        return all_held, time.monotonic() - started
    finally:
        server.send_signal(signal.SIGKILL)
        server.wait()


def main() -> None:
    """Measure and print."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--camera", action="store_true", help="declare a test-pattern camera too")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as temporary:
        folder = Path(temporary)
        sims = [
            PtySimBus(folder / f"tty-{name}", SimBus(), share=True).start()
            for name in ("left", "right")
        ]
        try:
            text = "port = 0\n" + "".join(
                ARM.format(name=name, port=sim.link)
                for name, sim in zip(("left", "right"), sims, strict=True)
            )
            config = folder / "lab.toml"
            config.write_text(text + (CAMERA if args.camera else ""), encoding="utf-8")
            for number in range(args.runs):
                all_held, listening = run_once(config, sims, folder)
                print(
                    f"run {number + 1}: both arms held {all_held:.2f} s after the process "
                    f"started, listening at {listening:.2f} s (load {os.getloadavg()[0]:.1f})"
                )
        finally:
            for sim in sims:
                sim.close()


if __name__ == "__main__":
    main()
