"""What arrives on a robot actor's inbox: one message type per kind of request, and the
reply a caller waits on. Only the robot handle, the actor and the links make them."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Generic, Protocol, TypeVar

import trio

from arena.protocol.errors import Severity
from arena.robot import safety
from arena.robot.episodes import Episode
from arena.robot.motion import Command, CommandResult
from arena.robot.peers import MasterPeer, SlavePeer
from arena.robot.workspace import Workspace

R = TypeVar("R")


class Driver(Protocol):
    """A master or slave driver as the actor runs it (`arena.robot.links.MasterDriver` and
    `SlaveDriver` say what each is given)."""

    kind: str

    async def run(self, link: Any) -> None:
        """Run until done, through `link`."""


class Reply(Generic[R]):
    """A one-shot answer from the actor to a waiting caller."""

    __slots__ = ("_done", "_error", "_value")

    def __init__(self) -> None:
        self._done = trio.Event()
        self._value: R | None = None
        self._error: BaseException | None = None

    def set(self, value: R) -> None:
        self._value = value
        self._done.set()

    def fail(self, error: BaseException) -> None:
        self._error = error
        self._done.set()

    async def wait(self) -> R:
        await self._done.wait()
        if self._error is not None:
            raise self._error
        return self._value  # type: ignore[return-value]


@dataclass(slots=True)
class CommandMsg:
    source: str | None
    command: Command
    reply: Reply[CommandResult] | None
    in_burst: bool = False  # more commands of its master are in hand (see `RobotCore.command`)


@dataclass(slots=True)
class EventMsg:
    event: safety.Event
    reply: Reply[safety.Outcome] | None


@dataclass(slots=True)
class AttachMsg:
    role: str  # "master" | "slave"
    peer_id: str | None
    kind: str
    driver: Driver | None
    autonomous: bool
    takeover: bool
    heartbeat_timeout: float | None
    reply: Reply[Any]
    description: str = ""  # what the master is, in words (told to a master it displaces)
    intervene: bool = False  # the master intervenes: the running master is paused, not ended


@dataclass(slots=True)
class DetachMsg:
    role: str  # "master" | "slave"
    peer_id: str | None
    lost: bool
    reason: str
    reply: Reply[None] | None
    hold: bool = True
    released: bool = False  # the master's own release (recorded as "released")


@dataclass(slots=True)
class StatesMsg:
    slave_id: str
    joints: Mapping[str, float]


@dataclass(slots=True)
class FaultMsg:
    """A fault of a peer (`role`: "master" or "slave"), or with `cleared` its end."""

    role: str
    peer_id: str
    code: str
    message: str
    severity: Severity
    joint: str | None
    cleared: bool = False


@dataclass(slots=True)
class AliveMsg:
    peer_id: str


@dataclass(slots=True)
class LinkMsg:
    slave_id: str
    connected: bool
    reason: str


@dataclass(slots=True)
class RejoinMsg:
    slave_id: str
    reason: str
    joints: dict[str, float] | None  # where the arm is now, if the slave knows


@dataclass(slots=True)
class DriverEndedMsg:
    peer: MasterPeer[Any] | SlavePeer[Any]
    error: BaseException | None


@dataclass(slots=True)
class WorkspaceMsg:
    workspace: Workspace
    reply: Reply[None]


@dataclass(slots=True)
class EpisodeMsg:
    action: str  # "start" | "stop" | "discard" | "highlight"
    task: str
    reply: Reply[Episode]
    since: float = 0.0  # a highlight starts no earlier (trio time)...
    keep: float = 0.0  # ...nor more than this many seconds before now, when it ends


@dataclass(slots=True)
class SensorFaultMsg:
    sensor_id: str
    code: str
    message: str
    severity: Severity


@dataclass(slots=True)
class ShutdownMsg:
    reason: str
    reply: Reply[None] | None


Msg = (
    CommandMsg
    | EventMsg
    | AttachMsg
    | DetachMsg
    | StatesMsg
    | FaultMsg
    | AliveMsg
    | LinkMsg
    | RejoinMsg
    | DriverEndedMsg
    | WorkspaceMsg
    | EpisodeMsg
    | SensorFaultMsg
    | ShutdownMsg
)


# ---------------------------------------------------------------------------------------------
# Links: what a driver (or a network edge) holds to talk to the robot
