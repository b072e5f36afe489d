"""`SlaveSession`: a slave of one robot, taking its targets and reporting its joints."""

from __future__ import annotations

from collections import deque
from collections.abc import AsyncIterator, Awaitable, Callable, Mapping
from contextlib import asynccontextmanager
from typing import Any, Self
from urllib.parse import quote

from arena.client import messages
from arena.client.messages import ws_url
from arena.client.session import Session, running_session


class SlaveSession(Session):
    """A slave of one robot: `on_target` gets each `execute_command` as {joint: degrees}."""

    def __init__(
        self,
        url: str,
        on_target: Callable[[dict[str, float]], Awaitable[None]] | None = None,
        **options: Any,
    ) -> None:
        super().__init__(url, **options)
        self.on_target = on_target
        self.notices: deque[str] = deque(maxlen=64)
        self.targets = 0

    @classmethod
    @asynccontextmanager
    async def open(
        cls,
        base_url: str,
        robot_id: str,
        on_target: Callable[[dict[str, float]], Awaitable[None]] | None = None,
        *,
        slave_id: str | None = None,
        **options: Any,
    ) -> AsyncIterator[Self]:
        """Run a session to `/ws/slave/{robot_id}` for the `async with` block, connected."""
        url = ws_url(base_url, f"/ws/slave/{quote(robot_id)}", id=slave_id or "")
        session = cls(url, on_target, **options)
        async with running_session(session):
            yield session

    async def report(self, joints: Mapping[str, float]) -> None:
        """Report real joint values in degrees."""
        await self.send(messages.joint_states(joints))

    async def on_message(self, message: dict[str, Any]) -> None:
        kind = message.get("type")
        if kind == "execute_command":
            self.targets += 1
            joints = {j["name"]: float(j["value"]) for j in message["data"]["joints"]}
            if self.on_target is not None:
                await self.on_target(joints)
        elif isinstance(kind, str) and kind != "heartbeat":
            self.notices.append(kind)
