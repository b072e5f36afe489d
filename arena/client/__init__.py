"""A Python client for Arena servers: REST helpers and WebSocket sessions that reconnect.

REST: `Arena` (blocking, for plain scripts) and `AsyncArena` (for trio code) offer the same
methods. WebSockets (trio): `MasterSession`, `SlaveSession` and `ViewerSession` hold one
endpoint open, reconnect with exponential backoff and jitter, and send heartbeats. A plain
script runs its session code with `trio.run(main)`; see the README's agent example.

    async def main() -> None:
        async with MasterSession.open("http://127.0.0.1:8080", "arm-1") as master:
            ack = await master.command({"Rotation": 30})

Every call ends: what the server refuses raises `Refused` (with its `code` and `message`), a
wait that runs out raises `ClientTimeout`, a dropped link `Disconnected`; all three are
`ArenaClientError`s. A master session that ends normally releases the robot (`idle`; the
commands it accepted complete); one that ends with an exception leaves without a word, and the
server applies its loss policy (an e-stop by default).

The modules: `errors` (the exceptions), `messages` (URLs and the messages a client sends, made
with the protocol's own structs), `session` (one WebSocket held open: `Session`, `Backoff`),
`master`, `slave` and `viewer` (the three endpoints), `rest` (`Arena`, `AsyncArena`), and
`handshake` (the WebSocket opening handshake without I/O, for clients that own their socket).
"""

from arena.client.errors import ArenaClientError, ClientTimeout, Disconnected, Refused
from arena.client.master import MasterSession
from arena.client.messages import (
    command_message,
    finite_joints,
    joint_states_message,
    now_iso,
    ws_url,
)
from arena.client.rest import Arena, AsyncArena
from arena.client.session import HOPELESS_CLOSES, Backoff, Session, WatchingSession
from arena.client.slave import SlaveSession
from arena.client.viewer import ViewerSession

__all__ = [
    "HOPELESS_CLOSES",
    "Arena",
    "ArenaClientError",
    "AsyncArena",
    "Backoff",
    "ClientTimeout",
    "Disconnected",
    "MasterSession",
    "Refused",
    "Session",
    "SlaveSession",
    "ViewerSession",
    "WatchingSession",
    "command_message",
    "finite_joints",
    "joint_states_message",
    "now_iso",
    "ws_url",
]
