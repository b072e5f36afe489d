"""The planned-move master: plays a planned path's poses onto a robot at their times
(specs/cartesian.md, "Planned paths"), each one command through every rule, as a sequence
plays its keyframes."""

from __future__ import annotations

import logging

import trio

from arena.drivers.refusals import Refusals
from arena.protocol.errors import ErrorCode
from arena.robot.links import MasterLink
from arena.robot.motion import Command, JointGoal
from arena.robot.planning import PlannedPath

log = logging.getLogger(__name__)

#: Degrees within which the arm's targets count as on a corner of the path.
ON_CORNER = 1e-3
#: Seconds a corner is waited for at most (then the next pose is commanded all the same, and
#: the guard checks the way from wherever the targets are).
CORNER_PATIENCE = 5.0


class PlannedMove:
    """Commands every pose of `path` at its time. Autonomous: an e-stop ends it for good. It
    takes no robot another master holds. A refused pose ends it (a planned path that skips a
    pose is not the path that was checked), except a rate limit's refusal: the next pose is
    on the same path."""

    kind = "planned-move"
    autonomous = True
    takes_over = False

    def __init__(self, path: PlannedPath, source: str = "planned-move") -> None:
        self.path = path
        self._commands = tuple(
            (at, Command(tuple(JointGoal(n, v) for n, v in pose.items()), None, source))
            for at, pose in path.samples
        )
        corners = {tuple(corner.values()) for corner in path.waypoints}
        #: Which poses are corners (reached at rest in the plan's timing).
        self._corners = [tuple(pose.values()) in corners for _, pose in path.samples]
        self.refusals = Refusals()
        #: Poses accepted so far.
        self.sent = 0

    async def _reach(self, link: MasterLink, corner: Command) -> None:
        """Wait (at most `CORNER_PATIENCE`) until the robot's targets are on `corner`."""
        goals = {goal.name: goal.value for goal in corner.joints}
        with trio.move_on_after(CORNER_PATIENCE):
            while True:
                joints = link.robot.snapshot().joints
                if all(
                    abs(j.virtual_value - goals[j.name]) <= ON_CORNER
                    for j in joints
                    if j.name in goals
                ):
                    return
                await trio.sleep(0.005)

    @property
    def description(self) -> str:
        """What it plays, in words."""
        corners = len(self.path.waypoints)
        return f"a planned move ({corners} corners, {self.path.duration:.1f} s)"

    async def run(self, link: MasterLink) -> None:
        """Command each pose at its time; return when the last is sent or one is refused."""
        # The master's own clock: it stands still while the robot has it paused.
        start = trio.current_time() - link.paused_time(trio.current_time())
        for k, (at, command) in enumerate(self._commands):
            await link.sleep_until(start + at)
            if k and self._corners[k - 1]:
                # A corner first: the trajectory behind the plan's timing (a loaded machine, the
                # jerk limits) would otherwise cut it, off the path that was checked.
                await self._reach(link, self._commands[k - 1][1])
            result = await link.command(command)
            if result.accepted:
                self.sent += 1
                continue
            self.refusals.append((result.code, result.message))
            if result.code is not ErrorCode.RATE_LIMITED:
                log.info("planned move ends: %s", result.message)
                return
