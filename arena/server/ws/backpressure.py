"""What a peer that does not read gets: the newest states, and a count of what it missed.

`send` never waits, so a reader answering its peer never stalls on that peer. Once the peer
has let the transport's `high_water` bytes pile up, states and joint states keep only the
newest of each, and acks, errors, heartbeats and faults are dropped and counted (a viewer that
was behind reads a robot's faults that last in its details); when the peer has
read what was queued, it gets one `missed` message with the counts, then the newest states.
Messages that must not be dropped (a slave's targets) go through `send_in_turn`, which waits
for room in the writer task that sends them.
"""

from __future__ import annotations

import collections
from typing import NamedTuple, Protocol

import msgspec
import trio

from arena.protocol import messages as wire
from arena.protocol.ws_frames import UpgradeRequest
from arena.server.metrics import Metrics


class PeerSocket(Protocol):
    """What a connection needs of its socket: a `ws_transport.WebSocket`, or the robot's
    node's end of a fleet tunnel (`fleet.tunnel.TunnelSocket`)."""

    request: UpgradeRequest
    close_sent: bool

    @property
    def backlogged(self) -> bool:
        """More than the high-water mark waits for the peer."""
        ...

    @property
    def queued_bytes(self) -> int:
        """Bytes waiting for the peer to read."""
        ...

    async def receive(self) -> str | bytes:
        """The next message; raises `WebSocketClosed` once the peer has closed."""
        ...

    def next_in_hand(self) -> str | bytes | None:
        """The next message if one is in hand already."""
        ...

    def holds_more(self) -> bool:
        """True when more frames are in hand."""
        ...

    def offer(self, *texts: str, whole: bool = False) -> bool:
        """Send now if there is room; False (nothing sent) if not."""
        ...

    async def send(self, *texts: str) -> None:
        """Send, waiting for room."""
        ...

    def send_nowait(self, text: str) -> None:
        """Queue whatever the backlog."""
        ...

    def send_now(self, *texts: str) -> bool:
        """Write at once if the socket is idle; False (nothing sent) if not."""
        ...

    def close_nowait(self, code: int, reason: str = "") -> None:
        """Send the close frame."""
        ...

    async def wait_drained(self) -> None:
        """Wait until the peer has read what was queued."""
        ...


class Encoded(NamedTuple):
    """A message encoded already, with its kind: `ack`, `error`, `heartbeat`, `state` or
    `joint_states`, the last two optionally `:<robot id>` (a group master hears from several)."""

    kind: str
    text: str


Outgoing = msgspec.Struct | Encoded

#: Kinds of which a peer that is behind gets only the newest, once it reads again.
LATEST_KINDS = frozenset({"state", "joint_states"})
#: Kinds that a peer that is behind misses (counted in the `missed` message).
DROPPED_KINDS = frozenset({"ack", "error", "heartbeat", "fault"})
_KIND_OF: dict[type, str] = {
    wire.StateMessage: "state",
    wire.JointStatesOut: "joint_states",
    wire.AckMessage: "ack",
    wire.GroupAckMessage: "ack",
    wire.ErrorMessage: "error",
    wire.HeartbeatMessage: "heartbeat",
    wire.FaultMessage: "fault",
}


class LatestWins:
    """The sending half of a connection, with the policy above. (A base class rather than an
    object of its own: `send` runs for every message out, and an attribute less is a lookup
    less.)"""

    def __init__(self, ws: PeerSocket, metrics: Metrics) -> None:
        self.ws = ws
        self.metrics = metrics
        self._ended = trio.Event()
        self._held: dict[str, str] = {}  # the newest text of each latest-only kind
        self._missed: collections.Counter[str] = collections.Counter()
        self._behind = trio.Event()  # set while something is held or missed

    async def send(self, *messages: Outgoing, whole: bool = False) -> None:
        """Send messages in one write (a struct is encoded as JSON); never waits. `whole`:
        they answer every frame the reader took together (see `WebSocket.offer`)."""
        if self._held or self._missed:
            self._catch_up()
        texts = [m.text if isinstance(m, Encoded) else wire.encode(m) for m in messages]
        if not (self._held or self._missed) and self.ws.offer(*texts, whole=whole):
            self._note_closed()
            return
        for message, text in zip(messages, texts, strict=True):
            kind = message.kind if isinstance(message, Encoded) else _KIND_OF.get(type(message))
            self._keep(kind, text)

    async def send_in_turn(self, message: msgspec.Struct) -> None:
        """Send a message that must not be dropped, first waiting while the peer is behind."""
        await self.ws.send(wire.encode(message))
        self._note_closed()

    def send_now(self, message: msgspec.Struct) -> bool:
        """Write a message at once if the socket is idle; False (nothing sent) if it is not."""
        if not self.ws.send_now(wire.encode(message)):
            return False
        self._note_closed()
        return True

    @property
    def queued_bytes(self) -> int:
        """Bytes waiting for the peer to read."""
        return self.ws.queued_bytes

    def _keep(self, kind: str | None, text: str) -> None:
        """A message for a peer that is behind: keep the newest of its kind, or count it."""
        base = kind.partition(":")[0] if kind else ""
        if base in LATEST_KINDS:
            assert kind is not None
            missed = self._held.pop(kind, None) is not None  # superseded by this one
            self._held[kind] = text
        elif base in DROPPED_KINDS:
            missed = True
        else:  # rare and small (a detach notice): queued whatever the backlog
            self.ws.send_nowait(text)
            return
        if missed:
            self._missed[base] += 1
            self.metrics.dropped[base] += 1
        self._behind.set()

    def _catch_up(self) -> None:
        """If the peer has room again: the `missed` counts, then the newest states."""
        if self.ws.backlogged or not (self._held or self._missed):
            return
        texts = []
        if self._missed:
            missed = wire.MissedData(**{k: self._missed[k] for k in self._missed})
            texts.append(wire.encode(wire.MissedMessage(timestamp=wire.now_iso(), data=missed)))
        texts.extend(self._held.values())
        self._held.clear()
        self._missed.clear()
        self._behind = trio.Event()
        self.ws.offer(*texts)
        self._note_closed()

    async def catch_up_when_read(self) -> None:
        """Run beside the connection: catch up each time a peer that was behind has read."""
        while not self.ws.close_sent:
            await self._behind.wait()
            await self.ws.wait_drained()
            self._catch_up()

    def _note_closed(self) -> None:
        if self.ws.close_sent:  # the transport closed (protocol error, or the peer is gone)
            self._ended.set()
