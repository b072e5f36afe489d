"""Simulated leader arms the server owns (`arena serve --sim-leader [TYPE]`; `make run` makes
one): a servo bus of the robot type on a pty of its own, which a `usb-master` opens as it opens
a real leader arm, and whose joints `PUT /api/robots/{id}/leader/joints` moves as a hand moves
a real one's (`arena.server.sim_leader_api`). The leader's usb-master then drives the robot
through every rule, exactly as it would with the arm on the table.

The server knows which leaders are its own by their port: a usb-master is simulated when the
port it opened is one of these. Nothing else is ever moved: a real leader arm's servos are
never written to by this route.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from arena.drivers.servo_arm import simulated_bus
from arena.robot.handle import Robot
from arena.robot.model import RobotModel, load_robot_model
from arena.servo.sim_control import BURST, RATE, SimControl
from arena.servo.sim_pty import PtySimBus

#: The kind of master a leader arm is.
LEADER_KIND = "usb-master"


@dataclass
class SimLeader:
    """One simulated leader arm: its bus on a pty at `link`, and the hand that moves it."""

    robot_type: str
    link: Path
    sim: PtySimBus
    #: The hand: built for the usb-master that reads the arm (its robot's joints and its
    #: calibration), so that a joint set to a value reads as that value to the master.
    _control: SimControl | None = None
    _control_for: str | None = None
    _stop: threading.Event | None = None
    #: Moves a second, and a burst of them (a token bucket).
    rate: float = RATE
    burst: float = float(BURST)
    _tokens: float = float(BURST)
    _last: float | None = None

    @property
    def port(self) -> str:
        """The path a usb-master's `port` names."""
        return str(self.link)

    def is_port(self, port: str | None) -> bool:
        """Whether `port` (as a usb-master opened it) is this arm's."""
        if not port:
            return False
        with contextlib.suppress(OSError):
            return os.path.realpath(port) == os.path.realpath(self.link)
        return False

    def control(self, master_id: str, model: RobotModel, calibration: Any) -> SimControl:
        """The hand for the usb-master `master_id` (a new one for a new master; its mover, on
        a thread of its own, carries out smooth moves)."""
        if self._control is None or self._control_for != master_id:
            self._stop_mover()
            self._control = SimControl(self.sim, model, calibration)
            self._control_for = master_id
            self._stop = threading.Event()
            threading.Thread(
                target=self._control.run_mover,
                args=(self._stop,),
                name=f"sim-leader-{self.robot_type}",
                daemon=True,
            ).start()
        self._control.calibration = calibration
        return self._control

    def allow(self, now: float) -> bool:
        """Whether one more move may go now (`now`: seconds of any steady clock)."""
        if self._last is not None:
            self._tokens = min(self.burst, self._tokens + (now - self._last) * self.rate)
        self._last = now
        if self._tokens < 1.0:
            return False
        self._tokens -= 1.0
        return True

    def _stop_mover(self) -> None:
        if self._stop is not None:
            self._stop.set()
        self._stop = None

    def close(self) -> None:
        """Stop moving and remove the port."""
        self._stop_mover()
        self.sim.close()


@dataclass
class SimLeaders:
    """The server's simulated leader arms, and the leader arms (usb-masters) attached to each
    robot, by robot and master id, so that a robot's leader can be told simulated or not."""

    leaders: list[SimLeader] = field(default_factory=list)
    _drivers: dict[str, dict[str, Any]] = field(default_factory=dict)
    _folders: list[Path] = field(default_factory=list)

    def start(self, robot_type: str) -> SimLeader:
        """A new simulated leader arm of `robot_type` on a pty in a folder of its own (so
        that servers side by side never share one)."""
        model = load_robot_model(robot_type)
        folder = Path(tempfile.mkdtemp(prefix="arena-sim-leader-"))
        self._folders.append(folder)
        sim = PtySimBus(folder / f"{robot_type}-leader", simulated_bus(model), share=True)
        sim.start()
        leader = SimLeader(robot_type, sim.link, sim)
        self.leaders.append(leader)
        return leader

    def close(self) -> None:
        """Remove every simulated arm and its folder."""
        for leader in self.leaders:
            leader.close()
        self.leaders.clear()
        for folder in self._folders:
            shutil.rmtree(folder, ignore_errors=True)
        self._folders.clear()

    def follow(self, robot: Robot, master_id: str, driver: object) -> None:
        """Remember a master just attached to `robot` if it is a leader arm (and forget the
        robot's leaders gone since: what is kept stays bounded)."""
        self._attached(robot)
        if getattr(driver, "kind", None) == LEADER_KIND:
            self._drivers.setdefault(robot.robot_id, {})[master_id] = driver

    def forget(self, robot_id: str) -> None:
        """A robot deleted: its leaders with it."""
        self._drivers.pop(robot_id, None)

    def _attached(self, robot: Robot) -> dict[str, bool]:
        """The robot's leader arms attached now (each: whether it drives), the others
        forgotten."""
        snapshot = robot.snapshot()
        attached = {
            peer.peer_id: peer is snapshot.master
            for peer in (snapshot.master, snapshot.paused_master)
            if peer is not None and peer.kind == LEADER_KIND
        }
        known = self._drivers.get(robot.robot_id, {})
        for master_id in [m for m in known if m not in attached]:
            del known[master_id]  # detached, or ended, since
        return attached

    def leader_of(self, robot: Robot) -> tuple[str, Any, bool] | None:
        """The robot's leader arm: (master id, its driver, whether it drives now, rather than
        waiting while another intervenes); None if no leader arm is attached."""
        attached = self._attached(robot)
        known = self._drivers.get(robot.robot_id, {})
        for master_id, driving in sorted(attached.items(), key=lambda item: not item[1]):
            if master_id in known:
                return master_id, known[master_id], driving
        return None

    def owning(self, port: str | None) -> SimLeader | None:
        """The simulated arm whose port a usb-master opened, if it is one of ours."""
        return next((leader for leader in self.leaders if leader.is_port(port)), None)
