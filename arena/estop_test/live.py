"""`arena estop-test`: stop a running robot every way it can be stopped, and time each stop.

The tester is an ordinary client of the server: REST through `arena.client.AsyncArena`, its
messages made by `arena.client.messages` (the protocol's structs), WebSockets with `websockets`
on asyncio. Not `arena.client`'s sessions for those: a trial needs every message with its
arrival time (a session keeps the newest), a master cut without a close frame (as a pulled
cable), and no reconnection (a session's would be a new master in the middle of a trial). For
the whole run it watches the robot as a viewer (`/ws/robots/{id}/state`: the
e-stopped state and the measured joints) and as an extra slave, the probe
(`/ws/slave/{id}?id=estop-probe`: the targets every slave is sent, and the stop notice); it
reports no joints of its own. Each trial it takes the robot as master, sweeps a joint so the
arm is moving, triggers one stop path, observes for `settle` seconds after the e-stop, and
resets. For the paths that leave the master in place, the master keeps commanding through the
stop: those commands must be refused and nothing may move.

Every time is taken on this process's monotonic clock when a message arrives, so the delays
include the trip back to the tester (on loopback, tens of microseconds).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field

import websockets
from websockets.asyncio.client import ClientConnection

from arena.client import ArenaClientError, AsyncArena, messages, ws_url
from arena.estop_test.analysis import STILL_FOR, Sample, Trial, joint_stops, stop_trial
from arena.protocol.errors import Severity
from arena.protocol.messages import encode

#: Every stop path, in the order they run.
PATHS = (
    "rest",  # POST /api/robots/{id}/estop
    "global",  # POST /api/estop: every robot of the server (see `_prepare`)
    "master-message",  # the master's {"type": "estop"}
    "master-cut",  # the master's TCP connection dropped without a close frame
    "heartbeat",  # the master goes silent until the server's heartbeat_timeout
    "slave-error",  # a slave reports a critical error
    "group",  # POST /api/groups/{gid}/estop of a group holding the robot
)
#: The heartbeat path is left out by default when the server waits longer than this.
HEARTBEAT_DEFAULT_MAX = 10.0
PROBE_ID = "estop-probe"
MASTER_ID = "estop-test"
COMMAND_RATE = 50.0  # Hz, the master's sweep
HOLD_FIRST = 0.3  # seconds at the sweep's center before it starts


@dataclass
class Settings:
    """How to run the test."""

    url: str
    robot: str
    trials: int = 5
    paths: tuple[str, ...] = ()  # empty: every path (heartbeat only if the server is quick)
    api_key: str | None = None
    settle: float = 3.0  # seconds at most for the arm to come to rest after the stop
    threshold: float = 0.5  # degrees: a joint within this of its final value is at rest
    joint: str | None = None  # the joint swept (default: the robot's first)
    amplitude: float = 20.0  # degrees of the sweep
    sweep_hz: float = 1.0
    lead: float = 0.5  # seconds of sweep before the trigger
    timeout: float = 5.0  # seconds for a stop to show (heartbeat: plus the server's timeout)


@dataclass
class _Watch:
    """What the viewer and the probe have seen, with arrival times."""

    modes: list[tuple[float, str]] = field(default_factory=list)
    samples: list[Sample] = field(default_factory=list)
    targets: list[float] = field(default_factory=list)
    notices: list[float] = field(default_factory=list)
    changed: asyncio.Event = field(default_factory=asyncio.Event)

    def mark(self) -> None:
        self.changed.set()

    async def until(
        self, check: Callable[[], bool], timeout: float, every: float | None = None
    ) -> bool:
        """Wait until `check()` holds (re-checked on every message, and `every` seconds when
        silence can make it true) or time runs out."""
        deadline = time.monotonic() + timeout
        while not check():
            left = deadline - time.monotonic()
            if left <= 0:
                return False
            self.changed.clear()
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self.changed.wait(), min(left, every or left))
        return True


class EStopTest:
    """One run of the test against a server (use `run`)."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.http = AsyncArena(settings.url, settings.api_key)
        self.watch = _Watch()
        self.joint = ""
        self.center = 0.0
        self.heartbeat_timeout: float | None = None
        self.group: str | None = None
        self.notes: list[str] = []

    def _ws_url(self, path: str, **query: str) -> str:
        return ws_url(self.settings.url, path, **query, token=self.settings.api_key or "")

    async def run(self) -> dict[str, list[Trial]]:
        """Every chosen path, `trials` times each; the trials per path."""
        try:
            paths = await self._prepare()
            robot = self.settings.robot
            async with (
                websockets.connect(self._ws_url(f"/ws/robots/{robot}/state")) as viewer,
                websockets.connect(self._ws_url(f"/ws/slave/{robot}", id=PROBE_ID)) as probe,
            ):
                readers = [
                    asyncio.create_task(self._read_viewer(viewer)),
                    asyncio.create_task(self._read_probe(probe)),
                    asyncio.create_task(_heartbeats(probe, self._heartbeat_interval())),
                ]
                try:
                    await self.watch.until(lambda: bool(self.watch.samples), self.settings.timeout)
                    results: dict[str, list[Trial]] = {}
                    for path in paths:
                        results[path] = [
                            await self._trial(path, probe) for _ in range(self.settings.trials)
                        ]
                    return results
                finally:
                    for task in readers:
                        task.cancel()
                    # Detached on purpose first: a slave that just goes is a slave lost, and
                    # that e-stops the robot.
                    with contextlib.suppress(ArenaClientError):
                        await self.http.detach_slave(robot, PROBE_ID)
                    await self._reset()
        except ArenaClientError as error:
            raise EStopTestError(_described(error, self.settings.url)) from None
        finally:
            if self.group is not None:
                with contextlib.suppress(ArenaClientError):
                    await self.http.delete_group(self.group)
            await self.http.aclose()

    def _heartbeat_interval(self) -> float:
        return min(5.0, (self.heartbeat_timeout or 20.0) / 4)

    async def _prepare(self) -> list[str]:
        robot = self.settings.robot
        try:
            found = await self.http.robot(robot)
        except ArenaClientError as error:
            if error.code == "UNREACHABLE":
                raise
            raise EStopTestError(f"robot {robot!r}: {error.status} {error}") from None
        joints = found.get("joints", [])
        if not joints:
            raise EStopTestError(f"robot {robot!r} reports no joints")
        first = joints[0]
        if self.settings.joint is not None:
            named = [j for j in joints if j["name"] == self.settings.joint]
            if not named:
                known = ", ".join(j["name"] for j in joints)
                raise EStopTestError(
                    f"robot {robot!r} has no joint {self.settings.joint!r} ({known})"
                )
            first = named[0]
        self.joint = first["name"]
        limits = first.get("limits", {})
        lower, upper = float(limits.get("lower", -90)), float(limits.get("upper", 90))
        reach = self.settings.amplitude
        self.center = min(max(0.0, lower + reach), upper - reach)
        status = await self.http.status()
        self.heartbeat_timeout = status.get("heartbeat_timeout")
        paths = list(self.settings.paths or PATHS)
        unknown = sorted(set(paths) - set(PATHS))
        if unknown:
            raise EStopTestError(f"unknown stop paths {unknown}; known: {', '.join(PATHS)}")
        if "global" in paths and "global" not in self.settings.paths:
            # POST /api/estop stops every robot of the server: only when this is its only
            # robot, or when asked for by name.
            listed = await self.http.robots()
            others = sorted(str(r["id"]) for r in listed if r.get("id") != robot)
            if others:
                paths.remove("global")
                shown = ", ".join(others[:5]) + (", ..." if len(others) > 5 else "")
                self.notes.append(
                    f"global skipped: POST /api/estop would e-stop every robot on the server, "
                    f"and it has {len(others)} besides {robot!r} ({shown}); name it in --paths "
                    "to include it"
                )
        wait = self.heartbeat_timeout
        if not self.settings.paths and (wait is None or wait > HEARTBEAT_DEFAULT_MAX):
            paths.remove("heartbeat")
            self.notes.append(
                f"heartbeat left out: the server waits {wait} s for a silent master; "
                "name it in --paths to include it"
            )
        if "group" in paths:
            self.group = f"estop-test-{uuid.uuid4().hex[:8]}"
            try:
                await self.http.create_group(self.group, [robot])
            except ArenaClientError as error:
                raise EStopTestError(f"cannot make a group: {error.status} {error}") from None
        await self._reset()
        return paths

    async def _read_viewer(self, viewer: ClientConnection) -> None:
        async for raw in viewer:
            now = time.monotonic()
            message = json.loads(raw)
            data = message.get("data")
            if message.get("type") == "state" and data:
                self.watch.modes.append((now, str(data["mode"])))
            elif message.get("type") == "joint_states" and data:
                real = {j["name"]: j["real_value"] for j in data if j["real_value"] is not None}
                if real:
                    self.watch.samples.append((now, real))
            self.watch.mark()

    async def _read_probe(self, probe: ClientConnection) -> None:
        async for raw in probe:
            now = time.monotonic()
            kind = json.loads(raw).get("type")
            if kind == "execute_command":
                self.watch.targets.append(now)
            elif kind == "estop":
                self.watch.notices.append(now)
            self.watch.mark()

    async def _trial(self, path: str, probe: ClientConnection) -> Trial:
        settings = self.settings
        robot = settings.robot
        master = await websockets.connect(
            self._ws_url(f"/ws/master/{robot}", id=MASTER_ID, takeover="true", acks="false")
        )
        draining = asyncio.create_task(_drain(master))
        sweeping: asyncio.Task[None] | None = None
        try:
            sweeping = asyncio.create_task(self._sweep(master))
            await asyncio.sleep(HOLD_FIRST + settings.lead)
            watch = self.watch
            modes_before, notices_before = len(watch.modes), len(watch.notices)
            if path in ("master-cut", "heartbeat"):
                sweeping.cancel()  # the master is gone or silent from here on
            trigger = time.monotonic()
            await self._trigger(path, master, probe)
            wait = settings.timeout + (self.heartbeat_timeout or 0.0) * (path == "heartbeat")

            def stopped() -> bool:
                modes = watch.modes[modes_before:]
                notices = len(watch.notices) > notices_before
                return notices and any(mode == "estopped" for _, mode in modes)

            await watch.until(stopped, wait)
            estopped = next((t for t, m in watch.modes[modes_before:] if m == "estopped"), None)
            notice = watch.notices[notices_before] if len(watch.notices) > notices_before else None
            start = trigger - settings.lead
            await watch.until(
                lambda: _at_rest(watch.samples, start, trigger, settings.threshold),
                settings.settle,
                every=0.02,
            )
            return stop_trial(
                path,
                trigger,
                estopped=estopped,
                notice=notice,
                targets=[t for t in watch.targets if t >= start],
                samples=[s for s in watch.samples if s[0] >= start],
                threshold=settings.threshold,
                until=time.monotonic(),
            )
        finally:
            if sweeping is not None:
                sweeping.cancel()
            draining.cancel()
            if path != "master-cut":
                with contextlib.suppress(websockets.ConnectionClosed):
                    await master.close()
            await self._reset()

    async def _sweep(self, master: ClientConnection) -> None:
        """Commands at COMMAND_RATE: the center for HOLD_FIRST seconds (the arm gets there),
        then a sine around it, until cancelled."""
        start = time.monotonic()
        tick = 1.0 / COMMAND_RATE
        omega = 2 * math.pi * self.settings.sweep_hz
        with contextlib.suppress(websockets.ConnectionClosed):
            while True:
                t = max(0.0, time.monotonic() - start - HOLD_FIRST)
                await self._command(
                    master, self.center + self.settings.amplitude * math.sin(omega * t)
                )
                await asyncio.sleep(tick - (time.monotonic() - start) % tick)

    async def _command(self, master: ClientConnection, value: float) -> None:
        await master.send(encode(messages.command({self.joint: round(value, 3)})))

    async def _trigger(self, path: str, master: ClientConnection, probe: ClientConnection) -> None:
        robot = self.settings.robot
        reason = f"estop-test {path}"
        if path == "rest":
            await self.http.estop(robot, reason)
        elif path == "global":
            await self.http.estop(None, reason)
        elif path == "group" and self.group is not None:
            await self.http.estop_group(self.group, reason)
        elif path == "master-message":
            await master.send(encode(messages.estop(reason)))
        elif path == "master-cut":
            master.transport.abort()  # no close frame: as a cable pulled or a process killed
        elif path == "slave-error":
            error = messages.error("ESTOP_TEST", "estop-test", Severity.CRITICAL)
            await probe.send(encode(error))
        # "heartbeat": nothing to do; the master has gone silent

    async def _reset(self) -> None:
        """Clear the e-stop of the robot (and of its group); a refusal changes nothing here."""
        with contextlib.suppress(ArenaClientError):
            await self.http.reset(self.settings.robot)
        if self.group is not None:
            with contextlib.suppress(ArenaClientError):
                await self.http.reset_group(self.group)


class EStopTestError(Exception):
    """The test cannot run (no such robot, a refused request)."""


def _described(error: ArenaClientError, url: str) -> str:
    """What `arena estop-test` says of a failed request."""
    if error.code == "UNREACHABLE":
        detail = error.message.split(": ", 1)[-1]  # the client's sentence names the URL too
        return f"cannot reach --url {url}: {detail}"
    return f"{error.status} {error}" if error.status else str(error)


def _at_rest(samples: list[Sample], start: float, trigger: float, threshold: float) -> bool:
    """Every joint has stayed still (within `threshold`) for `STILL_FOR` by now."""
    now = time.monotonic()
    recent = [sample for sample in samples if sample[0] >= start]
    if not any(t > trigger for t, _ in recent):  # nothing has moved since the trigger
        return now - trigger >= STILL_FOR
    return all(stop.at_rest for stop in joint_stops(recent, trigger, threshold, now).values())


async def _drain(connection: ClientConnection) -> None:
    """Read what the server sends (so it never has to keep anything for us)."""
    with contextlib.suppress(websockets.ConnectionClosed):
        async for _ in connection:
            pass


async def _heartbeats(connection: ClientConnection, interval: float) -> None:
    with contextlib.suppress(websockets.ConnectionClosed):
        while True:
            await connection.send(encode(messages.heartbeat()))
            await asyncio.sleep(interval)


def run(settings: Settings) -> tuple[dict[str, list[Trial]], list[str]]:
    """Run the test (blocking); the trials per path and notes on what was left out."""
    test = EStopTest(settings)
    results = asyncio.run(test.run())
    return results, test.notes
