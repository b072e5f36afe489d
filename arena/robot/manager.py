"""The manager: creates, finds, lists and deletes robots, and supervises their actors.

All actors live in the manager's nursery. An actor that crashes (a bug, never a driver: drivers
are contained by their actor) is logged and removed; the other robots go on.
"""

from __future__ import annotations

import contextlib
import logging
import re
import secrets
from collections.abc import AsyncIterator, Awaitable, Callable, Iterable

import trio

from arena.protocol.errors import ArenaError, ErrorCode
from arena.protocol.rest import DEFAULT_TENANT
from arena.robot.handle import Robot
from arena.robot.links import RobotView
from arena.robot.model import SafetyPolicy, load_robot_model

log = logging.getLogger(__name__)

_ID_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
#: Seconds a robot gets to stop its drivers before it is cancelled.
SHUTDOWN_GRACE = 1.0


async def estop_together(robots: Iterable[RobotView], reason: str) -> None:
    """E-stop robots: the idle ones at once in this task (in their actor's idle turn,
    `arena.robot.idle`), the busy ones together (each after the message it is handling),
    rather than one after another. A robot that has stopped (was deleted) is skipped: it
    moves nothing."""

    async def stop(robot: RobotView) -> None:
        with contextlib.suppress(ArenaError):
            await robot.estop(reason)

    busy = []
    for robot in robots:
        try:
            if robot.estop_now(reason) is None:
                busy.append(robot)
        except ArenaError:
            continue
    async with trio.open_nursery() as nursery:
        for robot in busy:
            nursery.start_soon(stop, robot)


class RobotManager:
    """All robots of one process. Open it with `open_manager()`."""

    def __init__(self, nursery: trio.Nursery) -> None:
        self._nursery = nursery
        self._robots: dict[str, Robot] = {}
        self._scopes: dict[Robot, trio.CancelScope] = {}
        #: Called with every new robot once it runs (the recorder follows robots this way).
        self.on_create: list[Callable[[Robot], None]] = []

    async def create_robot(
        self,
        robot_type: str,
        name: str | None = None,
        robot_id: str | None = None,
        policy: SafetyPolicy | None = None,
        tenant: str = DEFAULT_TENANT,
    ) -> Robot:
        """Create and start a robot of `tenant`. Raises `ArenaError` for a bad type, id or
        duplicate."""
        model = load_robot_model(robot_type)
        if robot_id is None:
            robot_id = f"robot-{secrets.token_hex(4)}"
        if not _ID_PATTERN.match(robot_id):
            raise ArenaError(
                ErrorCode.INVALID_CONFIG,
                "Robot ids are 1-64 letters, digits, '.', '_' or '-', "
                "starting with a letter or digit.",
            )
        if robot_id in self._robots:
            raise ArenaError(ErrorCode.ROBOT_EXISTS, f"A robot with id {robot_id!r} exists.")
        robot = Robot(robot_id, name or robot_id, model, policy, tenant=tenant)
        self._robots[robot_id] = robot
        await self._nursery.start(self._supervise, robot)
        for callback in self.on_create:
            callback(robot)
        log.info("robot %s created (%s)", robot_id, robot_type)
        return robot

    def get(self, robot_id: str) -> Robot:
        """The robot `robot_id`; raises `ArenaError(UNKNOWN_ROBOT)`."""
        robot = self._robots.get(robot_id)
        if robot is None:
            raise ArenaError(ErrorCode.UNKNOWN_ROBOT, f"No robot with id {robot_id!r}.")
        return robot

    def find(self, robot_id: str) -> Robot | None:
        """The robot `robot_id`, None if there is none."""
        return self._robots.get(robot_id)

    def robots(self) -> list[Robot]:
        """Every robot, in creation order."""
        return list(self._robots.values())

    async def delete(self, robot_id: str) -> None:
        """Stop a robot's drivers cleanly and remove it."""
        robot = self.get(robot_id)
        await self._stop(robot, "robot deleted")

    def spawn(self, task: Callable[..., Awaitable[object]], *args: object) -> None:
        """Run a background task for as long as the manager (group watchers, say)."""
        self._nursery.start_soon(task, *args)

    async def estop_all(self, reason: str = "emergency stop (all robots)") -> None:
        """E-stop every robot at once (see `estop_together`)."""
        await estop_together(self.robots(), reason)

    async def close(self) -> None:
        """Stop every robot."""
        for robot in self.robots():
            await self._stop(robot, "server shutting down")

    async def _stop(self, robot: Robot, reason: str) -> None:
        with trio.move_on_after(SHUTDOWN_GRACE) as scope:
            scope.shield = True
            await robot.shutdown(reason)
            await robot.stopped.wait()
        if scope.cancelled_caught:
            log.warning(
                "robot %s did not stop within %.1f s; cancelled", robot.robot_id, SHUTDOWN_GRACE
            )
            self._scopes[robot].cancel()
        self._robots.pop(robot.robot_id, None)

    async def _supervise(
        self, robot: Robot, *, task_status: trio.TaskStatus[None] = trio.TASK_STATUS_IGNORED
    ) -> None:
        try:
            with trio.CancelScope() as scope:
                self._scopes[robot] = scope
                await robot.run(task_status=task_status)
        except Exception:
            log.exception("robot %s crashed; removed", robot.robot_id)
        finally:
            self._scopes.pop(robot, None)
            if self._robots.get(robot.robot_id) is robot:
                del self._robots[robot.robot_id]


@contextlib.asynccontextmanager
async def open_manager() -> AsyncIterator[RobotManager]:
    """A manager whose robots all stop when the block ends."""
    async with trio.open_nursery() as nursery:
        manager = RobotManager(nursery)
        try:
            yield manager
        finally:
            await manager.close()
            nursery.cancel_scope.cancel()
