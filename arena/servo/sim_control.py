"""Moving a simulated arm's joints by hand, from a script or a keyboard: `arena sim-bus
--control PORT` (and a few keys when it runs in a terminal). A simulated leader arm is then
something a new user can try, and a test can drive, without code against Arena's internals.

The control socket is TCP on 127.0.0.1, one JSON object a line, one answer a line:

    {"joint": "shoulder_pan", "deg": 30}                       one joint, at once
    {"joints": {"shoulder_pan": 30, "gripper": 50}, "duration": 1.0}   smoothly (minimum jerk)
    {"read": true}                                             where every joint is

Values are the robot type's units (degrees; 0-100 for a percent gripper) as a server reads the
arm with the same calibration (`--calibration`, Arena's or LeRobot's file; none: an
uncalibrated arm, step 2048 at 0). A joint is moved as a hand moves a servo's horn: a leader,
torque off, stays there; a servo under torque goes back to its goal. Every client may be
hostile: lines are at most `MAX_LINE` bytes, each connection `RATE` lines a second (bursts of
`BURST`), at most `MAX_CLIENTS` at once; a bad line gets an error code and a sentence.
"""

from __future__ import annotations

import json
import math
import socket
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from arena.robot.model import PERCENT, RobotModel
from arena.servo.calibration import Calibration
from arena.servo.sim_pty import PtySimBus

#: The longest line (bytes, newline included) a client may send; a longer one closes it.
MAX_LINE = 4096
#: Lines a second a connection may send, and its burst; more are answered RATE_LIMITED.
RATE = 50.0
BURST = 20
#: Connections served at once; another is told so and closed.
MAX_CLIENTS = 4
#: The longest smooth move (seconds).
MAX_DURATION = 60.0
#: Seconds a connection may stay silent before it is closed.
IDLE_TIMEOUT = 600.0
#: How often a smooth move places the joints (seconds).
TICK = 0.01
#: What one key press moves the selected joint by (its units).
KEY_STEP = 5.0


class ControlError(Exception):
    """A line the control refuses: `code` (upper case) and a sentence."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code
        self.message = message


@dataclass
class _Move:
    """One joint on its way: from `start` at `t0` to `goal` over `duration` seconds."""

    start: float
    goal: float
    t0: float
    duration: float

    def at(self, now: float) -> tuple[float, bool]:
        """Where it is at `now` (minimum jerk), and whether it has arrived."""
        if self.duration <= 0.0 or now >= self.t0 + self.duration:
            return self.goal, True
        s = max(0.0, (now - self.t0) / self.duration)
        share = s**3 * (10.0 - 15.0 * s + 6.0 * s * s)
        return self.start + (self.goal - self.start) * share, False


class SimControl:
    """The joints of the arm simulated by `sim`, moved by hand in the robot type's units
    through `calibration`. Pure but for the bus (`sim.paused()` guards every change): `apply`
    and `advance` take the time, so tests run it on any clock; `serve` runs it on threads."""

    def __init__(
        self,
        sim: PtySimBus,
        model: RobotModel,
        calibration: Calibration | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.sim = sim
        self.model = model
        ids = {j.name: j.servo_id for j in model.joints}
        self.calibration = calibration or Calibration.identity(ids, model.robot_type)
        self.spans = {j.name: math.degrees(j.span) for j in model.joints if j.unit == PERCENT}
        self.clock = clock
        self.lock = threading.Lock()  # the moves, shared by the clients and the mover
        self._moves: dict[str, _Move] = {}
        self._wake = threading.Event()

    @property
    def names(self) -> list[str]:
        """The joints, in the robot type's order."""
        return [j.name for j in self.model.joints]

    def read(self) -> dict[str, float]:
        """Every joint's value now (the robot type's units), as a server would read it."""
        with self.sim.paused() as bus:
            raw = {sid: round(servo.present_position) for sid, servo in bus.servos.items()}
        values = self.calibration.to_values(raw, self.spans)
        return {name: round(values[name], 3) for name in self.names if name in values}

    def _place(self, values: Mapping[str, float]) -> None:
        steps = self.calibration.to_goal_steps(values, self.spans)
        with self.sim.paused() as bus:
            for sid, step in steps.items():
                if sid in bus.servos:
                    bus.servo(sid).move_by_hand(step)

    def move(self, goals: Mapping[str, float], duration: float, now: float) -> None:
        """Move joints to `goals` (validated: see `parse`) over `duration` seconds (0: at
        once); a joint already on its way turns to the new goal from where it is."""
        current = self.read()
        with self.lock:
            for name, goal in goals.items():
                self._moves[name] = _Move(current[name], goal, now, duration)
        self.advance(now)
        self._wake.set()

    def advance(self, now: float) -> bool:
        """Place every moving joint where its move has it at `now`; True while any moves."""
        with self.lock:
            placed = {}
            for name, move in list(self._moves.items()):
                placed[name], arrived = move.at(now)
                if arrived:
                    del self._moves[name]
            moving = bool(self._moves)
        if placed:
            self._place(placed)
        return moving

    def parse(self, line: bytes) -> tuple[str, dict[str, float], float]:
        """A line as (`read` or `move`, goals, duration), or `ControlError`."""
        try:
            message = json.loads(line)
        except (ValueError, UnicodeDecodeError):
            raise ControlError("INVALID_JSON", "The line is not JSON.") from None
        if not isinstance(message, dict):
            raise ControlError("INVALID_BODY", "A line is one JSON object.")
        if message.get("read") is True and len(message) == 1:
            return "read", {}, 0.0
        duration = message.get("duration", 0.0)
        if not _number(duration) or not 0.0 <= duration <= MAX_DURATION:
            raise ControlError(
                "INVALID_BODY", f"duration is seconds from 0 to {MAX_DURATION:g}: {duration!r}."
            )
        if "joint" in message and "joints" not in message:
            unit = "deg" if "deg" in message else "value"
            if set(message) - {"joint", unit, "duration"} or unit not in message:
                raise ControlError(
                    "INVALID_BODY",
                    'One joint is {"joint": NAME, "deg": VALUE} (or "value"), with "duration".',
                )
            goals = {message["joint"]: message[unit]}
        elif isinstance(message.get("joints"), dict) and not set(message) - {"joints", "duration"}:
            goals = message["joints"]
        else:
            raise ControlError(
                "INVALID_BODY",
                'Send {"joint": NAME, "deg": VALUE}, {"joints": {NAME: VALUE, ...}, '
                '"duration": SECONDS} or {"read": true}.',
            )
        return "move", self.check_goals(goals), float(duration)

    def check_goals(self, goals: Mapping[Any, Any]) -> dict[str, float]:
        """Goals by joint name, each a joint of the model within its limits, or
        `ControlError` (INVALID_BODY, UNKNOWN_JOINT, OUT_OF_RANGE)."""
        if not goals:
            raise ControlError("INVALID_BODY", "No joint named.")
        checked = {}
        for name, value in goals.items():
            joint = self.model.joint(name) if isinstance(name, str) else None
            if joint is None:
                raise ControlError(
                    "UNKNOWN_JOINT", f"No joint {name!r}; the joints: {', '.join(self.names)}."
                )
            if not _number(value) or not joint.lower <= value <= joint.upper:
                unit = "%" if joint.unit == PERCENT else " deg"
                raise ControlError(
                    "OUT_OF_RANGE",
                    f"{joint.name} goes from {joint.lower:.1f}{unit} to {joint.upper:.1f}{unit}: "
                    f"{value!r}.",
                )
            checked[joint.name] = float(value)
        return checked

    def apply(self, line: bytes, now: float) -> dict[str, Any]:
        """One line's answer (and its move, if it is one)."""
        try:
            kind, goals, duration = self.parse(line)
        except ControlError as error:
            return {"ok": False, "error": error.code, "message": error.message}
        if kind == "read":
            return {"ok": True, "joints": self.read()}
        self.move(goals, duration, now)
        return {"ok": True, "moving": sorted(goals), "duration": duration}

    # -- on threads ---------------------------------------------------------------------------

    def serve(self, port: int, stop: threading.Event) -> ControlServer:
        """Listen on 127.0.0.1:`port` (0: any free port) until `stop`; the mover runs too."""
        server = ControlServer(self, port, stop)
        server.start()
        return server

    def run_mover(self, stop: threading.Event) -> None:
        """Carry out smooth moves every `TICK` until `stop` (a thread's body)."""
        while not stop.is_set():
            self._wake.clear()  # (before: a move set after this wakes the wait below)
            if self.advance(self.clock()):
                stop.wait(TICK)
            else:
                self._wake.wait(0.5)


def _number(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


class ControlServer:
    """The control socket's threads: one accepting, one per client (at most `MAX_CLIENTS`),
    and the mover."""

    def __init__(self, control: SimControl, port: int, stop: threading.Event) -> None:
        self.control = control
        self.stop = stop
        self.listener = socket.create_server(("127.0.0.1", port))
        self.listener.settimeout(0.5)
        self.port: int = self.listener.getsockname()[1]
        self._clients = threading.BoundedSemaphore(MAX_CLIENTS)

    def start(self) -> None:
        """Start accepting and moving (daemon threads: they end with the simulator)."""
        for target, name in ((self._accept, "sim-control"), (self._move, "sim-control-mover")):
            threading.Thread(target=target, name=name, daemon=True).start()

    def _move(self) -> None:
        self.control.run_mover(self.stop)

    def _accept(self) -> None:
        with self.listener:
            while not self.stop.is_set():
                try:
                    connection, _ = self.listener.accept()
                except TimeoutError:
                    continue
                except OSError:
                    return
                if not self._clients.acquire(blocking=False):
                    with connection:
                        _send(connection, _busy())
                    continue
                threading.Thread(
                    target=self._client, args=(connection,), name="sim-control-client", daemon=True
                ).start()

    def _client(self, connection: socket.socket) -> None:
        try:
            with connection:
                connection.settimeout(IDLE_TIMEOUT)
                self._talk(connection)
        except OSError:
            pass  # gone, or silent too long
        finally:
            self._clients.release()

    def _talk(self, connection: socket.socket) -> None:
        pending = b""
        tokens, last = float(BURST), self.control.clock()
        while not self.stop.is_set():
            data = connection.recv(MAX_LINE)
            if not data:
                return
            pending += data
            while b"\n" in pending:
                line, pending = pending.split(b"\n", 1)
                now = self.control.clock()
                tokens = min(float(BURST), tokens + (now - last) * RATE)
                last = now
                if not line.strip():
                    continue
                if tokens < 1.0:
                    answer = {
                        "ok": False,
                        "error": "RATE_LIMITED",
                        "message": f"More than {RATE:g} lines a second; line dropped.",
                    }
                else:
                    tokens -= 1.0
                    answer = self.control.apply(line, now)
                _send(connection, answer)
            if len(pending) >= MAX_LINE:
                _send(
                    connection,
                    {
                        "ok": False,
                        "error": "LINE_TOO_LONG",
                        "message": f"A line is at most {MAX_LINE} bytes; closing.",
                    },
                )
                _drain(connection)
                return


def _drain(connection: socket.socket) -> None:
    """Close our side and read what the client still sends, a little (closing with unread
    bytes resets the connection, and the client may lose the answer it was sent)."""
    connection.shutdown(socket.SHUT_WR)
    connection.settimeout(1.0)
    left = 16 * MAX_LINE
    while left > 0 and (data := connection.recv(MAX_LINE)):
        left -= len(data)


def _busy() -> dict[str, Any]:
    return {
        "ok": False,
        "error": "TOO_MANY_CLIENTS",
        "message": f"At most {MAX_CLIENTS} connections at once; closing.",
    }


def _send(connection: socket.socket, answer: Mapping[str, Any]) -> None:
    connection.sendall(json.dumps(answer).encode() + b"\n")


def usage(control: SimControl, port: int | None, keys: bool) -> str:
    """How to move the joints, printed when the simulator starts."""
    lines = []
    if port is not None:
        first = control.names[0]
        lines += [
            f"control: JSON lines on 127.0.0.1:{port}, one answer a line, e.g.",
            f'  echo \'{{"joint": "{first}", "deg": 30}}\' > /dev/tcp/127.0.0.1/{port}   (bash)',
            f'  {{"joints": {{"{first}": -20, ...}}, "duration": 1.0}}   (smoothly)',
            '  {"read": true}   (every joint)',
            f"  joints: {', '.join(control.names)}",
        ]
    if keys:
        numbered = ", ".join(f"{k + 1} {name}" for k, name in enumerate(control.names[:9]))
        lines += [
            f"keys: {numbered}; + and - move it {KEY_STEP:g}, 0 to 0, r reads, ? says this",
        ]
    return "\n".join(lines)


def key_loop(control: SimControl, read_key: Callable[[], str], say: Callable[[str], None]) -> None:
    """Move joints from single key presses until `read_key` returns "" (end of input)."""
    names = control.names[:9]
    selected = names[0]
    goals = control.read()  # each key moves from the last goal (a reading is a step off)
    while key := read_key():
        if key.isdigit() and key != "0" and int(key) <= len(names):
            selected = names[int(key) - 1]
            say(f"{selected} selected")
            continue
        if key in "+=-0":
            joint = control.model.joint(selected)
            assert joint is not None
            step = KEY_STEP if key in "+=" else -KEY_STEP
            goal = goals[selected] = joint.clamp(0.0 if key == "0" else goals[selected] + step)
            control.move({selected: goal}, 0.2, control.clock())
            say(f"{selected} -> {goal:g}")
        elif key == "r":
            say(json.dumps(control.read()))
        elif key == "?":
            say(usage(control, None, keys=True))
