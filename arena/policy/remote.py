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

from arena.client import AsyncArena, MasterSession, messages
from arena.client.errors import ArenaClientError
from arena.policy.features import IMAGE_PREFIX
from arena.policy.master import Inference, PolicyMaster, PolicySettings, Shot
from arena.policy.wire import Loaded
from arena.protocol.errors import ErrorCode, Severity
from arena.robot.model import RobotModel, load_robot_model
from arena.robot.motion import Command, CommandResult

log = logging.getLogger(__name__)


#: Inference records waiting to be sent at most (beyond, the newest are dropped and counted:
#: a stalled link must not make this machine's memory grow).
INFERENCE_QUEUE = 64


@dataclass
class SessionArm:
    """`Arm` over a master's session: the joints' newest real values (else the targets the
    robot reported), commands answered by their acknowledgments; faults go to the log, and
    inferences to the server (`send_inferences`), which records them."""

    session: MasterSession
    model: RobotModel
    faults: list[tuple[str, str]] = field(default_factory=list)
    unsent: int = 0  # inference records dropped: the queue was full
    _outbox: tuple[trio.MemorySendChannel[Inference], trio.MemoryReceiveChannel[Inference]] = field(
        default_factory=lambda: trio.open_memory_channel[Inference](INFERENCE_QUEUE)
    )

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
        """Sent to the server, which records it on `/robots/{id}/policy` (`send_inferences`)."""
        try:
            self._outbox[0].send_nowait(inference)
        except trio.WouldBlock:
            self.unsent += 1

    async def send_inferences(self) -> None:
        """Send the inference records as they come, while the link is up (one that cannot go
        is dropped: the server's record is of what reached it)."""
        async for item in self._outbox[1]:
            message = messages.inference(
                item.timestep,
                item.chunk_size,
                item.kept,
                item.latency,
                item.inference,
                item.frame_age,
            )
            try:
                sent = await self.session.try_send(message)
            except ArenaClientError:
                sent = False
            if not sent:
                self.unsent += 1

    @property
    def paused(self) -> bool:
        """The server paused this master (its `pause` message, until `resume`)."""
        return self.session.paused

    @property
    def pauses(self) -> int:
        """The server's pauses of this master so far (its `pause` messages)."""
        return self.session.pauses

    async def wait_resumed(self) -> None:
        """See `paused`."""
        await self.session.wait_resumed()


class CameraPoller:
    """The newest JPEG of each of the robot's cameras, fetched over REST at `fps`; a frame's
    capture time is its arrival here (the server's clock is not this machine's). Once `sizes`
    names a camera's (width, height), the server scales its frames to that size before they
    leave (a policy's input size: a 96 x 96 frame is a fraction of a 640 x 480 one)."""

    def __init__(self, arena: AsyncArena, robot_id: str, names: list[str], fps: float) -> None:
        self.arena = arena
        self.robot_id = robot_id
        self.names = names
        self.fps = fps
        self.frames: dict[str, Shot | None] = dict.fromkeys(names)
        self.sizes: dict[str, tuple[int, int]] = {}
        self.received = 0  # bytes of frames fetched
        self.fetched = 0  # frames fetched

    def __call__(self) -> Mapping[str, Shot | None]:
        return self.frames

    async def run(self) -> None:
        """Fetch every camera's frame once a period, forever."""
        while True:
            started = trio.current_time()
            for name in self.names:
                path = f"/api/robots/{quote(self.robot_id)}/cameras/{quote(name)}/frame"
                size = self.sizes.get(name)
                query = {} if size is None else {"width": size[0], "height": size[1]}
                response = await self.arena.http.get(path, params=query)
                if response.status_code == 200:
                    self.received += len(response.content)
                    self.fetched += 1
                    self.frames[name] = Shot(response.content, trio.current_time())
            await trio.sleep_until(started + 1 / self.fps)


@dataclass
class RemoteRun:
    """What a remote policy did: its master (with its counters), the camera frames it fetched
    and their bytes, and the inference records it could not send."""

    master: PolicyMaster
    frames: int
    frame_bytes: int
    unsent: int


async def run_remote(
    settings: PolicySettings,
    url: str,
    robot_id: str,
    api_key: str | None = None,
    takeover: bool = False,
) -> RemoteRun:
    """Load the policy here, check it against the robot there, and drive it until the robot
    stops it (an e-stop, a takeover) or the worker ends. `ArenaError(POLICY_INVALID)` before
    anything is sent if the robot cannot feed it."""
    async with AsyncArena(url, api_key) as arena:
        robot = await arena.robot(robot_id)
        cameras = await arena.http.get(f"/api/robots/{quote(robot_id)}/cameras")
        names = [camera["name"] for camera in cameras.json().get("cameras", [])]
        model = load_robot_model(robot["robot_type"])
        poller = CameraPoller(arena, robot_id, names, settings.fps)
        master = PolicyMaster(settings, model, poller)
        await master.prepare()
        assert master.loaded is not None
        poller.sizes = input_sizes(master.loaded)
        async with (
            MasterSession.open(
                url, robot_id, takeover=takeover, master_id=master.identity, api_key=api_key
            ) as session,
            trio.open_nursery() as nursery,
        ):
            await session.declare_policy(settings.fps, settings.stall_periods)
            arm = SessionArm(session, model)
            nursery.start_soon(poller.run)
            nursery.start_soon(arm.send_inferences)
            await session.wait_for(lambda s: bool(s.joints), timeout=10)
            await master.drive(arm)
            nursery.cancel_scope.cancel()
        return RemoteRun(master, poller.fetched, poller.received, arm.unsent)


def input_sizes(loaded: Loaded) -> dict[str, tuple[int, int]]:
    """Each camera the policy takes, at the (width, height) it takes it, rounded up to even
    numbers (JPEG's 4:2:0; the worker scales to the exact size as it does any frame)."""
    sizes = {}
    for feature in loaded.inputs:
        if feature.name.startswith(IMAGE_PREFIX) and len(feature.shape) == 3:
            _, height, width = feature.shape
            sizes[feature.name.removeprefix(IMAGE_PREFIX)] = (
                width + width % 2,
                height + height % 2,
            )
    return sizes
