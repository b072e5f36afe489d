"""`arena policy DIR --url ... --robot ID`: a policy on this machine (the one with the GPU) as
the master of a robot on an Arena server, over the public API only: the master's WebSocket for
commands and joint states, REST for the robot, its cameras and their newest frames. The same
`PolicyMaster` loop runs as on the server, with the same rules; the server adds its own.

Nothing read from the server is more than JSON and JPEG bytes, and the worker hears only typed
frames (specs/policy.md).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field
from urllib.parse import quote

import trio

from arena.client import AsyncArena, MasterSession
from arena.client.errors import ArenaClientError
from arena.policy.master import Inference, PolicyMaster, PolicySettings, Shot
from arena.protocol.errors import ErrorCode, Severity
from arena.robot.model import RobotModel, load_robot_model
from arena.robot.motion import Command, CommandResult

log = logging.getLogger(__name__)


@dataclass
class SessionArm:
    """`Arm` over a master's session: the joints' newest real values (else the targets the
    robot reported), commands answered by their acknowledgments; faults go to the log."""

    session: MasterSession
    model: RobotModel
    faults: list[tuple[str, str]] = field(default_factory=list)

    def measured(self) -> tuple[float, ...]:
        """See `Arm.measured`."""
        values = []
        for joint in self.model.joints:
            entry = self.session.joints.get(joint.name) or {}
            value = entry.get("real_value")
            if value is None:
                value = entry.get("virtual_value", entry.get("value", 0.0))
            values.append(float(value))
        return tuple(values)

    async def command(self, command: Command) -> CommandResult:
        """See `Arm.command`."""
        joints = {goal.name: goal.value for goal in command.joints}
        metadata = {"source": command.source} if command.source else {}
        try:
            await self.session.command(joints, metadata=metadata)
        except ArenaClientError as error:
            try:
                code = ErrorCode(error.code)
            except ValueError:  # DISCONNECTED, TIMEOUT: this link no longer drives the robot
                code = ErrorCode.NOT_OWNER
            return CommandResult.refused(code, error.message)
        return CommandResult(True)

    def fault(self, source: str, code: ErrorCode, message: str, severity: Severity) -> None:
        """Logged here (the server records the commands, not this machine's faults)."""
        self.faults.append((str(code), message))
        log.warning("%s: %s (%s): %s", source, code, severity, message)

    def inferred(self, source: str, inference: Inference) -> None:
        """Logged here at debug level (the server records only what reaches it)."""
        log.debug("%s: %s", source, inference)

    @property
    def paused(self) -> bool:
        """The server paused this master (its `pause` message, until `resume`)."""
        return self.session.paused

    async def wait_resumed(self) -> None:
        """See `paused`."""
        await self.session.wait_resumed()


class CameraPoller:
    """The newest JPEG of each of the robot's cameras, fetched over REST at `fps`; a frame's
    capture time is its arrival here (the server's clock is not this machine's)."""

    def __init__(self, arena: AsyncArena, robot_id: str, names: list[str], fps: float) -> None:
        self.arena = arena
        self.robot_id = robot_id
        self.names = names
        self.fps = fps
        self.frames: dict[str, Shot | None] = dict.fromkeys(names)

    def __call__(self) -> Mapping[str, Shot | None]:
        return self.frames

    async def run(self) -> None:
        """Fetch every camera's frame once a period, forever."""
        while True:
            started = trio.current_time()
            for name in self.names:
                path = f"/api/robots/{quote(self.robot_id)}/cameras/{quote(name)}/frame"
                response = await self.arena.http.get(path)
                if response.status_code == 200:
                    self.frames[name] = Shot(response.content, trio.current_time())
            await trio.sleep_until(started + 1 / self.fps)


async def run_remote(
    settings: PolicySettings,
    url: str,
    robot_id: str,
    api_key: str | None = None,
    takeover: bool = False,
) -> PolicyMaster:
    """Load the policy here, check it against the robot there, and drive it until the robot
    stops it (an e-stop, a takeover) or the worker ends. Returns the master, with its counters.
    `ArenaError(POLICY_INVALID)` before anything is sent if the robot cannot feed it."""
    async with AsyncArena(url, api_key) as arena:
        robot = await arena.robot(robot_id)
        cameras = await arena.http.get(f"/api/robots/{quote(robot_id)}/cameras")
        names = [camera["name"] for camera in cameras.json().get("cameras", [])]
        model = load_robot_model(robot["robot_type"])
        poller = CameraPoller(arena, robot_id, names, settings.fps)
        master = PolicyMaster(settings, model, poller)
        await master.prepare()
        async with (
            MasterSession.open(
                url, robot_id, takeover=takeover, master_id=master.identity, api_key=api_key
            ) as session,
            trio.open_nursery() as nursery,
        ):
            nursery.start_soon(poller.run)
            await session.wait_for(lambda s: bool(s.joints), timeout=10)
            await master.drive(SessionArm(session, model))
            nursery.cancel_scope.cancel()
        return master
