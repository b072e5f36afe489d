"""Links to robots on other Arena servers: the `websocket-slave` and the `remote-server` master.

`WebSocketSlave` is a slave here and a master there: it connects out to the other server's
`/ws/master/{robotId}`, sends our targets there as commands, and reports that robot's real
joint values as ours. `RemoteServerMaster` is a master here and a slave there: it connects out
to `/ws/slave/{robotId}`, turns the `execute_command`s it gets into our commands, and reports
our real joint values back. Chained through a relay server, the two let an operator's robot on
one server drive an arm on another and show its real pose.

Both reconnect with exponential backoff and jitter and send heartbeats. While a link is down
our own safety policy applies: a lost websocket-slave is a lost slave (`connection_lost`), a
lost remote master e-stops the robot (or holds it, with the robot type's `hold` loss policy).
Nothing from before an outage is executed after it: targets that arrived while the link was
down are dropped, and the robot stays e-stopped until someone resets it.
"""

from __future__ import annotations

import logging
import math
import random
from typing import Any

import httpx
import trio

from arena.client import ArenaClientError, Backoff, MasterSession, SlaveSession, messages, ws_url
from arena.drivers.config import RemoteLinkConfig
from arena.protocol.errors import ArenaError, ErrorCode, Severity
from arena.robot.events import JointStatesReceived, NoticeKind, SlaveTarget
from arena.robot.links import MasterLink, SlaveLink
from arena.robot.model import LossPolicy
from arena.robot.motion import Command, JointGoal

log = logging.getLogger(__name__)

#: Seconds between joint_states reports to the other server (at most).
REPORT_INTERVAL = 0.02


def _http_base(url: str) -> str:
    url = url.rstrip("/")
    return "http" + url[2:] if url.startswith("ws") else url


def _session_options(config: RemoteLinkConfig, rng: random.Random | None) -> dict[str, Any]:
    return {
        "api_key": config.api_key,
        "backoff": Backoff(
            config.reconnect_initial, max(config.reconnect_initial, config.reconnect_max)
        ),
        "heartbeat": config.heartbeat,
        "rng": rng,
    }


async def check_remote_robot(config: RemoteLinkConfig, robot_id: str) -> dict[str, Any]:
    """Ask the other server about `robot_id` over REST, so that a wrong URL, key or id is the
    attaching caller's error now rather than a link that retries forever."""
    headers = {"Authorization": f"Bearer {config.api_key}"} if config.api_key else {}
    where = f"{config.url} robot {robot_id!r}"
    try:
        async with httpx.AsyncClient(base_url=_http_base(config.url), timeout=5) as http:
            response = await http.get(f"/api/robots/{robot_id}", headers=headers)
    except httpx.HTTPError as error:
        raise ArenaError(
            ErrorCode.REMOTE_UNREACHABLE,
            f"Cannot reach {config.url}: {error or type(error).__name__}.",
        ) from None
    if response.status_code != 200:
        try:
            code = response.json().get("code", response.status_code)
        except ValueError:
            code = response.status_code
        raise ArenaError(ErrorCode.REMOTE_REFUSED, f"{where}: the server answered {code}.")
    answer: dict[str, Any] = response.json()
    return answer


class WebSocketSlave:
    """See the module docstring. `rng` makes the backoff's jitter repeatable (tests)."""

    kind = "websocket-slave"
    # Not yet a slave that joins: the robot over there may have no measured pose to report
    # (a relay, a robot with no slave), and a join would then wait for ever. Its own
    # measuring slaves join it over there; see specs/robot-model.md for what is left.
    measures = False

    def __init__(self, config: RemoteLinkConfig, rng: random.Random | None = None) -> None:
        if config.robot_id is None:  # (the server says which field of its body)
            raise ArenaError(ErrorCode.INVALID_CONFIG, "A websocket-slave needs the remote id.")
        self.config = config
        self.robot_id = config.robot_id
        query = {"takeover": "1" if config.takeover else ""}
        self.session = _Upstream(
            ws_url(config.url, f"/ws/master/{self.robot_id}", **query),
            **_session_options(config, rng),
        )

    async def prepare(self) -> None:
        """The remote robot exists, the key is good, and (without takeover) it has no master."""
        robot = await check_remote_robot(self.config, self.robot_id)
        if robot.get("master") and not self.config.takeover:
            raise ArenaError(
                ErrorCode.MASTER_ACTIVE,
                f"{self.robot_id!r} on {self.config.url} already has a master; "
                "attach with takeover to displace it.",
            )

    async def run(self, link: SlaveLink) -> None:
        """Forward targets and notices until detached.

        Detached (or our robot going away) is a normal end: the robot over there is released,
        holding where it is, rather than lost. A failure just drops the link, and the other
        server's loss policy applies. The session's task is shielded so that the release can
        still go out through it once this driver is cancelled.
        """
        self.session.link = link
        session_scope = trio.CancelScope(shield=True)

        async def hold_session() -> None:
            with session_scope:
                await self.session.run()

        async with trio.open_nursery() as nursery:
            nursery.start_soon(hold_session)
            try:
                await self._forward(link)
            except trio.Cancelled:
                with trio.CancelScope(shield=True):  # (bounded: the session's timeouts)
                    await self._release()
                raise
            else:  # the detach notice came first: the cancellation follows at once
                with trio.CancelScope(shield=True):
                    await self._release()
            finally:
                session_scope.cancel()

    async def _forward(self, link: SlaveLink) -> None:
        interval = 1.0 / link.robot.model.safety.command_rate
        async for message in link.messages():
            if isinstance(message, SlaveTarget):
                if message.time >= self.session.accept_after:
                    await self.session.forward(message.joints)
                    # Within the rate limit (the other side has the same robot type):
                    # targets that come meanwhile merge, the newest wins.
                    await trio.sleep(interval)
            elif message.kind is NoticeKind.ESTOP:
                await self.session.try_send(messages.estop("upstream"))
            elif message.kind is NoticeKind.RESET:
                await self.session.try_send(messages.reset())

    async def _release(self) -> None:
        """Release the robot over there, if the link is up (bounded by the session's timeout)."""
        if not self.session.connected:
            return
        try:
            await self.session.release()
        except ArenaClientError as error:
            log.warning("websocket-slave %s: not released: %s", self.session.url, error)


class _Upstream(MasterSession):
    """The websocket-slave's master session on the other server."""

    def __init__(self, url: str, **options: Any) -> None:
        super().__init__(url, **options)
        self.link: SlaveLink | None = None
        self.accept_after = math.inf  # targets from before this trio time are stale
        self.was_down = False
        self.sent = 0
        self.refused = 0

    async def forward(self, joints: dict[str, float]) -> None:
        """Send a target as a command (if the link is up); its ack comes to `on_message`."""
        if await self.try_send(messages.command(joints)):
            self.sent += 1

    async def on_connect(self) -> None:
        await super().on_connect()
        self.accept_after = trio.current_time()
        if self.was_down and self.link is not None:
            self.was_down = False
            await self.link.connection_restored(f"{self.url}: reconnected")

    async def on_disconnect(self, reason: str) -> None:
        await super().on_disconnect(reason)
        self.accept_after = math.inf
        if self.finished:
            return  # released: the session is over, our slave is going away
        if self.link is not None and not self.was_down:
            self.was_down = True
            await self.link.connection_lost(f"{self.url}: {reason}")

    async def on_message(self, message: dict[str, Any]) -> None:
        await super().on_message(message)  # answers to requests (the release)
        if self.link is None:
            return
        kind = message.get("type")
        if kind == "ack":
            data = message.get("data") or {}
            if data.get("status") == "refused":
                self.refused += 1
                await self.link.report_fault(
                    str(data.get("code") or ErrorCode.REMOTE_REFUSED),
                    f"{self.url} refused a command: {data.get('message', '')}",
                    Severity.WARNING,
                )
        elif kind == "joint_states":
            real = {
                j["name"]: j["real_value"]
                for j in message.get("data") or []
                if isinstance(j.get("real_value"), int | float)
            }
            if real:
                await self.link.report_joint_states(real)
        elif kind == "state":
            data = message.get("data") or {}
            if data.get("mode") == "estopped":
                await self.link.report_fault(
                    ErrorCode.REMOTE_ESTOPPED,
                    f"the robot on {self.url} is e-stopped: {data.get('estop_reason')}",
                    Severity.WARNING,
                )
            else:
                await self.link.clear_fault(
                    ErrorCode.REMOTE_ESTOPPED, message=f"the robot on {self.url} was reset"
                )
        elif kind in ("error", "detached"):
            data = message.get("data") or {}
            await self.link.report_fault(
                str(data.get("code") or ErrorCode.REMOTE_REFUSED),
                f"{self.url}: {data.get('message', kind)}",
                Severity.WARNING,
            )
        else:
            self.link.alive()


class RemoteServerMaster:
    """See the module docstring."""

    kind = "remote-server"
    autonomous = False  # a link, not a program: it stays through an e-stop and its reset
    takes_over = False

    def __init__(
        self, config: RemoteLinkConfig, robot_id: str, rng: random.Random | None = None
    ) -> None:
        self.config = config
        self.remote_id = config.robot_id or robot_id
        self.session = _Downstream(
            ws_url(config.url, f"/ws/slave/{self.remote_id}", id=f"remote-{robot_id}"),
            **_session_options(config, rng),
        )

    @property
    def description(self) -> str:
        """What it is, in words (told to a master it takes over from)."""
        return f"remote server {self.config.url} (robot {self.remote_id!r})"

    async def prepare(self) -> None:
        """The remote robot exists and the key is good."""
        await check_remote_robot(self.config, self.remote_id)

    async def run(self, link: MasterLink) -> None:
        """Relay the other server's commands until detached."""
        self.session.link = link
        async with trio.open_nursery() as nursery:
            nursery.start_soon(self.session.run)
            nursery.start_soon(self.session.report_states)
            nursery.start_soon(self.session.command_targets)
            await trio.sleep_forever()


class _Downstream(SlaveSession):
    """The remote-server master's slave session on the other server."""

    def __init__(self, url: str, **options: Any) -> None:
        super().__init__(url, **options)
        self.link: MasterLink | None = None
        self.our_estop: str | None = None  # the reason of an e-stop this link raised
        self.commands = 0
        self.refused = 0
        self.pending: Command | None = None  # the newest target not yet commanded
        self._target_arrived = trio.Event()

    async def command_targets(self) -> None:
        """Command the newest target, at most at the robot's rate limit (newest wins).

        The reader never waits on the robot, so heartbeats and notices are never held up.
        """
        assert self.link is not None
        interval = 1.0 / self.link.robot.model.safety.command_rate
        while True:
            await self._target_arrived.wait()
            self._target_arrived = trio.Event()
            command, self.pending = self.pending, None
            if command is None:
                continue
            result = await self.link.command(command)
            self.commands += 1
            if not result.accepted:
                self.refused += 1
                error = messages.error(str(result.code), result.message, Severity.WARNING)
                await self.try_send(error)
            await trio.sleep(interval)

    async def on_connect(self) -> None:
        self.pending = None  # nothing from before the outage

    async def on_message(self, message: dict[str, Any]) -> None:
        link = self.link
        if link is None:
            return
        kind = message.get("type")
        if kind == "execute_command":
            joints = message.get("data", {}).get("joints") or []
            self.pending = Command(
                tuple(JointGoal(j["name"], float(j["value"])) for j in joints),
                source=f"remote:{self.url}",
            )
            self._target_arrived.set()
        elif kind == "estop":
            await self._estop("the remote robot was e-stopped")
        elif kind == "reset":
            snapshot = link.robot.snapshot()
            if str(snapshot.mode) == "estopped" and snapshot.estop_reason == self.our_estop:
                await link.robot.reset()  # only an e-stop this link raised
        else:
            link.alive()

    async def _estop(self, why: str) -> None:
        assert self.link is not None
        reason = f"remote-server {self.url}: {why}"
        self.our_estop = reason
        await self.link.robot.estop(reason)

    async def on_disconnect(self, reason: str) -> None:
        if self.link is None:
            return
        log.warning("remote-server %s: %s", self.url, reason)
        if self.link.robot.model.safety.loss_policy is LossPolicy.ESTOP:
            snapshot = self.link.robot.snapshot()
            if str(snapshot.mode) != "estopped":
                await self._estop(f"link lost ({reason})")

    async def report_states(self) -> None:
        """Our real joint values to the other server, at most every REPORT_INTERVAL."""
        assert self.link is not None
        robot = self.link.robot
        with robot.subscribe(maxlen=64) as events:
            while True:
                try:
                    batch = [await events.get(), *events.drain()]
                except trio.EndOfChannel:  # the robot is gone
                    return
                if not any(isinstance(e, JointStatesReceived) for e in batch):
                    continue
                real = {
                    j.name: j.real_value
                    for j in robot.snapshot().joints
                    if j.real_value is not None
                }
                if real and self.connected:
                    await self.try_send(messages.joint_states(real))
                await trio.sleep(REPORT_INTERVAL)
