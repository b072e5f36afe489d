"""Shared fixtures: a robot manager, a slave that records its targets, real servers on port 0."""

from __future__ import annotations

from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import pytest
import trio

from arena.robot.events import SlaveNotice, SlaveTarget
from arena.robot.links import SlaveLink
from arena.robot.manager import RobotManager, open_manager
from arena.server.config import ServerConfig
from arena.server.run import run_server


@pytest.fixture
async def manager() -> AsyncIterator[RobotManager]:
    """A robot manager. Tests take `autojump_clock` too, so that its time is virtual."""
    async with open_manager() as opened:
        yield opened


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
