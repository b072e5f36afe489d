"""One Arena node of a fleet: its Zenoh session, what it knows of the others, and tunnels.

Zenoh's callbacks run on Zenoh's threads. Each one only hands its sample or query to trio
through the trio token (`_Bridge.post`), into a bounded memory channel; everything that
touches a robot or the node's tables then runs in trio, in order. Queries are answered from
trio too (Zenoh lets a query be replied to from any thread while the `Query` lives; it is
finished when dropped).

What the node knows of the fleet comes from liveliness: a token per node and per robot. A node
that dies loses its tokens when its session's lease runs out (`lease_ms`, 1 s by default, so
the others see it within about 2 s); its robots then show `offline` until it returns.
"""

from __future__ import annotations

import contextlib
import json
import logging
import secrets
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from functools import partial
from typing import Any

import trio

import arena
from arena.fleet import keys
from arena.protocol.errors import ArenaError, ErrorCode
from arena.robot.handoff import Handoff

log = logging.getLogger(__name__)

#: Items from Zenoh's threads waiting for trio; beyond it they are dropped and counted.
BRIDGE_SIZE = 4096
#: Messages of one tunnel waiting for trio (the tunnel's reader drops the oldest past it).
TUNNEL_QUEUE = 1024
#: How long a fleet e-stop waits for every live node.
ESTOP_TIMEOUT = 0.1
#: How long listing or asking another node waits.
QUERY_TIMEOUT = 1.0


@dataclass(frozen=True)
class FleetSettings:
    """How a node joins its fleet."""

    node: str
    fleet: str = "default"
    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    scout: bool = False  # multicast scouting (off: explicit endpoints only)
    lease_ms: int = 1000  # a node silent this long is gone
    #: A Zenoh configuration file (JSON5) to start from: TLS certificates, access control,
    #: anything Zenoh offers. The settings above are applied on top of it.
    zenoh_config_file: str | None = None

    def check(self) -> None:
        """Refuse names that cannot be key chunks, and a node that cannot be reached."""
        for what, name in (("node", self.node), ("fleet", self.fleet)):
            if not keys.NAME.match(name):
                raise ArenaError(
                    ErrorCode.INVALID_CONFIG,
                    f"A {what} name is 1-64 letters, digits, '_' or '-': {name!r} is not.",
                )
        for endpoint in (*self.listen, *self.connect):
            if "/" not in endpoint:
                raise ArenaError(
                    ErrorCode.INVALID_CONFIG,
                    f"{endpoint!r} is not a Zenoh endpoint (PROTOCOL/HOST:PORT, e.g. "
                    "tcp/127.0.0.1:7447).",
                )
        if not 100 <= self.lease_ms <= 60_000:
            raise ArenaError(ErrorCode.INVALID_CONFIG, "fleet lease must be 100-60000 ms.")

    def zenoh_config(self) -> Any:
        """The Zenoh configuration: peer mode, these endpoints, scouting as asked."""
        import zenoh

        if self.zenoh_config_file:
            try:
                config = zenoh.Config.from_file(self.zenoh_config_file)
            except (OSError, zenoh.ZError) as exc:
                raise ArenaError(
                    ErrorCode.INVALID_CONFIG,
                    f"Cannot read the Zenoh configuration {self.zenoh_config_file}: {exc}",
                ) from None
        else:
            config = zenoh.Config()
        config.insert_json5("mode", '"peer"')
        config.insert_json5("listen/endpoints", json.dumps(list(self.listen)))
        config.insert_json5("connect/endpoints", json.dumps(list(self.connect)))
        scout = "true" if self.scout else "false"
        config.insert_json5("scouting/multicast/enabled", scout)
        config.insert_json5("transport/link/tx/lease", str(self.lease_ms))
        config.insert_json5("transport/link/tx/keep_alive", "4")
        config.insert_json5("adminspace/enabled", "true")  # to read the ports chosen
        return config


@dataclass
class NodeView:
    """What this node knows of one node of the fleet."""

    name: str
    alive: bool
    version: str | None = None
    robots: list[dict[str, Any]] = field(default_factory=list)  # last known
    locators: list[str] = field(default_factory=list)
    http: str | None = None  # the node's own URL, for clients that want to go direct

    def update(self, info: dict[str, Any]) -> None:
        """Take what the node said of itself (its `info` answer)."""
        self.version = info.get("version")
        self.robots = list(info.get("robots", []))
        self.locators = list(info.get("locators", []))
        self.http = info.get("http")


class Tunnel:
    """A pipe of messages between two nodes (a WebSocket carried over Zenoh)."""

    def __init__(self, node: FleetNode, tunnel_id: str, send_key: str, peer: str) -> None:
        self.node = node
        self.tunnel_id = tunnel_id
        self.peer = peer  # the node at the other end
        self._send_key = send_key
        self._inbox_send, self.inbox = trio.open_memory_channel[bytes](TUNNEL_QUEUE)
        self.dropped = 0
        self.closed = False
        self._publisher: Any = None
        self._subscriber: Any = None

    def deliver(self, data: bytes) -> None:
        """In trio: a message from the other end (dropped and counted if the reader lags)."""
        try:
            self._inbox_send.send_nowait(data)
        except trio.WouldBlock:
            self.dropped += 1
        except trio.ClosedResourceError:
            pass

    def send(self, data: bytes) -> None:
        """Send a message to the other end (never waits)."""
        if not self.closed and self._publisher is not None:
            self._publisher.put(data)

    def close(self) -> None:
        """Stop receiving; the subscription is undeclared."""
        if self.closed:
            return
        self.closed = True
        self._inbox_send.close()
        for entity in (self._subscriber, self._publisher):
            if entity is not None:
                with contextlib.suppress(Exception):
                    entity.undeclare()
        self.node.tunnels.pop(self.tunnel_id, None)


#: A service of this node: given the query's payload, its answer (JSON-able) or `ArenaError`.
Service = Callable[[bytes], Awaitable[Any]]


async def session_locators(session: Any) -> list[str]:
    """Where a Zenoh session listens (the ports it was given, or chose for port 0); [] without
    a session. Asked of Zenoh's admin space in a thread: the call blocks."""
    if session is None:
        return []

    def read() -> list[str]:
        zid = str(session.info.zid())
        for reply in session.get(f"@/{zid}/peer", timeout=1.0):
            if reply.ok is not None:
                return list(json.loads(reply.ok.payload.to_bytes()).get("locators", []))
        return []

    return await trio.to_thread.run_sync(read)


class FleetNode:
    """This node's membership of the fleet. `run` holds the session."""

    def __init__(self, settings: FleetSettings) -> None:
        self.settings = settings
        self.name = settings.node
        self.fleet = settings.fleet
        self.session: Any = None
        self.nodes: dict[str, NodeView] = {}
        #: robot id -> the live node that owns it (from the robots' liveliness tokens)
        self.robot_nodes: dict[str, str] = {}
        self.tunnels: dict[str, Tunnel] = {}
        self.services: dict[str, Service] = {}
        #: Called in trio with a node's name when it is seen gone (its tunnels end).
        self.on_node_lost: list[Callable[[str], None]] = []
        #: Called in trio with (node, robot id, state JSON) for another node's state changes.
        self.on_remote_state: list[Callable[[str, str, dict[str, Any]], None]] = []
        self.started = trio.Event()
        #: Where the node's own tasks run (tunnels served here live in it).
        self.nursery: trio.Nursery | None = None
        self._token: trio.lowlevel.TrioToken | None = None
        self._handoff = Handoff(BRIDGE_SIZE, "fleet")
        self._entities: list[Any] = []
        self._robot_tokens: dict[str, Any] = {}
        self._state_publishers: dict[str, Any] = {}

    @property
    def dropped(self) -> int:
        """Items from Zenoh's threads dropped because trio had not taken the ones before."""
        return self._handoff.dropped

    # -- life -----------------------------------------------------------------------------

    async def run(self, *, task_status: Any = trio.TASK_STATUS_IGNORED) -> None:
        """Join the fleet, serve it until cancelled, then leave (tokens go with the session)."""
        import zenoh

        self._token = trio.lowlevel.current_trio_token()
        self._handoff.open()
        try:
            self.session = await trio.to_thread.run_sync(zenoh.open, self.settings.zenoh_config())
        except zenoh.ZError as exc:
            raise ArenaError(ErrorCode.INVALID_CONFIG, f"Cannot join the fleet: {exc}") from None
        try:
            self.nodes[self.name] = NodeView(self.name, True, arena.__version__)
            self._declare()
            async with trio.open_nursery() as nursery:
                self.nursery = nursery
                self.started.set()
                task_status.started()
                await self._handoff.serve(nursery)
        finally:
            with trio.CancelScope(shield=True):
                for tunnel in list(self.tunnels.values()):
                    tunnel.close()
                session, self.session = self.session, None
                await trio.to_thread.run_sync(session.close)

    def _declare(self) -> None:
        session, fleet = self.session, self.fleet
        liveliness = session.liveliness()
        self._entities.append(liveliness.declare_token(keys.node_alive(fleet, self.name)))
        self._entities.append(
            liveliness.declare_subscriber(
                keys.node_alive(fleet), self._from_zenoh(self._on_node_token), history=True
            )
        )
        self._entities.append(
            liveliness.declare_subscriber(
                keys.robot_alive(fleet), self._from_zenoh(self._on_robot_token), history=True
            )
        )
        self._entities.append(
            session.declare_subscriber(
                keys.robot_state(fleet), self._from_zenoh(self._on_state_sample)
            )
        )
        for name in ("info", "estop", "http", "tunnel"):
            self._entities.append(
                session.declare_queryable(
                    keys.service(fleet, self.name, name),
                    self._from_zenoh(partial(self._answer, name)),
                )
            )

    # -- the bridge from Zenoh's threads ------------------------------------------------------

    def _from_zenoh(self, handler: Callable[[Any], Any]) -> Callable[[Any], None]:
        """A Zenoh callback that hands its argument to `handler` in trio."""
        return self._handoff.callback(handler)

    # -- what the others tell us --------------------------------------------------------------

    def _on_node_token(self, sample: Any) -> Awaitable[None] | None:
        name = keys.parse(str(sample.key_expr))[0]
        alive = str(sample.kind).endswith("PUT")
        view = self.nodes.setdefault(name, NodeView(name, alive))
        view.alive = alive
        if alive:
            log.info("fleet: node %s is here", name)
            return self._refresh(name)
        log.warning("fleet: node %s is gone", name)
        for robot, owner in list(self.robot_nodes.items()):
            if owner == name:
                del self.robot_nodes[robot]
        for tunnel in list(self.tunnels.values()):
            if tunnel.peer == name:
                tunnel.deliver(b"")  # the end: the tunnel's reader closes its client
        for callback in self.on_node_lost:
            callback(name)
        return None

    async def _refresh(self, name: str) -> None:
        with contextlib.suppress(ArenaError):
            await self.info(name)

    def _on_robot_token(self, sample: Any) -> None:
        parts = keys.parse(str(sample.key_expr))  # node, "robots", id, "alive"
        node, robot = parts[0], parts[2]
        if str(sample.kind).endswith("PUT"):
            self.robot_nodes[robot] = node
        elif self.robot_nodes.get(robot) == node:
            del self.robot_nodes[robot]

    def _on_state_sample(self, sample: Any) -> None:
        parts = keys.parse(str(sample.key_expr))
        node, robot = parts[0], parts[2]
        if node == self.name:
            return
        try:
            state = json.loads(sample.payload.to_bytes())
        except ValueError:
            return
        view = self.nodes.get(node)
        if view is not None:
            for entry in view.robots:
                if entry.get("id") == robot:
                    entry["state"] = state.get("mode", entry.get("state"))
                    entry["estop_reason"] = state.get("estop_reason")
        for callback in self.on_remote_state:
            callback(node, robot, state)

    # -- serving the others -------------------------------------------------------------------

    async def _answer(self, name: str, query: Any) -> None:
        service = self.services.get(name)
        payload = query.payload.to_bytes() if query.payload is not None else b""
        key = keys.service(self.fleet, self.name, name)  # who answers: the asker reads it
        try:
            if service is None:
                raise ArenaError(ErrorCode.NOT_FOUND, f"Node {self.name} offers no {name}.")
            answer = await service(payload)
            body = {"ok": answer}
        except ArenaError as error:
            body = {"error": {"code": str(error.code), "message": error.message}}
        except Exception as exc:  # a bug: said, and the asker still gets an answer
            log.exception("fleet: %s failed", name)
            body = {"error": {"code": str(ErrorCode.INTERNAL_ERROR), "message": str(exc)}}
        with contextlib.suppress(Exception):  # the asker may have given up
            query.reply(key, json.dumps(body).encode())
        del query

    # -- asking the others --------------------------------------------------------------------

    async def ask(
        self, node: str, name: str, payload: Any = None, timeout: float = QUERY_TIMEOUT
    ) -> Any:
        """One node's answer to a service; `ArenaError` with its code if it refused, or
        NODE_LOST if it did not answer."""
        answers = await self.ask_all(name, payload, timeout, node=node)
        if node not in answers:
            raise ArenaError(ErrorCode.NODE_LOST, f"Node {node!r} did not answer.")
        answer = answers[node][0]
        if "error" in answer:
            raise ArenaError(ErrorCode(answer["error"]["code"]), answer["error"]["message"])
        return answer["ok"]

    async def ask_all(
        self, name: str, payload: Any = None, timeout: float = QUERY_TIMEOUT, node: str = "*"
    ) -> dict[str, tuple[dict[str, Any], float]]:
        """Every node's answer (`node` narrows it) with its time in seconds, within
        `timeout`."""
        import zenoh

        selector = keys.service(self.fleet, node, name)
        data = json.dumps(payload).encode()
        session = self.session
        if session is None:
            raise ArenaError(ErrorCode.NODE_LOST, "This node has left the fleet.")

        def gather() -> dict[str, tuple[dict[str, Any], float]]:
            start = time.perf_counter()
            found: dict[str, tuple[dict[str, Any], float]] = {}
            replies = session.get(
                selector,
                payload=data,
                timeout=timeout,
                target=zenoh.QueryTarget.ALL,
                consolidation=zenoh.ConsolidationMode.NONE,
            )
            for reply in replies:
                if reply.ok is None:
                    continue
                sender = keys.parse(str(reply.ok.key_expr))[0]
                with contextlib.suppress(ValueError):
                    found[sender] = (
                        json.loads(reply.ok.payload.to_bytes()),
                        time.perf_counter() - start,
                    )
            return found

        return await trio.to_thread.run_sync(gather)

    async def info(self, node: str) -> NodeView:
        """Ask a node about itself (and remember the answer)."""
        answer = await self.ask(node, "info")
        view = self.nodes.setdefault(node, NodeView(node, True))
        view.update(answer)
        return view

    async def refresh_all(self) -> None:
        """Ask every live node about itself at once."""
        answers = await self.ask_all("info")
        for name, (answer, _) in answers.items():
            if "ok" not in answer:
                continue
            self.nodes.setdefault(name, NodeView(name, True)).update(answer["ok"])

    async def locators(self) -> list[str]:
        """Where this node listens (the ports it was given, or chose for port 0)."""
        return await session_locators(self.session)

    def owner_of(self, robot_id: str) -> str | None:
        """The node of the fleet that owns `robot_id` (this one's name for its own), None if
        no node ever said it had it. NODE_LOST when the node that had it is gone and no live
        node has it now: its robots are listed `offline`, and a call for one says so (rather
        than "no such robot") and which node to bring back."""
        node = self.robot_nodes.get(robot_id)
        if node is not None:
            return node
        for view in self.nodes.values():
            if not view.alive and any(robot.get("id") == robot_id for robot in view.robots):
                raise ArenaError(
                    ErrorCode.NODE_LOST,
                    f"Robot {robot_id!r} is on node {view.name!r}, which has left the fleet: "
                    "it is back when that node is.",
                )
        return None

    # -- this node's robots --------------------------------------------------------------------

    def robot_added(self, robot_id: str) -> None:
        """Declare that this node owns `robot_id` (its liveliness token)."""
        if self.session is None:
            return
        key = keys.robot_alive(self.fleet, self.name, robot_id)
        self._robot_tokens[robot_id] = self.session.liveliness().declare_token(key)
        self._state_publishers[robot_id] = self.session.declare_publisher(
            keys.robot_state(self.fleet, self.name, robot_id)
        )
        self.robot_nodes[robot_id] = self.name

    def robot_removed(self, robot_id: str) -> None:
        """The robot is gone: its token and publisher go too."""
        for table in (self._robot_tokens, self._state_publishers):
            entity = table.pop(robot_id, None)
            if entity is not None:
                with contextlib.suppress(Exception):
                    entity.undeclare()
        if self.robot_nodes.get(robot_id) == self.name:
            del self.robot_nodes[robot_id]

    def publish_state(self, robot_id: str, state: bytes) -> None:
        """Tell the fleet about a state change of one of this node's robots."""
        publisher = self._state_publishers.get(robot_id)
        if publisher is not None:
            publisher.put(state)

    async def owner_elsewhere(self, robot_id: str) -> str | None:
        """The other live node that owns `robot_id`, asking the fleet's tokens afresh."""
        session = self.session
        if session is None:
            return None

        def tokens() -> list[str]:
            key = keys.robot_alive(self.fleet, "*", robot_id)
            return [
                keys.parse(str(reply.ok.key_expr))[0]
                for reply in session.liveliness().get(key, timeout=QUERY_TIMEOUT)
                if reply.ok is not None
            ]

        owners = [node for node in await trio.to_thread.run_sync(tokens) if node != self.name]
        return owners[0] if owners else None

    # -- tunnels -----------------------------------------------------------------------------

    def open_tunnel(self, peer: str, tunnel_id: str | None = None, *, serving: bool) -> Tunnel:
        """A tunnel with `peer`: the client's end (`serving` False: sends on `in` at the
        peer, hears on `out` here) or the robot's end (sends on `out` at the peer)."""
        assert self.session is not None
        tunnel_id = tunnel_id or secrets.token_hex(8)
        if serving:
            send_key = keys.tunnel(self.fleet, peer, tunnel_id, "out")
            hear_key = keys.tunnel(self.fleet, self.name, tunnel_id, "in")
        else:
            send_key = keys.tunnel(self.fleet, peer, tunnel_id, "in")
            hear_key = keys.tunnel(self.fleet, self.name, tunnel_id, "out")
        tunnel = Tunnel(self, tunnel_id, send_key, peer)
        token = self._token
        assert token is not None

        def heard(sample: Any) -> None:
            data = sample.payload.to_bytes()
            with contextlib.suppress(trio.RunFinishedError):
                token.run_sync_soon(tunnel.deliver, data)

        import zenoh

        tunnel._subscriber = self.session.declare_subscriber(hear_key, heard)
        # Never BLOCK: a put happens on trio's thread, and a congested peer must not stall
        # the node; what Zenoh drops then shows as a missing acknowledgment.
        tunnel._publisher = self.session.declare_publisher(
            send_key, congestion_control=zenoh.CongestionControl.DROP
        )
        self.tunnels[tunnel_id] = tunnel
        return tunnel
