"""Robot groups: one master drives several robots, each keeping its own safety state.

A group names its members; a master attached to the group claims every member and each of its
commands goes to each member, which accepts or refuses it by its own rules (an e-stopped member
stays still while the others move). With `stop_together`, an e-stop of any member e-stops the
rest of the group too.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import trio

from arena.protocol.errors import ArenaError, ErrorCode
from arena.protocol.rest import DEFAULT_TENANT
from arena.robot.events import StateChanged
from arena.robot.manager import RobotManager, estop_together
from arena.robot.safety import Mode


@dataclass
class Group:
    """A named set of robots of one tenant."""

    group_id: str
    members: tuple[str, ...]
    stop_together: bool = False
    tenant: str = DEFAULT_TENANT
    scope: trio.CancelScope = field(default_factory=trio.CancelScope)
    #: Members the group is e-stopping for another's e-stop: theirs is not passed on again
    #: (a member's own reason would otherwise race the first's to the others).
    passing_on: set[str] = field(default_factory=set)

    def describe(self, manager: RobotManager) -> dict[str, object]:
        """The group and each member's state, for the REST API."""
        states: dict[str, dict[str, str | None]] = {}
        for robot_id in self.members:
            try:
                snapshot = manager.get(robot_id).snapshot()
            except ArenaError:
                states[robot_id] = {"state": "deleted"}
                continue
            states[robot_id] = {
                "state": str(snapshot.mode),
                "master": snapshot.owner,
                "estop_reason": snapshot.estop_reason,
            }
        return {
            "id": self.group_id,
            "members": list(self.members),
            "stopTogether": self.stop_together,
            "states": states,
        }


class GroupRegistry:
    """Every group of a server, each tenant's apart: a group id is unique in its tenant and
    shares no space with the tenant's robot ids, so `/ws/master/{id}` is plain to each
    caller. Another tenant's groups and robots are as if they did not exist."""

    def __init__(self, manager: RobotManager) -> None:
        self.manager = manager
        self._groups: dict[tuple[str, str], Group] = {}

    def all(self, tenant: str | None = None) -> list[Group]:
        """Every group (of `tenant`, if given), oldest first."""
        return [g for g in self._groups.values() if tenant is None or g.tenant == tenant]

    def find(self, group_id: str, tenant: str = DEFAULT_TENANT) -> Group | None:
        """The group of `tenant`, or None."""
        return self._groups.get((tenant, group_id))

    def get(self, group_id: str, tenant: str = DEFAULT_TENANT) -> Group:
        """The group of `tenant`, or UNKNOWN_GROUP."""
        group = self._groups.get((tenant, group_id))
        if group is None:
            raise ArenaError(ErrorCode.UNKNOWN_GROUP, f"No group {group_id!r}.")
        return group

    def create(
        self,
        group_id: str,
        members: list[str],
        stop_together: bool,
        tenant: str = DEFAULT_TENANT,
    ) -> Group:
        """A new group of existing robots of `tenant` (at least one, no repeats)."""
        if (tenant, group_id) in self._groups:
            raise ArenaError(ErrorCode.GROUP_EXISTS, f"A group {group_id!r} exists already.")
        robot = self.manager.find(group_id)
        if robot is not None and robot.tenant == tenant:
            raise ArenaError(ErrorCode.GROUP_EXISTS, f"{group_id!r} is a robot's id.")
        if not members or len(set(members)) != len(members):
            raise ArenaError(ErrorCode.INVALID_BODY, "A group needs one or more distinct robots.")
        for robot_id in members:
            self.manager.get(robot_id)  # UNKNOWN_ROBOT for a stranger
        group = Group(group_id, tuple(members), stop_together, tenant=tenant)
        self._groups[tenant, group_id] = group
        if stop_together:
            self.manager.spawn(self._stop_together, group)
        return group

    def delete(self, group_id: str, tenant: str = DEFAULT_TENANT) -> None:
        """Forget the group; its robots stay as they are."""
        self.get(group_id, tenant).scope.cancel()
        del self._groups[tenant, group_id]

    async def _stop_together(self, group: Group) -> None:
        with group.scope:
            async with trio.open_nursery() as nursery:
                for robot_id in group.members:
                    nursery.start_soon(self._watch, group, robot_id)

    async def _watch(self, group: Group, robot_id: str) -> None:
        try:
            robot = self.manager.get(robot_id)
        except ArenaError:  # deleted before this watcher started
            return
        with robot.subscribe(maxlen=64, kinds=[StateChanged]) as events:
            while True:
                try:
                    event = await events.get()
                except trio.EndOfChannel:  # the robot was deleted
                    return
                if not isinstance(event, StateChanged):
                    continue
                # Passed on by the group, or reset (its next e-stop is its own): forget it.
                if event.mode is not Mode.ESTOPPED or robot_id in group.passing_on:
                    group.passing_on.discard(robot_id)
                else:
                    await self._estop_others(group, robot_id)

    async def _estop_others(self, group: Group, stopped: str) -> None:
        others = []
        for other in group.members:
            if other == stopped:
                continue
            try:
                robot = self.manager.get(other)
            except ArenaError:  # deleted
                continue
            if robot.snapshot().mode is not Mode.ESTOPPED:
                others.append(robot)
        group.passing_on.update(robot.robot_id for robot in others)
        await estop_together(others, f"group {group.group_id!r}: {stopped!r} was e-stopped")
