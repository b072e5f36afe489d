"""Shared fixtures: a robot manager, a slave that records its targets, real servers on port 0."""

from __future__ import annotations

import functools
import importlib
import inspect
import os
import struct
import subprocess
from collections.abc import AsyncIterator, Awaitable, Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import Any, NoReturn

import httpx
import pytest
import trio
import trio.testing

from arena.robot.events import SlaveNotice, SlaveTarget
from arena.robot.links import SlaveLink
from arena.robot.manager import RobotManager, open_manager
from arena.server.config import ServerConfig
from arena.server.run import run_server

# MuJoCo chooses how it renders when it is first imported: with no display, OSMesa (the physics
# twin's cameras, tests/test_gym.py), whichever test imports it first.
if "DISPLAY" not in os.environ:
    os.environ.setdefault("MUJOCO_GL", "osmesa")

#: In CI (`CI=true`) every optional extra and the shared reference data are there by design:
#: a test that cannot run there fails instead of skipping (a broken install tests nothing).
IN_CI = os.environ.get("CI", "").strip().lower() in ("true", "1", "yes")
REPOSITORY = Path(__file__).absolute().parent.parent


def missing(reason: str) -> NoReturn:
    """Call where a test (or, at module level, a test file) cannot run for want of something
    outside the code: skipped with `reason` (`make test` lists skips with theirs), failed in
    CI."""
    caller = next(f for f in inspect.stack() if f.filename != __file__)
    where = f"{Path(caller.filename).name}:{caller.lineno}"
    if IN_CI:
        pytest.fail(f"{where}: in CI, nothing may be missing: {reason}", pytrace=False)
    pytest.skip(f"{where}: {reason}", allow_module_level=True)


def write_stl(path: Path, points: Sequence[Sequence[float]]) -> None:
    """A binary STL whose triangles run through `points`, three at a time (the last point
    repeated to fill the last triangle); normals zero, as mesh readers recompute them."""
    points = [*points] + [points[-1]] * (-len(points) % 3)
    data = bytearray(80) + struct.pack("<I", len(points) // 3)
    for n in range(0, len(points), 3):
        corners = [float(c) for point in points[n : n + 3] for c in point]
        data += struct.pack("<12fH", 0.0, 0.0, 0.0, *corners, 0)
    path.write_bytes(bytes(data))


def need(module: str, extra: str) -> ModuleType:
    """Import `module` of the optional extra `extra` for a test: see `missing`."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        missing(f"needs {module} ({exc}): pip install 'arena[{extra}]'")


async def eventually(
    check: Callable[[], bool | Awaitable[bool]], timeout: float = 30.0, what: str = "condition"
) -> None:
    """Wait until `check()` holds (it may be async, such as a question to a server); fail the
    test after `timeout` seconds (a deadline only a broken feature reaches, never a slow
    machine). The one waiting helper of the tests.

    It polls on trio's clock (`trio.sleep`), so under `MockClock(autojump_threshold=0)` it
    takes no real time and its deadline is virtual. Wait for an event instead where there is
    one to wait for (`trio.Event`, a session's `wait_for`, the next message).
    """
    with trio.move_on_after(timeout):
        while True:
            held = check()
            if inspect.isawaitable(held):
                held = await held
            if held:
                return
            await trio.sleep(0.01)
    raise AssertionError(f"timed out waiting for {what}")


def shared_dir() -> Path | None:
    """The `shared/` folder beside the repository (reference data, the benchmark's floor):
    `ARENA_SHARED` if set, else beside this checkout (as it was reached, and with symlinks
    resolved), else beside the main checkout of a git worktree."""
    candidates = []
    if os.environ.get("ARENA_SHARED"):
        candidates.append(Path(os.environ["ARENA_SHARED"]))
    candidates += [REPOSITORY.parent / "shared", REPOSITORY.resolve().parent / "shared"]
    try:
        common = subprocess.run(
            ["git", "rev-parse", "--path-format=absolute", "--git-common-dir"],
            cwd=REPOSITORY,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
        candidates.append(Path(common).parent.parent / "shared")  # main/.git -> shared
    except (OSError, subprocess.CalledProcessError):
        pass
    return next((path for path in candidates if path.is_dir()), None)


@pytest.fixture
async def manager() -> AsyncIterator[RobotManager]:
    """A robot manager. Tests take `autojump_clock` too, so that its time is virtual."""
    async with open_manager() as opened:
        yield opened


#: Under mutation testing only: a test on the mock clock that has run this many virtual seconds
#: has hung (a mutant that never sends the event the test waits for, while ticks and heartbeats
#: keep the clock jumping). It fails at once instead of holding the run until mutmut's
#: wall-clock bound. No test here needs more than a few minutes of virtual time.
MUTANT_VIRTUAL_LIMIT = 3600.0
#: The same for a test on the real clock (sockets, Zenoh, a simulated bus): none needs as long.
MUTANT_REAL_LIMIT = 120.0


class _HungTest(Exception):
    """A test ran past its bound under a mutant."""


def _bounded(
    test: Callable[..., Awaitable[None]], seconds: float
) -> Callable[..., Awaitable[None]]:
    @functools.wraps(test)
    async def bounded(**kwargs: Any) -> None:
        try:
            with trio.fail_after(seconds):
                await test(**kwargs)
        except trio.TooSlowError:
            raise _HungTest(f"past {seconds} s of its clock: hung under a mutant") from None

    return bounded


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Under a mutant (mutmut sets MUTANT_UNDER_TEST to its name), every async test fails past
    MUTANT_VIRTUAL_LIMIT seconds of the mock clock, or MUTANT_REAL_LIMIT of the real one; tests
    marked `real_io` wait for a thread or a process on the mock clock, which jumps on
    meanwhile: they are left to mutmut's own bound."""
    if "__mutmut_" not in os.environ.get("MUTANT_UNDER_TEST", ""):
        return
    for item in items:
        if not isinstance(item, pytest.Function) or not inspect.iscoroutinefunction(item.obj):
            continue
        if item.get_closest_marker("real_io"):
            continue
        virtual = {"autojump_clock", "mock_clock"} & set(item.fixturenames)
        limit = MUTANT_VIRTUAL_LIMIT if virtual else MUTANT_REAL_LIMIT
        item.obj = _bounded(item.obj, limit)


@dataclass
class RecordingSlave:
    """A slave driver that keeps every target and notice it takes, with trio times."""

    kind: str = "recording-slave"
    measures: bool = False  # reports what it is told: a twin
    targets: list[tuple[float, dict[str, float]]] = field(default_factory=list)
    notices: list[tuple[float, SlaveNotice]] = field(default_factory=list)
    fail_after: int | None = None  # raise after this many targets (a crashing driver)

    async def run(self, link: SlaveLink) -> None:
        async for message in link.messages():
            if isinstance(message, SlaveTarget):
                self.targets.append((trio.current_time(), dict(message.joints)))
                if self.fail_after is not None and len(self.targets) >= self.fail_after:
                    raise RuntimeError("simulated driver crash")
                await link.report_joint_states(message.joints)
            else:
                self.notices.append((trio.current_time(), message))


@dataclass
class RunningServer:
    """A real Arena server on 127.0.0.1 with a port the system chose."""

    app: Any
    url: str
    stop: trio.Event
    done: trio.Event

    @property
    def ws_url(self) -> str:
        return "ws" + self.url[len("http") :]

    def client(self, **kwargs: Any) -> httpx.AsyncClient:
        return httpx.AsyncClient(base_url=self.url, timeout=10, **kwargs)


@pytest.fixture
async def start_server(
    nursery: trio.Nursery, tmp_path: Path
) -> AsyncIterator[Callable[..., Awaitable[RunningServer]]]:
    """Start servers with settings of the test's choosing; each stops when the test ends.

    Recordings go to the test's own folder unless the test says otherwise.
    """
    started: list[RunningServer] = []

    async def start(**settings: Any) -> RunningServer:
        settings.setdefault("recordings_dir", str(tmp_path / "recordings"))
        settings.setdefault("port", 0)  # a restarted server may ask for its old port
        # A loaded machine can stall a test's process between two requests on one connection
        # longer than the default 5 s, and the server then closes it under the second (CI:
        # "Server disconnected without sending a response"); the timeout's tests set theirs.
        settings.setdefault("keep_alive_timeout", 60.0)
        config = ServerConfig(**settings)
        stop, done = trio.Event(), trio.Event()

        async def run(task_status: trio.TaskStatus[Any]) -> None:
            try:
                await run_server(config, stop=stop, task_status=task_status)
            finally:
                done.set()

        app, urls = await nursery.start(run)
        server = RunningServer(app, urls[0], stop, done)
        started.append(server)
        return server

    yield start
    for server in started:
        server.stop.set()
    with trio.move_on_after(5):
        for server in started:
            await server.done.wait()


@pytest.fixture
async def server(start_server: Callable[..., Awaitable[RunningServer]]) -> RunningServer:
    """A server with the demo robot `demo-arm` (a mock slave attached)."""
    return await start_server(demo=True)
