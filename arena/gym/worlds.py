"""Where an `ArenaEnv` runs its robot: a private Arena with the physics twin (`TwinWorld`,
stepped on a virtual clock) or a robot of a running server (`ServerWorld`, paced in real
time). Both drive the robot as a master like any other, so every rule of a master's command
applies (limits, velocity, the collision guard, the rate limit, the e-stop).

Each runs trio in a thread of its own (`TrioLoop`); their methods are plain blocking calls.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import AsyncIterator, Mapping, Sequence
from pathlib import Path
from typing import Any, Protocol

import trio
from trio.testing import MockClock, wait_all_tasks_blocked

from arena.client import Arena, MasterSession
from arena.client.errors import ArenaClientError, ClientTimeout
from arena.drivers.physics import PhysicsSettings, PhysicsSlave, View
from arena.gym.loop import TrioLoop
from arena.robot.handle import Robot
from arena.robot.links import MasterLink
from arena.robot.manager import RobotManager, open_manager
from arena.robot.model import RobotModel, load_robot_model
from arena.robot.motion import Command, CommandResult
from arena.robot.safety import Mode

#: A refusal or an e-stop that ended an episode: `{"code": ..., "message": ...}`.
Safety = dict[str, str]
#: The id of the private Arena's robot, and of the environment as its master.
TWIN_ROBOT = "twin"
MASTER_ID = "gym"
#: Longest a reset may take to bring the arm to rest (seconds of the world's clock).
RESET_TIMEOUT = 10.0
#: How long a reset lets the robot stand once its targets are at rest (seconds): past the
#: motion limiter's burst and the command rate's refill, so every episode starts alike.
SETTLE = 0.2
#: Every episode of the twin starts at `EPOCH + n * EPISODE_SPACING` seconds of its virtual
#: clock: times in one binade of floats, all a multiple of the same power of two from its
#: start, round alike, so episodes that start alike run alike to the last bit (the robot
#: computes with absolute times). Episodes are shorter than the spacing.
EPOCH = 2.0**20
EPISODE_SPACING = 256.0
#: How long after a step's boundary the twin's master commands (seconds; see
#: `TwinWorld.command`): far above a float's rounding, far below anything physical. Steps
#: take turns at one and two of it.
COMMAND_DELAY = 1e-7
#: How long after a step's boundary an episode's start is marked (seconds): after the first
#: command, before the twin's next report, with room for the recording's rounding.
MARK_DELAY = 0.001
#: The arm is at rest when every joint is this close (degrees) to its rest value.
REST_TOLERANCE = 0.5


class World(Protocol):
    """What an environment needs of the robot it runs."""

    model: RobotModel
    fps: float

    def reset(self, target: Sequence[float]) -> tuple[float, ...]:
        """Bring the arm to rest through Arena, show `target`; the measured joints."""

    def step(self, action: Sequence[float]) -> tuple[tuple[float, ...], Safety | None]:
        """Send one command, let one period pass; the measured joints, and what refused the
        command or stopped the robot (None if nothing)."""

    def images(self, size: tuple[int, int]) -> dict[str, Any]:
        """The newest image (height, width, 3 uint8) of each of the world's cameras."""

    def close(self) -> None:
        """Let the robot go and stop the loop."""


def rest_pose(model: RobotModel) -> dict[str, float]:
    """Every joint at its wire zero (the type's neutral pose, where the twin starts)."""
    return dict.fromkeys(model.joint_names, 0.0)


def command_of(model: RobotModel, action: Sequence[float]) -> Command:
    """An action (wire units, servo order) as a command of the environment."""
    values = {joint.name: float(value) for joint, value in zip(model.joints, action, strict=True)}
    return Command.of(values)


class TwinWorld:
    """A private Arena (a manager, one robot, the physics twin as its slave) stepped on a
    virtual clock: each step moves the clock one period and the twin with it, so it runs as
    fast as the machine allows and the same way every time. `recordings` records it to MCAP
    as a server would (`arena.recording`)."""

    def __init__(
        self,
        robot_type: str = "so-arm100",
        fps: float = 30.0,
        recordings: Path | None = None,
        cameras: Mapping[str, View] | None = None,
    ) -> None:
        self.model = load_robot_model(robot_type)
        #: The twin's cameras: views of its MuJoCo scene, rendered on demand (`images`).
        self.cameras = dict(cameras or {})
        self.fps = fps
        self.period = 1.0 / fps
        self.recordings = recordings
        self.clock = MockClock()  # stands still unless a step moves it (autojump off)
        self.slave = PhysicsSlave(PhysicsSettings(realtime=False, stepped=True, target_marker=True))
        self.manager: RobotManager | None = None
        self._robot: Robot | None = None
        self._link: MasterLink | None = None
        self._time = 0.0
        self._turn = False  # which of the two command delays the next step takes
        self._holds = 0  # `standing_still` blocks open: the clock must not move
        self._free = trio.Event()
        self._free.set()
        self._jumping = False  # `_until` lets the clock jump now
        self.loop = TrioLoop(self._serve, clock=self.clock, name="arena-gym-twin")

    @property
    def robot(self) -> Robot:
        """The twin's robot in the private Arena."""
        if self._robot is None:
            raise RuntimeError("the twin is not running")
        return self._robot

    async def _serve(self, task_status: trio.TaskStatus[None]) -> None:
        async with trio.open_nursery() as nursery:
            if self.recordings is not None:
                from arena.recording.recorder import Recorder  # MCAP only when recording

                recorder = Recorder(self.recordings, {"source": "arena.gym"}, foxglove=False)
                await nursery.start(recorder.run)
            async with open_manager() as manager:
                if self.recordings is not None:
                    manager.on_create.append(recorder.follow)
                self.manager = manager
                self._robot = await manager.create_robot(self.model.robot_type, robot_id=TWIN_ROBOT)
                await self._robot.attach_slave(self.slave, "twin")
                await self.slave.ready.wait()
                self._link = await self._robot.connect_master(MASTER_ID, kind="gym")
                self._time = trio.current_time()
                task_status.started()
                await trio.sleep_forever()

    async def _until(self, when: float) -> None:
        """Let the clock run to `when`, every timer due meanwhile firing in order, then stand
        still until everything due has been done. While a `standing_still` block is open the
        clock waits for it first."""
        await self._free.wait()
        self._jumping = True
        self.clock.autojump_threshold = 0.0  # jump from timer to timer until then
        try:
            await trio.sleep_until(when)
        finally:
            self._jumping = False
            self.clock.autojump_threshold = math.inf
        await wait_all_tasks_blocked()

    @contextlib.asynccontextmanager
    async def standing_still(self) -> AsyncIterator[None]:
        """The world's clock stands still for the block (a policy's inference, which takes
        real time in its own process, takes none of the world's: the twin waits for it)."""
        self._holds += 1
        if self._holds == 1:
            self._free = trio.Event()
        self.clock.autojump_threshold = math.inf
        try:
            yield
        finally:
            self._holds -= 1
            if self._holds == 0:
                self._free.set()
                if self._jumping:
                    self.clock.autojump_threshold = 0.0

    async def advance(self, seconds: float) -> None:
        """Let `seconds` pass on the world's clock, the twin stepped every report interval."""
        end = self._time + seconds
        interval = self.slave.settings.report_interval
        while self._time < end - 1e-12:
            self._time = min(self._time + interval, end)
            await self._until(self._time)
            await self.slave.step_to(self._time)
        await wait_all_tasks_blocked()  # the twin's report reached the robot

    async def command(self, command: Command, link: MasterLink | None = None) -> CommandResult:
        """Send `command` as the environment's master (or as `link`'s), a hair after the step
        boundary: one `COMMAND_DELAY` after it, then two, then one... A timer the robot set a
        whole number of its control periods after the last command then always fires on the
        same side of this command (before it after a short delay, after it after a long
        one), and the twin's steps, on the boundaries' grid, never meet the robot's ticks."""
        self._turn = not self._turn
        await self._until(self._time + COMMAND_DELAY * (1 if self._turn else 2))
        link = link or self._link
        if link is None:
            raise RuntimeError("the twin is not running")
        return await link.command(command)

    def measured(self) -> tuple[float, ...]:
        """Each joint's measured value (else its target), wire units, servo order."""
        values = []
        for joint in self.robot.snapshot().joints:
            values.append(joint.real_value if joint.real_value is not None else joint.virtual_value)
        return tuple(values)

    async def _master(self) -> MasterLink:
        robot = self.robot
        if robot.snapshot().mode is Mode.ESTOPPED:
            await robot.reset()  # the twin is the environment's own: nobody else to ask
        if self._link is None or self._link.detached.is_set():
            self._link = await robot.connect_master(MASTER_ID, kind="gym", takeover=True)
        return self._link

    async def _reset(self, target: Sequence[float]) -> tuple[float, ...]:
        await self._master()
        rest = rest_pose(self.model)
        result = await self.command(Command.of(rest))
        if not result.accepted:
            raise RuntimeError(f"the twin could not be brought to rest: {result.message}")
        waited = 0.0
        motion = self.robot.core.motion
        # (until the trajectory is done, not only at the pose: a tick still due would fire
        # after the jump below, at a phase the last episode left)
        while motion.moving or any(
            abs(j.virtual_value) > 1e-9 for j in self.robot.snapshot().joints
        ):
            if waited > RESET_TIMEOUT:
                raise RuntimeError("the twin's targets did not reach the rest pose")
            await self.advance(self.period)
            waited += self.period
        # The targets are at rest: on to the episode's start time; there, put the simulated
        # arm at rest exactly (a real arm would settle there), so every episode starts alike.
        now = trio.current_time()
        start = EPOCH + EPISODE_SPACING * max(
            0, math.ceil((now + SETTLE - EPOCH) / EPISODE_SPACING)
        )
        self.clock.jump(start - now)
        self._time = start
        self._turn = False  # (the commands' delays too)
        await wait_all_tasks_blocked()
        await self.slave.place(rest)
        if self.slave.simulation is not None:
            x, y, z = (float(v) for v in target)
            self.slave.simulation.set_target((x, y, z))
        await wait_all_tasks_blocked()
        return self.measured()

    async def reset_now(self, target: Sequence[float]) -> tuple[float, ...]:
        """`reset` from a task of the world's own loop."""
        return await self._reset(target)

    async def episode_now(self, action: str, task: str = "") -> int:
        """Mark an episode (`start`, `stop`, `discard`) of the robot from a task of the world's
        loop; its index. A start is marked `MARK_DELAY` after the step's boundary, so that the
        export's frame k (every 1/fps from the start) holds the joints measured at step k and
        the command sent on them (the recording's log times are good to a microsecond)."""
        if action == "start":
            await self._until(self._time + MARK_DELAY)
        return (await self.robot.episode(action, task)).index

    def reset(self, target: Sequence[float]) -> tuple[float, ...]:
        """See `World.reset`."""
        return self.loop.call(self._reset, target)

    async def _step(self, action: Sequence[float]) -> tuple[tuple[float, ...], Safety | None]:
        result = await self.command(command_of(self.model, action))
        safety = None
        if not result.accepted:
            safety = {"code": str(result.code), "message": result.message}
        await self.advance(self.period)
        return self.measured(), safety

    def step(self, action: Sequence[float]) -> tuple[tuple[float, ...], Safety | None]:
        """See `World.step`."""
        return self.loop.call(self._step, action)

    async def _images(self, size: tuple[int, int]) -> dict[str, Any]:
        simulation = self.slave.simulation
        if simulation is None:
            raise RuntimeError("the twin is not running")
        height, width = size
        return {name: simulation.render(view, width, height) for name, view in self.cameras.items()}

    def images(self, size: tuple[int, int]) -> dict[str, Any]:
        """See `World.images`: each camera's view of the MuJoCo scene, rendered now (in the
        loop's thread, which steps the simulation)."""
        return self.loop.call(self._images, size)

    def close(self) -> None:
        """Stop the private Arena."""
        if self.loop.running and self.slave.simulation is not None:
            simulation = self.slave.simulation

            async def release() -> None:
                simulation.close()  # in the thread that made the renderers' GL contexts

            self.loop.call(release)
        self.loop.close()


class ServerWorld:
    """A robot of a running Arena server, driven over its master WebSocket in real time: each
    step sends one command and waits for the next tick of `fps`. The server's e-stop, from
    anyone, refuses the next command and so ends the episode."""

    def __init__(
        self,
        url: str,
        robot: str,
        fps: float = 30.0,
        api_key: str | None = None,
        takeover: bool = False,
        observation_wait: float | None = None,
    ) -> None:
        with Arena(url, api_key) as rest:
            details = rest.robot(robot)
        self.model = load_robot_model(str(details["robot_type"]))
        self.url, self.robot_id, self.fps = url, robot, fps
        self.period = 1.0 / fps
        self.api_key, self.takeover = api_key, takeover
        # A step waits this long at most, after its tick, for the joint states its command
        # caused: one period by default (a real-time loop must not stall on a late report).
        self.observation_wait = self.period if observation_wait is None else observation_wait
        self._session: MasterSession | None = None
        self._tick = 0.0
        self.loop = TrioLoop(self._serve, name="arena-gym-server")

    async def _serve(self, task_status: trio.TaskStatus[None]) -> None:
        async with MasterSession.open(
            self.url,
            self.robot_id,
            takeover=self.takeover,
            master_id=MASTER_ID,
            api_key=self.api_key,
        ) as session:
            self._session = session
            await session.wait_for(lambda s: bool(s.joints) and s.state is not None, timeout=10)
            task_status.started()
            await trio.sleep_forever()

    @property
    def session(self) -> MasterSession:
        """The master's session."""
        if self._session is None:
            raise RuntimeError("not connected")
        return self._session

    def _measured(self) -> tuple[float, ...]:
        values = []
        for joint in self.model.joints:
            entry: Mapping[str, Any] = self.session.joints.get(joint.name) or {}
            value = entry.get("real_value")
            if value is None:
                value = entry.get("virtual_value", 0.0)
            values.append(float(value))
        return tuple(values)

    def _estop(self) -> Safety | None:
        state = self.session.state or {}
        if state.get("mode") == Mode.ESTOPPED.value:
            reason = state.get("estop_reason") or "the robot is e-stopped"
            return {"code": "ESTOPPED", "message": str(reason)}
        return None

    async def _reset(self, target: Sequence[float]) -> tuple[float, ...]:
        stopped = self._estop()
        if stopped is not None:
            raise RuntimeError(
                f"{self.robot_id} is e-stopped ({stopped['message']}): reset it "
                f"(POST /api/robots/{self.robot_id}/reset) before a new episode"
            )
        rest = rest_pose(self.model)
        await self.session.command(rest)

        def there(session: MasterSession) -> bool:
            measured = self._measured()
            return all(abs(v) <= REST_TOLERANCE for v in measured)

        await self.session.wait_for(there, timeout=RESET_TIMEOUT)
        self._tick = trio.current_time()
        return self._measured()

    def reset(self, target: Sequence[float]) -> tuple[float, ...]:
        """See `World.reset`. An e-stopped robot is not reset here: that is its operator's."""
        return self.loop.call(self._reset, target)

    async def _step(self, action: Sequence[float]) -> tuple[tuple[float, ...], Safety | None]:
        safety = self._estop()
        # The joint states before the command: the next ones are what it did (they may come
        # with its acknowledgment, or after it, at most every `joint_states_interval`).
        before = self.session.joints
        if safety is None:
            joints = {j.name: float(v) for j, v in zip(self.model.joints, action, strict=True)}
            try:
                await self.session.command(joints, metadata={"source": MASTER_ID})
            except ArenaClientError as error:
                safety = {"code": error.code, "message": error.message}
        self._tick = max(self._tick + self.period, trio.current_time() - self.period)
        await trio.sleep_until(self._tick)
        if safety is None:
            with contextlib.suppress(ClientTimeout):  # a command that moved nothing
                await self.session.wait_for(
                    lambda session: session.joints is not before, timeout=self.observation_wait
                )
        return self._measured(), safety or self._estop()

    def step(self, action: Sequence[float]) -> tuple[tuple[float, ...], Safety | None]:
        """See `World.step`."""
        return self.loop.call(self._step, action)

    def images(self, size: tuple[int, int]) -> dict[str, Any]:
        """None yet against a server (see specs/learning.md): no cameras."""
        return {}

    async def _release(self) -> None:
        if self.session.connected and self.session.released is None:
            await self.session.release(hold=True)

    def close(self) -> None:
        """Release the robot (it stops where it is, no e-stop) and stop the loop."""
        if self.loop.running:
            with contextlib.suppress(ArenaClientError):  # gone: the loss policy has it
                self.loop.call(self._release)
        self.loop.close()
