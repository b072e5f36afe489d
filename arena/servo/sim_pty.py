"""A simulated bus (either family's `SimBus`) on a pseudo-terminal, so the real servo SDKs (and
LeRobot's buses on them) can talk to it.

The bus runs in its own thread. Its port is the pty's slave side, reached through a stable
symlink (`link`) that survives `unplug()` / `plug()`: a test can make the bus disappear and
come back under the same path, as a USB adapter does.

On a loaded machine the bus can be kept off the CPU for longer than a driver waits for a reply,
and a healthy servo would look silent. It counts what it owes its client (`arena.servo.sim_pace`):
`servo_bus()` gives a bus of the simulator's family in the same process whose reply timeout also
waits for the simulator, and with `share` (`arena sim-bus`) the counters are published for
clients in other processes, whose buses (`servo_arm.open_family_bus`) find them by the port.
Only a servo silent or late on purpose (`ServoFaults`) times out, however slow the machine.
"""

from __future__ import annotations

import contextlib
import math
import os
import select
import threading
import time
import tty
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, TypeVar

from arena.protocol.errors import ArenaError, ErrorCode
from arena.servo.interface import ServoBus, ServoFamily
from arena.servo.sdk_bus import SdkRegister
from arena.servo.sim_pace import LocalPace, SharedPace, paced_class, publish

R = TypeVar("R", bound=SdkRegister)

BITS_PER_BYTE = 10  # 8N1: start bit, 8 data bits, stop bit


#: Steps of position error at which a servo pushing on a stop gives its full torque: its
#: position loop's gain (the STS3215 and the X series both saturate within a few degrees).
FULL_PUSH_STEPS = 40.0
AMBIENT_C = 30.0
#: Degrees C per second at full load (heat grows with the square of the current), and the
#: share of the excess over ambient lost each second: a servo held at full load settles at
#: ambient + HEATING / COOLING (110 C: it burns), at half load at a quarter of that rise.
HEATING_C_PER_S = 4.0
COOLING_PER_S = 0.05
#: The load of a horn moving freely at full speed (friction, as a share of full torque).
MOVING_LOAD = 0.15
#: The overload protection of both families as they ship: a load past this share (the
#: STS3215's Overload_Torque 80 %) for this long (its Protection_Time 2 s; the X series'
#: Shutdown alike) releases the horn.
OVERLOAD_SHARE = 0.8
OVERLOAD_AFTER_S = 2.0


@dataclass
class Obstacle:
    """A stop in a servo's way: at `at` (present steps), on the `side` (+1 or -1) of the horn
    it was placed on; the horn does not pass it going that way."""

    at: float
    side: int


class SimServoBase:
    """What either family's simulated servo does alike: its registers as bytes in `memory`, and
    a motion model run up to the bus's time (`advance`: the family's `_step`, then `_refresh`
    of the registers it reports).

    The load model both share: a horn meets an `Obstacle` a test places (`place_obstacle`) and
    stops there; pushing on it (a goal beyond it, torque on), its load grows with the position
    error up to the torque its registers allow (`load_cap`); its temperature follows the load
    (a first-order model: heating with the load's square, cooling toward ambient), in the
    bus's time, so a test that passes the time in decides it exactly.
    """

    memory: bytearray
    last_update: float | None
    temperature: float
    obstacle: Obstacle | None
    hand: float | None  # a hand holds the horn here (present steps): it moves neither way
    heating: float  # C/s at full load (`HEATING_C_PER_S`)
    cooling: float  # share of the excess lost per second (`COOLING_PER_S`)
    overload_after: float  # seconds past OVERLOAD_SHARE before it trips (`OVERLOAD_AFTER_S`)
    load: float  # present load, as a share of full (0..1)

    def place_obstacle(self, at: float) -> None:
        """A stop at `at` (present steps) on the side of the horn it lies on: the horn will not
        pass it (as an object in the gripper's jaws, or a wall)."""
        here = self.present_position
        self.obstacle = Obstacle(float(at), 1 if at >= here else -1)

    def remove_obstacle(self) -> None:
        """The stop is gone: the horn moves freely again."""
        self.obstacle = None

    def hold_by_hand(self, present: float) -> None:
        """A hand takes the horn to `present` (stronger than the servo) and holds it there:
        the servo pushes on the hand, it does not move, until `let_go`."""
        self.move_by_hand(present)
        self.hand = float(present)

    def let_go(self) -> None:
        """The hand lets go of the horn."""
        self.hand = None

    def move_by_hand(self, present: float) -> None:
        """Someone moves the horn so that it reads `present` (the family's own)."""
        raise NotImplementedError

    @property
    def present_position(self) -> float:
        """Where the horn is, in present steps (the family's own frame)."""
        raise NotImplementedError

    def load_cap(self) -> float:
        """The most load (share of full, 0..1) the servo's registers let it give now."""
        raise NotImplementedError

    def blocked_move(self, move: float) -> tuple[float, bool]:
        """The part of a `move` (steps, in the present frame) the obstacle lets through, and
        whether it stopped the horn."""
        if self.hand is not None:
            return 0.0, True
        stop = self.obstacle
        if stop is None or move * stop.side <= 0:
            return move, False
        room = (stop.at - self.present_position) * stop.side
        if room <= 0:
            return 0.0, True
        if abs(move) > room:
            return room * stop.side, True
        return move, False

    def pushing(self, error: float) -> bool:
        """Whether a goal `error` steps away presses the horn on its obstacle (or a hand)."""
        if self.hand is not None:
            return True
        stop = self.obstacle
        if stop is None or error * stop.side <= 0:
            return False
        return (stop.at - self.present_position) * stop.side <= 0.5

    def push_load(self, error: float) -> float:
        """The load (share of full) of a horn held `error` steps short of its goal, capped."""
        return min(self.load_cap(), abs(error) / FULL_PUSH_STEPS)

    def move_toward(self, error: float, step: float, velocity: float, max_speed: float) -> float:
        """Move `step` steps toward a goal `error` away (all of it if the step reaches it),
        as far as the obstacle lets: the part moved. Stopped, the horn pushes on the stop;
        else it moves at `velocity` (of `max_speed`, its full speed) against friction."""
        moved, blocked = self.blocked_move(error if abs(step) >= abs(error) else step)
        if blocked:  # it ran into the stop: from now on it pushes on it
            self.load = self.push_load(error - moved)
        else:
            self.velocity = velocity
            self.load = min(self.load_cap(), MOVING_LOAD * abs(velocity) / max_speed)
        return moved

    def overload_tripped(self, dt: float) -> bool:
        """The overload protection after `dt` more seconds at the present load: True once a
        load past OVERLOAD_SHARE has lasted `overload_after` (the family then drops torque)."""
        if self.load < OVERLOAD_SHARE:
            self.stall_time = 0.0
            return False
        self.stall_time += dt
        return self.stall_time >= self.overload_after

    def heat(self, dt: float) -> None:
        """The temperature after `dt` seconds at the present load: exact for a constant load
        (the first-order model's own solution), so a long step does not overshoot."""
        settled = AMBIENT_C + self.heating * self.load**2 / self.cooling
        self.temperature = settled + (self.temperature - settled) * math.exp(-self.cooling * dt)

    def _step(self, dt: float) -> None:
        raise NotImplementedError

    def _refresh(self) -> None:
        raise NotImplementedError

    def advance(self, now: float) -> None:
        """Run the servo's model up to `now`."""
        if self.last_update is None:
            self.last_update = now
        dt = max(0.0, now - self.last_update)
        self.last_update = now
        if dt:
            self._step(dt)
        self._refresh()

    def peek(self, register: SdkRegister) -> int:
        """A register's value."""
        start = register.address
        return register.decode(bytes(self.memory[start : start + register.size]))

    def poke(self, register: SdkRegister, value: int) -> None:
        """Set a register directly (the servo's own doing, not a bus write)."""
        start = register.address
        self.memory[start : start + register.size] = register.encode(value)

    def read(self, address: int, length: int) -> bytes:
        """Bytes of the table (unknown addresses, and beyond its end, read as zeros)."""
        data = bytes(self.memory[address : address + length])
        return data + bytes(length - len(data))


def register_at(registers: Iterable[R]) -> dict[int, R]:
    """Each byte address of a family's registers, and the register it belongs to."""
    return {
        register.address + offset: register
        for register in registers
        for offset in range(register.size)
    }


@dataclass
class ServoFaults:
    """Faults a test can inject into one simulated servo."""

    silent: bool = False  # answers nothing
    drop: int = 0  # answers nothing to this many more packets, then answers again
    corrupt: bool = False  # answers with a bad checksum
    late: float = 0.0  # seconds its answers are held back
    error_bits: int = 0  # always set in its status packets (FaultBit flags)
    stalled: bool = False  # an obstacle: it cannot move, load and heat rise


@dataclass(frozen=True, slots=True)
class Reply:
    """A status packet, how long after the request the servo holds it back, and whether that
    is a fault (`ServoFaults.late`: a reader may time out) or its normal return delay (a
    reader waits for it, as for any reply the simulator owes)."""

    data: bytes
    delay: float = 0.0
    late: bool = False


class FrameParser(Protocol):
    """A family's incremental packet parser: bytes in, whole frames out (corrupt ones too)."""

    def feed(self, data: bytes) -> list[Any]: ...

    def clear(self) -> None: ...


class SimulatedBus(Protocol):
    """What a family's simulated bus offers `PtySimBus`."""

    family: ServoFamily
    servos: dict[int, Any]

    def parser(self) -> FrameParser:
        """A new parser for the instruction packets sent to this bus."""

    def handle(self, frame: Any, now: float) -> list[Reply]:
        """Carry out one frame (a corrupt one is counted and dropped); the replies in order."""


class PtySimBus:
    """Serve a `SimBus` on a pty at `link` (a symlink to the pty) until `close()`.

    With `wire_time` each exchange takes as long as its bytes would at `baud`, so a driver
    sees the same timing as on a real bus. With `share`, what it owes its client is published
    for other processes (`arena.servo.sim_pace`).
    """

    def __init__(
        self,
        link: Path,
        bus: SimulatedBus,
        *,
        wire_time: bool = False,
        baud: int = 1_000_000,
        share: bool = False,
    ) -> None:
        self.link = link
        self.bus = bus
        self.wire_time = wire_time
        self.baud = baud
        self.lock = threading.Lock()  # held while the bus handles a packet: tests poke safely
        self.requests = 0
        self.share = share
        # Bytes on the present pty (see `arena.servo.sim_pace`): sent by its client, dealt with
        # by the bus (answered, or left unanswered on purpose), and written back as replies.
        self.pace: LocalPace | SharedPace = LocalPace()
        self._master: int | None = None
        self._slave: int | None = None
        self._tty: str | None = None  # our pty's slave path, where `link` points while plugged
        self._wake_r, self._wake_w = os.pipe()
        self._stop = False
        self._thread: threading.Thread | None = None

    # -- lifetime -----------------------------------------------------------------------------

    def start(self) -> PtySimBus:
        """Create the pty and start serving; `ArenaError` (PORT_BUSY) if `link` is taken."""
        try:
            self.plug()
        except ArenaError:
            os.close(self._wake_r)
            os.close(self._wake_w)
            raise
        self._thread = threading.Thread(target=self._serve, name="sim-bus", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        """Stop serving and remove the port."""
        self._stop = True
        os.write(self._wake_w, b"x")
        if self._thread is not None:
            self._thread.join(timeout=5)
        self.unplug()
        os.close(self._wake_r)
        os.close(self._wake_w)

    def unplug(self) -> None:
        """The adapter disappears: the port path goes away and open handles see errors."""
        with self.lock:
            for fd in (self._master, self._slave):
                if fd is not None:
                    os.close(fd)
            self._master = self._slave = None
            if isinstance(self.pace, SharedPace):
                self.pace.withdraw()
                self.pace = LocalPace()
            # Only our own link: another bus may have taken the path since (a stale link).
            with contextlib.suppress(OSError):
                if self._tty is not None and os.readlink(self.link) == self._tty:
                    self.link.unlink()
            self._tty = None
        os.write(self._wake_w, b"x")

    def plug(self) -> None:
        """The adapter comes (back): a fresh pty behind the same path."""
        with self.lock:
            self._refuse_taken_link()
            master, slave = os.openpty()
            tty.setraw(master)
            tty.setraw(slave)  # pyserial sets it raw too; this covers the moment before
            self._master, self._slave = master, slave
            self._tty = os.ttyname(slave)
            if self.share:
                self.pace = publish(self._tty)
            else:
                self.pace.sent = self.pace.taken = self.pace.given = 0
            with contextlib.suppress(FileNotFoundError):
                self.link.unlink()  # a stale link (its pty gone), or our own
            self.link.parent.mkdir(parents=True, exist_ok=True)
            self.link.symlink_to(self._tty)
        os.write(self._wake_w, b"x")

    def _refuse_taken_link(self) -> None:
        # A link to a live device, or anything else at the path, belongs to someone else (often
        # another simulated bus a server is using): replacing it would cut them off.
        if not os.path.lexists(self.link):
            return
        if not self.link.is_symlink():
            raise ArenaError(
                ErrorCode.PORT_BUSY,
                f"{self.link} exists and is not a simulated bus's link: choose another path.",
            )
        target = os.readlink(self.link)
        if target != self._tty and os.path.exists(self.link):
            raise ArenaError(
                ErrorCode.PORT_BUSY,
                f"{self.link} is held by another simulated bus (it points to the live device "
                f"{target}): stop that bus first or choose another path.",
            )

    @property
    def plugged(self) -> bool:
        """Whether the port exists now."""
        return self._master is not None

    def __enter__(self) -> PtySimBus:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def servo_bus(self, timeout_margin: float) -> ServoBus:
        """A bus of the simulator's family on this port whose reply timeout waits for the
        simulator too (see the module docstring); `timeout_margin` as the bus takes it."""
        return self.bus.family.open_bus(
            str(self.link),
            self.baud,
            timeout_margin=timeout_margin,
            port_handler=self.paced_port(timeout_margin),
        )

    def paced_port(self, timeout_margin: float) -> Any:
        """An SDK port handler on this port paced as `servo_bus`'s is, for other programs'
        clients of the bus (LeRobot's `FeetechMotorsBus` and `DynamixelMotorsBus` in tests)."""
        paced = paced_class(self.bus.family.port_class)
        return paced(str(self.link), timeout_margin, lambda: self.pace)

    @contextlib.contextmanager
    def paused(self) -> Iterator[Any]:
        """Hold the bus still (no packet handled) while a test changes it."""
        with self.lock:
            yield self.bus

    # -- serving ------------------------------------------------------------------------------

    def _serve(self) -> None:
        parser = self.bus.parser()
        while not self._stop:
            master = self._master
            watch = [self._wake_r] + ([master] if master is not None else [])
            try:
                ready, _, _ = select.select(watch, [], [], 0.5)
            except (OSError, ValueError):
                continue  # the pty was closed under us (unplugged): look again
            if self._wake_r in ready:
                os.read(self._wake_r, 64)
                parser.clear()
                continue
            if master is None or master not in ready:
                continue
            try:
                data = os.read(master, 4096)
            except OSError:
                continue  # unplugged under us
            started = time.monotonic()
            taken = False
            for frame in parser.feed(data):
                with self.lock:
                    replies = self.bus.handle(frame, time.monotonic())
                self.requests += 1
                out = b"".join(reply.data for reply in replies)
                delay = max((reply.delay for reply in replies), default=0.0)
                if any(reply.late for reply in replies) and not taken:
                    self.pace.taken += len(data)  # the servo holds its reply back on purpose
                    taken = True
                if self.wire_time:
                    delay += (len(data) + len(out)) * BITS_PER_BYTE / self.baud
                    _sleep_until(started + delay)
                elif delay:
                    time.sleep(delay)
                if out:
                    self.pace.given += len(out)  # before the write: a reader never waits for less
                    with contextlib.suppress(OSError, TypeError):
                        os.write(master, out)
            if not taken:
                self.pace.taken += len(data)


def _sleep_until(deadline: float) -> None:
    # time.sleep overshoots by ~50-100 us; the wire times here are a few hundred us, so sleep
    # most of the way and yield the CPU in short naps for the rest.
    while (remaining := deadline - time.monotonic()) > 0:
        time.sleep(remaining if remaining > 2e-4 else 0)
