"""The servo bus: the USB slave's control loop and a leader arm driving a follower."""

from __future__ import annotations

import subprocess
import sys
import tempfile
import time
from pathlib import Path

from arena.bench.common import (
    percentile,
)


def usb_control_rate(
    seconds: float = 3.0, rate: float = 500.0, min_cycles: int = 0
) -> dict[str, float]:
    """The bus worker (sync write goals + sync read positions of 6 servos per cycle) against a
    simulated bus with wire-time emulation in another process: cycles/s flat out, and the
    worker thread's CPU share when paced at `rate`. Each run lasts `seconds`, and longer until
    the worker has made `min_cycles` cycles (a loaded machine may make none in a short run)."""
    from arena.feetech.bus import FeetechBus
    from arena.servo.health import ServoFault
    from arena.servo.worker import BusWorker, Reading, WorkerEvent, WorkerSettings

    class Count:
        def __init__(self) -> None:
            self.readings = 0
            self.faults = 0

        def reading(self, reading: Reading) -> None:
            self.readings += 1

        def event(self, event: WorkerEvent) -> None:
            self.faults += isinstance(event, ServoFault)

    def run(worker_rate: float, link: Path) -> tuple[float, float, int]:
        listener = Count()
        ids = (1, 2, 3, 4, 5, 6)
        worker = BusWorker(
            lambda: FeetechBus(str(link)), ids, listener, WorkerSettings(rate=worker_rate)
        )
        worker.start()
        worker.first_connect.result(timeout=10)
        goal = 0
        start = time.perf_counter()
        cycles0, cpu0 = worker.stats.cycles, worker.stats.thread_cpu
        while (elapsed := time.perf_counter() - start) < seconds or (
            worker.stats.cycles - cycles0 < min_cycles and elapsed < 60.0
        ):
            goal = (goal + 7) % 400
            worker.set_goals(dict.fromkeys(ids, 1848 + goal))
            time.sleep(0.002)
        cycles, cpu = worker.stats.cycles - cycles0, worker.stats.thread_cpu - cpu0
        worker.stop()
        return cycles / elapsed, cpu / elapsed, listener.faults

    with tempfile.TemporaryDirectory() as folder:
        link = Path(folder) / "ttySIM"
        sim = subprocess.Popen(
            [sys.executable, "-m", "arena.cli", "sim-bus", "--link", str(link), "--wire-time"],
            stdout=subprocess.PIPE,
            text=True,
        )
        try:
            assert sim.stdout is not None
            sim.stdout.readline()  # the banner: the port is there
            top_rate, top_cpu, faults_top = run(0.0, link)
            paced_rate, paced_cpu, faults_paced = run(rate, link)
        finally:
            sim.terminate()
            sim.wait(timeout=10)
    return {
        "usb_max_control_rate_hz": top_rate,
        "usb_max_rate_cpu_percent": 100 * top_cpu,
        f"usb_{rate:.0f}hz_achieved_hz": paced_rate,
        f"usb_{rate:.0f}hz_cpu_percent": 100 * paced_cpu,
        "usb_servo_faults": float(faults_top + faults_paced),
    }


def teleop_latency(moves: int = 200, rate: float = 100.0) -> dict[str, float]:
    """Leader register change -> follower Goal_Position write, through a robot (usb-master and
    usb-slave on two simulated buses with wire-time emulation, both loops at `rate`): to the
    write of the leader's new position (the follower there), and to the first write that moves
    toward it (the first reaction; with a trajectory the way there takes longer). The drivers
    are paced on the simulators (`share`: arena/servo/sim_pace.py), as on `arena sim-bus`: a
    simulator kept off the CPU of a loaded machine is no lost servo."""
    import trio

    from arena.drivers.config import UsbMasterConfig, UsbSlaveConfig
    from arena.drivers.usb_master import UsbMaster
    from arena.drivers.usb_slave import UsbSlave
    from arena.feetech import registers as reg
    from arena.feetech.sim import SimBus
    from arena.robot.manager import open_manager
    from arena.robot.model import load_robot_model
    from arena.servo.sim_pty import PtySimBus

    latencies: list[float] = []
    reactions: list[float] = []

    async def run(leader: PtySimBus, follower: PtySimBus) -> None:
        model = load_robot_model("so-arm100")
        log: list[tuple[float, int, int, bytes]] = []
        async with open_manager() as manager:
            robot = await manager.create_robot("so-arm100", robot_id="arm")
            await robot.attach_slave(
                UsbSlave(UsbSlaveConfig(port=str(follower.link), rate=rate), model)
            )
            master = UsbMaster(UsbMasterConfig(port=str(leader.link), rate=rate), model)
            await master.prepare()
            await robot.attach_master(master)
            await trio.sleep(0.3)
            with follower.paused() as bus:
                bus.write_log = log
            last: bytes | None = None  # the follower's newest goal for servo 1
            for i in range(moves):
                target = 2048 + (25 if i % 2 == 0 else -25)  # 2.2 degrees: one direct step
                with follower.paused():
                    for _, sid, address, data in log:
                        last = data if sid == 1 and address == 42 else last
                    log.clear()
                before = last  # a write that differs from it is the follower's reaction
                with leader.paused() as bus:
                    bus.servo(1).move_by_hand(target)
                    moved_at = time.monotonic()
                want = reg.GOAL_POSITION.encode(target)
                deadline = moved_at + 1.0
                reacted = False
                while time.monotonic() < deadline:
                    await trio.sleep(0.0005)
                    with follower.paused():
                        goals = [(t, d) for t, sid, a, d in log if sid == 1 and a == 42]
                        log.clear()
                    if goals:
                        last = goals[-1][1]
                    moved = [t for t, d in goals if t >= moved_at and d != before]
                    if moved and not reacted:
                        reactions.append(moved[0] - moved_at)
                        reacted = True
                    hit = [t for t, d in goals if d == want]
                    if hit:
                        latencies.append(hit[0] - moved_at)
                        break
                await trio.sleep(0.03 + (i % 7) * 0.003)  # spaced: the rate limit never waits

    with (
        tempfile.TemporaryDirectory() as folder,
        PtySimBus(Path(folder) / "leader", SimBus(), wire_time=True, share=True) as leader,
        PtySimBus(Path(folder) / "follower", SimBus(), wire_time=True, share=True) as follower,
    ):
        trio.run(run, leader, follower)
    latencies.sort()
    reactions.sort()
    tag = f"{rate:.0f}hz"
    return {
        f"teleop_{tag}_p50_ms": 1000 * percentile(latencies, 0.5),
        f"teleop_{tag}_p99_ms": 1000 * percentile(latencies, 0.99),
        f"teleop_{tag}_missed": float(moves - len(latencies)),
        f"teleop_{tag}_first_reaction_p50_ms": 1000 * percentile(reactions, 0.5),
        f"teleop_{tag}_first_reaction_p99_ms": 1000 * percentile(reactions, 0.99),
    }
