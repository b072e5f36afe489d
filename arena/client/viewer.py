"""`ViewerSession`: a read-only watcher of one robot."""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any, Self
from urllib.parse import quote

from arena.client.messages import ws_url
from arena.client.session import WatchingSession, running_session


class ViewerSession(WatchingSession):
    """A read-only watcher of one robot: its newest state and joint states."""

    @classmethod
    @asynccontextmanager
    async def open(cls, base_url: str, robot_id: str, **options: Any) -> AsyncIterator[Self]:
        """Run a session to `/ws/robots/{robot_id}/state` for the `async with` block."""
        session = cls(ws_url(base_url, f"/ws/robots/{quote(robot_id)}/state"), **options)
        async with running_session(session):
            yield session
