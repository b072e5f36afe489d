"""The ROS 2 bridge: one Zenoh session in rmw_zenoh's format, every robot a node on it.

Zenoh's callbacks run on Zenoh's threads. Each hands its sample or query to trio through the
trio token (`Ros2Bridge.from_zenoh`) into one bounded memory channel that the bridge's task
drains in order: a command, a service call or a token never touches a robot from a foreign
thread (specs/architecture.md, "How threads meet trio"). Beyond `BRIDGE_SIZE` items waiting,
they are dropped and counted.

What each robot's node publishes and takes is `arena.ros2.node`; the format is `wire`.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import trio

from arena.fleet.node import session_locators
from arena.protocol.errors import ArenaError, ErrorCode
from arena.robot.handoff import Handoff
from arena.ros2 import wire

if TYPE_CHECKING:
    from arena.robot.handle import Robot
    from arena.ros2.node import RobotNode

log = logging.getLogger(__name__)

#: Items from Zenoh's threads waiting for trio; beyond it they are dropped and counted.
BRIDGE_SIZE = 4096
#: Where rmw_zenoh's nodes find their router by default.
DEFAULT_ROUTER = "tcp/localhost:7447"
#: ROS_DOMAIN_ID's range.
MAX_DOMAIN = 232


@dataclass(frozen=True)
class Ros2Settings:
    """How Arena joins the ROS graph."""

    domain: int = 0
    listen: tuple[str, ...] = ()
    #: Routers or peers to connect to; with neither this nor `listen`, rmw_zenoh's router.
    connect: tuple[str, ...] = ()

    @classmethod
    def from_options(
        cls, domain: int | None, listen: tuple[str, ...], connect: tuple[str, ...]
    ) -> Ros2Settings:
        """The settings, the domain from `ROS_DOMAIN_ID` (else 0) when not given."""
        if domain is None:
            text = os.environ.get("ROS_DOMAIN_ID", "").strip() or "0"
            try:
                domain = int(text)
            except ValueError:
                raise ArenaError(
                    ErrorCode.INVALID_CONFIG, f"ROS_DOMAIN_ID is not a number: {text!r}."
                ) from None
        settings = cls(domain, listen, connect)
        settings.check()
        return settings

    def check(self) -> None:
        """Refuse a domain out of range and endpoints that are not Zenoh's."""
        if not 0 <= self.domain <= MAX_DOMAIN:
            raise ArenaError(
                ErrorCode.INVALID_CONFIG, f"A ROS domain is 0-{MAX_DOMAIN}, not {self.domain}."
            )
        for endpoint in (*self.listen, *self.connect):
            if "/" not in endpoint:
                raise ArenaError(
                    ErrorCode.INVALID_CONFIG,
                    f"{endpoint!r} is not a Zenoh endpoint (PROTOCOL/HOST:PORT, e.g. "
                    f"{DEFAULT_ROUTER}).",
                )

    def endpoints(self) -> tuple[str, ...]:
        """Where the session listens and connects (the router by default)."""
        connect = self.connect or (() if self.listen else (DEFAULT_ROUTER,))
        return (*self.listen, *connect)

    def zenoh_config(self) -> Any:
        """rmw_zenoh's session defaults: a peer, multicast scouting off, gossip on."""
        import zenoh

        connect = self.connect or (() if self.listen else (DEFAULT_ROUTER,))
        config = zenoh.Config()
        config.insert_json5("mode", '"peer"')
        config.insert_json5("listen/endpoints", json.dumps(list(self.listen)))
        config.insert_json5("connect/endpoints", json.dumps(list(connect)))
        config.insert_json5("scouting/multicast/enabled", "false")
        config.insert_json5("adminspace/enabled", "true")  # to read the ports chosen
        # Samples carry a timestamp (rmw_zenoh's default; a cache for late joiners needs it).
        config.insert_json5("timestamping/enabled", "true")
        return config


class Ros2Bridge:
    """Arena's robots as ROS 2 nodes. `run` holds the session; `follow` adds a robot."""

    def __init__(self, settings: Ros2Settings) -> None:
        self.settings = settings
        self.domain = settings.domain
        self.session: Any = None
        self.session_id = ""
        self.names = wire.NameBook()
        self.nodes: dict[str, RobotNode] = {}  # robot id -> its node
        self.started = trio.Event()
        self._next_node = 0
        self._next_entity = 0
        self._nursery: trio.Nursery | None = None
        self._waiting: list[Robot] = []
        self._handoff = Handoff(BRIDGE_SIZE, "ros2")
        self._entities: list[Any] = []

    @property
    def dropped(self) -> int:
        """Items from Zenoh's threads dropped because trio had not taken the ones before."""
        return self._handoff.dropped

    # -- life ----------------------------------------------------------------------------------

    async def run(self, *, task_status: Any = trio.TASK_STATUS_IGNORED) -> None:
        """Open the session, serve the robots until cancelled, then close it (every token goes
        with it)."""
        import zenoh

        self._handoff.open()
        try:
            self.session = await trio.to_thread.run_sync(zenoh.open, self.settings.zenoh_config())
        except zenoh.ZError as exc:
            raise ArenaError(ErrorCode.INVALID_CONFIG, f"Cannot join ROS 2: {exc}") from None
        self.session_id = str(self.session.info.zid())
        try:
            self._entities.append(
                self.session.liveliness().declare_subscriber(
                    f"{wire.ADMIN_SPACE}/{self.domain}/**",
                    self.from_zenoh(self._on_token),
                    history=True,
                )
            )
            async with trio.open_nursery() as nursery:
                self._nursery = nursery
                for robot in self._waiting:
                    self.follow(robot)
                self._waiting.clear()
                self.started.set()
                task_status.started()
                await self._handoff.serve(nursery)
        finally:
            with trio.CancelScope(shield=True):
                session, self.session = self.session, None
                await trio.to_thread.run_sync(session.close)

    def follow(self, robot: Robot) -> None:
        """Make `robot` a ROS 2 node (a `RobotManager.on_create` callback)."""
        from arena.ros2.node import RobotNode

        if self._nursery is None:
            self._waiting.append(robot)
            return
        name = self.names.take(robot.robot_id)
        if name != wire.ros_name(robot.robot_id):
            log.warning("ros2: robot %s is node /%s (its name was taken)", robot.robot_id, name)
        node = RobotNode(self, robot, name, self._new_id("node"))
        self.nodes[robot.robot_id] = node
        self._nursery.start_soon(self._serve, node)

    async def _serve(self, node: RobotNode) -> None:
        try:
            await node.run()
        except Exception:  # one robot's node failing never takes the others down
            log.exception("ros2: robot %s's node failed", node.robot.robot_id)
        finally:
            self.nodes.pop(node.robot.robot_id, None)
            self.names.release(node.robot.robot_id)

    def new_entity_id(self) -> int:
        """A fresh entity id of this session (unique across its nodes, as rmw_zenoh's)."""
        return self._new_id("entity")

    def _new_id(self, what: str) -> int:
        if what == "node":
            self._next_node += 1
            return self._next_node - 1
        self._next_entity += 1
        return self._next_entity

    async def locators(self) -> list[str]:
        """Where the session listens (the ports it was given, or chose for port 0)."""
        return await session_locators(self.session)

    # -- from Zenoh's threads -----------------------------------------------------------------

    def from_zenoh(self, handler: Callable[[Any], Any]) -> Callable[[Any], None]:
        """A Zenoh callback that hands its argument to `handler` in trio."""
        return self._handoff.callback(handler)

    def _on_token(self, sample: Any) -> Awaitable[None] | None:
        """A liveliness token came or went: a commanding publisher that went is a lost
        master."""
        if str(sample.kind).endswith("PUT"):
            return None
        key = str(sample.key_expr)
        found = wire.token_topic(key)
        if found is None or found[0] != wire.PUBLISHER:
            return None
        gid = wire.entity_gid(key)
        for node in list(self.nodes.values()):
            if node.commands_from(gid):
                return node.publisher_gone(gid, found[1])
        return None
