"""What a simulated bus still owes its client, so that a slow simulator never looks like a silent
servo.

A simulator is a program like any other: on a loaded machine it can be kept off the CPU for
longer than a driver waits for a servo's reply (a real bus answers within a millisecond or two,
and Arena waits the wire time plus 10 ms). A healthy simulated servo then looked silent, and 20
such cycles declared the bus lost and e-stopped the robot. So the simulator counts, per pty,
the bytes its client sent (`sent`, counted by the client before each write), the bytes it has
dealt with (`taken`: answered, or left unanswered on purpose) and the reply bytes it wrote
(`given`); the client's reply timeout also waits while the simulator has not dealt with all it
was sent, or a reply it wrote has not arrived (`Paced`). Only a servo silent or late on purpose
times out, however slow the machine; a simulator stuck `OWED_PATIENCE` past the timeout still
fails the read.

In one process (`PtySimBus` in the tests) the counters are plain numbers (`LocalPace`). Across
processes (`arena sim-bus` and a server's arm) they live in a small file both map
(`SharedPace`), named after the pty in `PACE_DIR`, with the simulator's pid: `find` gives a
client the counters of the simulator on its port, or None for any other port (a real adapter is
never a pty), whose timeouts then stay as they are.
"""

from __future__ import annotations

import contextlib
import mmap
import os
import select
import struct
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

#: A reply still owed after its timeout by this much (seconds) times out anyway: the simulator
#: is stuck, and a driver must say so rather than wait for ever.
OWED_PATIENCE = 30.0
#: Where simulators publish their counters (one file per pty).
PACE_DIR = Path(tempfile.gettempdir()) / "arena-sim-bus"
_LAYOUT = struct.Struct("<4Q")  # pid, sent, taken, given
_PID, _SENT, _TAKEN, _GIVEN = (8 * k for k in range(4))


class Pace(Protocol):
    """A simulator's counters on its present pty (see the module docstring)."""

    sent: int
    taken: int
    given: int


@dataclass
class LocalPace:
    """The counters of a simulator in the client's own process."""

    sent: int = 0
    taken: int = 0
    given: int = 0


class SharedPace:
    """The counters in a file mapped by the simulator (which writes `taken` and `given`) and
    its client (which writes `sent`): each number has one writer."""

    def __init__(self, path: Path, *, create: bool = False) -> None:
        self.path = path
        if create:
            path.parent.mkdir(parents=True, exist_ok=True)
            temporary = path.with_name(f".{path.name}.{os.getpid()}")
            temporary.write_bytes(_LAYOUT.pack(os.getpid(), 0, 0, 0))
            temporary.replace(path)  # whole or not at all, for a client looking now
        with path.open("r+b") as file:
            self._map = mmap.mmap(file.fileno(), _LAYOUT.size)

    def _get(self, offset: int) -> int:
        value: int = struct.unpack_from("<Q", self._map, offset)[0]
        return value

    def _set(self, offset: int, value: int) -> None:
        struct.pack_into("<Q", self._map, offset, value)

    @property
    def pid(self) -> int:
        """The simulator's process."""
        return self._get(_PID)

    sent = property(lambda self: self._get(_SENT), lambda self, v: self._set(_SENT, v))
    taken = property(lambda self: self._get(_TAKEN), lambda self, v: self._set(_TAKEN, v))
    given = property(lambda self: self._get(_GIVEN), lambda self, v: self._set(_GIVEN, v))

    def withdraw(self) -> None:
        """The simulator's pty is gone: its file goes (the mapping stays valid for whoever
        still holds it, and is unmapped with it)."""
        with contextlib.suppress(FileNotFoundError):
            self.path.unlink()


def pace_path(tty: str) -> Path:
    """Where the simulator serving the pty `tty` (`/dev/pts/7`) keeps its counters."""
    return PACE_DIR / tty.removeprefix("/dev/").replace("/", "-")


def publish(tty: str) -> SharedPace:
    """The simulator's counters for its pty `tty`, for clients in other processes."""
    return SharedPace(pace_path(tty), create=True)


def find(port: str) -> SharedPace | None:
    """The counters of the simulator that serves `port` (a path to a pty, or a link to one)
    from another process, or None: not a pty, no simulator published one, or it has exited."""
    tty = os.path.realpath(port)
    path = pace_path(tty)
    if not tty.startswith("/dev/pts/") or not path.exists():
        return None
    try:
        pace = SharedPace(path)
    except (OSError, ValueError):
        return None
    try:
        os.kill(pace.pid, 0)  # alive? (a file left by a killed simulator is no simulator)
    except ProcessLookupError:
        return None
    except PermissionError:
        pass  # alive, another user's
    return pace


class Paced:
    """Mixed in before a family's SDK port class: a reply timeout that also waits for the
    simulator (see the module docstring). `pace` gives the counters at each opening (the
    simulator's pty may be new), or None: the port's own timeouts, unchanged."""

    ser: Any
    packet_timeout: float

    def __init__(
        self, port_name: str, timeout_margin: float, pace: Callable[[], Pace | None]
    ) -> None:
        super().__init__(port_name, timeout_margin)  # type: ignore[call-arg]
        self.pace_of = pace
        self.pace: Pace | None = None
        self.received = 0

    def setupPort(self, cflag_baud: int) -> bool:
        """Open the port; the replies given to an earlier client are not owed to this one."""
        opened: bool = super().setupPort(cflag_baud)  # type: ignore[misc]
        self.pace = self.pace_of()
        self.received = 0 if self.pace is None else self.pace.given
        return opened

    def writePort(self, packet: Any) -> int:
        """Write, counted first: the simulator never takes more than was sent."""
        if self.pace is not None:
            self.pace.sent += len(packet)
        return self.ser.write(packet) or 0

    def clearPort(self) -> None:
        """Stale input is read and counted rather than dropped: every reply byte counts."""
        if self.pace is None:
            super().clearPort()  # type: ignore[misc]
            return
        while waiting := self.ser.in_waiting:
            self.received += len(self.ser.read(waiting))

    def readPort(self, length: int) -> bytes:
        """Read; past the deadline, while the simulator owes a reply, wait for it without
        spinning (a spinning reader would take the CPU the simulator needs)."""
        data: bytes = super().readPort(length)  # type: ignore[misc]
        if not data and self._owed():
            select.select([self.ser.fileno()], [], [], 0.005)
            data = self.ser.read(length)
        self.received += len(data)
        return data

    def isPacketTimeout(self) -> bool:
        """Timed out only when nothing is owed (or the simulator is stuck)."""
        since: float = self.getTimeSinceStart()  # type: ignore[attr-defined]
        if self._owed() and since < self.packet_timeout + OWED_PATIENCE * 1e3:
            return False
        timed_out: bool = super().isPacketTimeout()  # type: ignore[misc]
        return timed_out

    def _owed(self) -> bool:
        pace = self.pace
        return pace is not None and (pace.taken < pace.sent or self.received < pace.given)


_PACED: dict[str, type[Any]] = {}  # by the port class's qualified name


def paced_class(port_class: type[Any]) -> type[Any]:
    """The family's port class, paced (`Paced` mixed in before it); one class per family."""
    key = f"{port_class.__module__}.{port_class.__qualname__}"
    if key not in _PACED:
        _PACED[key] = type(f"Paced{port_class.__name__}", (Paced, port_class), {})
    return _PACED[key]
