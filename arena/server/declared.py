"""The setup the configuration file declares, brought up, kept trying and reloaded
(specs/declared-setup.md).

Each part is made by the function its REST route calls (`arena.server.parts`), in order: the
robots, their workspaces, slaves, cameras, masters, then the groups; an arm joins as any arm
joins. A part that cannot come up (an adapter not plugged in, a camera missing) leaves the rest
up: it is listed in `/readyz` and in its robot's details, and tried again after 1 s, the wait
doubling to 30 s, until it comes up or the file no longer declares it.

A reload (SIGHUP, `POST /api/config/reload`) compares the file with the setup brought up last
and changes only what differs: a part the file still declares as it was is never touched (an
arm that stays is never re-joined); what was made by hand over REST is left alone.
"""

from __future__ import annotations

import contextlib
import logging
import signal
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from typing import Any

import msgspec
import trio

from arena.protocol.errors import ArenaError, ErrorCode
from arena.protocol.rest import DEFAULT_TENANT, CreateRobotBody, GroupBody, WorkspaceBody
from arena.robot.handle import Robot
from arena.robot.workspace import workspace_to_json
from arena.server import parts
from arena.server.base import ArenaApp
from arena.server.config import ServerConfig
from arena.server.setup_file import (
    SECRET_SETTINGS,
    DeclaredRobot,
    Setup,
    check_references,
    parse_setup,
    read_toml,
    to_toml,
)

log = logging.getLogger(__name__)

#: The first wait before a part that did not come up is tried again, and the longest.
FIRST_RETRY = 1.0
LONGEST_RETRY = 30.0
#: The order parts come up in (and, reversed, go down in).
KINDS = ("robot", "workspace", "slave", "camera", "master", "group")

#: A part: (kind, robot id or group id, the slave's id or camera's name, else "").
PartKey = tuple[str, str, str]


def read_setup(config: ServerConfig) -> Setup:
    """The file's setup, read and checked whole (INVALID_CONFIG naming the line)."""
    assert config.config_file is not None
    text, data = read_toml(config.config_file)
    known = set(ServerConfig.__dataclass_fields__) - {"config_file"}
    setup = parse_setup(config.config_file, text, data, known)
    check_references(setup, config.policy_dir, config.recordings_dir, script_dir=config.script_dir)
    return setup


def _parts(setup: Setup) -> dict[PartKey, Any]:
    """Every part of the setup by key, in the order they come up; the value is what, changed,
    makes the part anew."""
    found: dict[PartKey, Any] = {}
    robots = setup.robots.values()
    for robot in robots:
        found["robot", robot.robot_id, ""] = robot.identity
    for robot in robots:
        if robot.workspace is not None:
            found["workspace", robot.robot_id, ""] = robot.workspace
    for robot in robots:
        for slave_id, slave in robot.slaves.items():
            found["slave", robot.robot_id, slave_id] = slave
    for robot in robots:
        for name, camera in robot.cameras.items():
            found["camera", robot.robot_id, name] = camera
    for robot in robots:
        if robot.master is not None:
            found["master", robot.robot_id, ""] = robot.master
    for group in setup.groups.values():
        found["group", group.id, ""] = group
    return found


class _Gone(Exception):
    """The robot of a part was deleted by hand since the file made it."""


@dataclass
class Pending:
    """A part that did not come up, and when it is tried next."""

    error: str
    attempts: int = 1
    next_try: float = 0.0  # trio time
    scope: trio.CancelScope = field(default_factory=trio.CancelScope)
    #: Set when what it waits for came up (its robot): it is tried at once.
    wake: trio.Event = field(default_factory=trio.Event)


class DeclaredSetup:
    """The file's setup on a running server (`app.declared`)."""

    def __init__(self, app: ArenaApp, path: str) -> None:
        self.app = app
        self.setup = Setup(path, {})
        self.pending: dict[PartKey, Pending] = {}
        self._masters: dict[str, str] = {}  # robot id -> the id of the master made for it
        self._lock = trio.Lock()

    async def reload(self) -> dict[str, Any]:
        """Read the file again and apply what changed (nothing if it is refused)."""
        if self.app.arena_config.config_file is None:
            raise ArenaError(
                ErrorCode.INVALID_CONFIG,
                "This server was started without --config: there is no file to reload.",
            )
        setup = await trio.to_thread.run_sync(read_setup, self.app.arena_config)
        return await self.apply(setup)

    async def apply(self, new: Setup) -> dict[str, Any]:
        """Bring the running setup from the last one applied to `new`: what is gone or
        changed goes down (last made first), what is new or changed comes up, in order."""
        async with self._lock:
            old = self.setup
            before, after = _parts(old), _parts(new)
            robots = {  # robots made anew (a new type, name or tenant), and their groups
                robot_id
                for (kind, robot_id, _), value in after.items()
                if kind == "robot" and before.get((kind, robot_id, "")) not in (None, value)
            }
            groups = {
                key[1]
                for key, group in after.items()
                if key[0] == "group" and robots & set(group.members)
            }

            def remade(key: PartKey) -> bool:
                return key[1] in (groups if key[0] == "group" else robots)

            gone = [k for k, v in before.items() if after.get(k) != v or remade(k)]
            coming = [k for k, v in after.items() if before.get(k) != v or remade(k)]
            dropped = {key[1] for key in gone if key[0] == "robot"}
            for key in reversed(gone):
                await self._take_down(key, dropped)
            self.setup = new
            for key in coming:
                await self._bring_up(key)
            changed = [k for k in coming if k in before]
            settings = sorted(
                name
                for name in set(old.settings) | set(new.settings)
                if old.settings.get(name) != new.settings.get(name)
            )
            return {
                "added": [_name(k) for k in coming if k not in changed],
                "changed": [_name(k) for k in changed],
                "removed": [_name(k) for k in gone if k not in after],
                "unchanged": [_name(k) for k in after if k not in coming],
                "pending": [_name(k) for k in self.pending],
                # Server settings take effect at the next start only.
                "restart_needed": settings if old.robots or old.groups or old.settings else [],
            }

    # -- one part -------------------------------------------------------------------------

    async def _bring_up(self, key: PartKey) -> None:
        """Make the part now; if it cannot be made, keep trying in the background."""
        try:
            await self._make(key)
        except Exception as error:
            pending = Pending(_reason(error))
            self.pending[key] = pending
            log.warning("%s did not come up: %s (tried again)", _name(key), pending.error)
            self.app.manager.spawn(self._retry, key, pending)

    async def _retry(self, key: PartKey, pending: Pending) -> None:
        """Try the part again after 1 s, then 2, 4... 30 s, until it comes up or goes."""
        wait = FIRST_RETRY
        with pending.scope:
            while True:
                pending.next_try = trio.current_time() + wait
                with trio.move_on_after(wait):
                    await pending.wake.wait()
                pending.wake = trio.Event()
                async with self._lock:
                    if self.pending.get(key) is not pending:
                        return
                    try:
                        await self._make(key)
                    except _Gone:  # its robot was deleted by hand: nothing left to wait for
                        del self.pending[key]
                        log.info("%s: its robot was deleted, no longer tried", _name(key))
                        return
                    except Exception as error:
                        pending.error = _reason(error)
                        pending.attempts += 1
                    else:
                        del self.pending[key]
                        log.info("%s came up (attempt %d)", _name(key), pending.attempts + 1)
                        if key[0] == "robot":  # its parts need not wait their turn
                            for (_, owner, _), waiting in self.pending.items():
                                if owner == key[1]:
                                    waiting.wake.set()
                        return
                wait = min(wait * 2, LONGEST_RETRY)

    async def _make(self, key: PartKey) -> None:
        kind, owner, name = key
        app = self.app
        if kind == "group":
            group = self.setup.groups[owner]
            tenant = self._robot(group.members[0]).tenant or DEFAULT_TENANT
            parts.create_group(app, group, tenant)
            return
        declared = self._robot(owner)
        if kind == "robot":
            body = CreateRobotBody(
                declared.robot_type, declared.name, declared.robot_id, declared.tenant
            )
            await parts.create_robot(app, parts.FILE_PRINCIPAL, body)
            return
        robot = self._robot_up(owner)
        if kind == "workspace":
            assert declared.workspace is not None
            await parts.set_workspace(robot, declared.workspace)
        elif kind == "slave":
            await parts.attach_slave(app, robot, declared.slaves[name], True, name)
        elif kind == "camera":
            await parts.attach_camera(app, robot, declared.cameras[name])
        elif kind == "master":
            assert declared.master is not None
            self._masters[owner] = await parts.attach_master(app, robot, declared.master, True)

    async def _take_down(self, key: PartKey, dropped: set[str]) -> None:
        """Undo a part (its retries stopped if it never came up); a part of a robot that goes
        too goes with it."""
        pending = self.pending.pop(key, None)
        if pending is not None:
            pending.scope.cancel()
            return
        kind, owner, name = key
        app = self.app
        if kind != "robot" and kind != "group" and owner in dropped:
            return
        with contextlib.suppress(ArenaError):  # gone by hand already
            if kind == "group":
                group = self.setup.groups[owner]
                tenant = self._robot(group.members[0]).tenant or DEFAULT_TENANT
                app.groups.delete(owner, tenant)
                return
            robot = app.manager.get(owner)
            if kind == "robot":
                await parts.delete_robot(app, robot)
            elif kind == "workspace":
                await robot.set_workspace(robot.model.workspace)
            elif kind == "slave":
                await robot.detach_slave(name, reason="no longer in the configuration file")
            elif kind == "camera":
                await app.cameras.detach(owner, name)
            elif kind == "master":
                master = robot.snapshot().master
                if master is not None and master.peer_id == self._masters.get(owner):
                    await robot.detach_master(master.peer_id)

    def _robot_up(self, robot_id: str) -> Robot:
        """The declared robot, made by the file: never a robot of that id made by hand while
        the file's could not be (its parts wait for it); `_Gone` once deleted by hand."""
        if ("robot", robot_id, "") in self.pending:
            raise ArenaError(ErrorCode.UNKNOWN_ROBOT, f"Robot {robot_id!r} is not up yet.")
        robot = self.app.manager.find(robot_id)
        if robot is None:
            raise _Gone
        return robot

    def _robot(self, robot_id: str) -> DeclaredRobot:
        return self.setup.robots[robot_id]

    # -- reports -----------------------------------------------------------------------------

    def pending_of(self, robot_id: str) -> list[dict[str, Any]]:
        """The robot's declared parts that are not up (for its details)."""
        now = trio.current_time()
        return [
            {
                "part": kind,
                "id": name or None,
                "error": pending.error,
                "attempts": pending.attempts,
                "retry_in": round(max(0.0, pending.next_try - now), 3),
            }
            for (kind, owner, name), pending in self.pending.items()
            if owner == robot_id and kind != "group"
        ]

    def not_ready(self) -> list[str]:
        """One sentence for each declared part not up (for `/readyz`)."""
        return [
            f"{_name(key)} is not up ({pending.error}); tried {pending.attempts} times"
            for key, pending in self.pending.items()
        ]

    def running(self) -> str:
        """The running setup in the file's form: the file's settings (no keys), every robot
        with the parts made from a body, by the file or by hand, and the declared parts
        still being tried; groups."""
        app = self.app
        robots: dict[str, DeclaredRobot] = {}
        for robot in app.manager.robots():
            robots[robot.robot_id] = self._live(robot)
        for robot_id, declared in self.setup.robots.items():
            if robot_id not in robots:  # not up yet: as declared
                robots[robot_id] = declared
        groups = {
            group.group_id: GroupBody(group.group_id, list(group.members), group.stop_together)
            for group in app.groups.all()
        }
        for key in self.pending:
            if key[0] == "group":
                groups[key[1]] = self.setup.groups[key[1]]
        settings = {k: v for k, v in self.setup.settings.items() if k not in SECRET_SETTINGS}
        notes = ["The running setup of Arena (GET /api/config): save it as the next boot's file."]
        if any(k in self.setup.settings for k in SECRET_SETTINGS):
            notes.append("api_keys and viewer_keys are left out: keep them in a key file.")
        return to_toml(settings, replace(self.setup, robots=robots, groups=groups), notes)

    def _live(self, robot: Robot) -> DeclaredRobot:
        app = self.app
        declared = self.setup.robots.get(robot.robot_id)
        pending = {key for key in self.pending if key[1] == robot.robot_id}

        def waiting(kind: str) -> Iterator[str]:
            return (name for k, owner, name in pending if k == kind)

        slaves = dict(app.parts.slaves_of(robot))
        cameras = {c.spec.name: parts.camera_body(c) for c in app.cameras.of(robot.robot_id)}
        master = app.parts.master_of(robot)
        if declared is not None:
            for slave_id in waiting("slave"):
                slaves[slave_id] = declared.slaves[slave_id]
            for name in waiting("camera"):
                cameras[name] = declared.cameras[name]
            if ("master", robot.robot_id, "") in pending:
                master = declared.master
        workspace = None
        if robot.workspace != robot.model.workspace:
            shown = {k: v for k, v in workspace_to_json(robot.workspace).items() if v is not None}
            workspace = msgspec.convert(shown, WorkspaceBody)
        snapshot = robot.snapshot()
        return DeclaredRobot(
            robot.robot_id,
            snapshot.robot_type,
            None if snapshot.name == robot.robot_id else snapshot.name,
            None if robot.tenant == DEFAULT_TENANT else robot.tenant,
            workspace,
            slaves,
            master,
            cameras,
        )


async def reload_on_sighup(declared: DeclaredSetup) -> None:
    """Reload the file on each SIGHUP; a file refused is said in the log, nothing changed."""
    with trio.open_signal_receiver(signal.SIGHUP) as signals:
        async for _ in signals:
            try:
                changes = await declared.reload()
            except ArenaError as error:
                log.error("SIGHUP: the file is refused, nothing changed: %s", error.message)
                continue
            log.info("SIGHUP: configuration reloaded: %s", changes)


def _name(key: PartKey) -> str:
    kind, owner, name = key
    if kind in ("robot", "group"):
        return f"{kind} {owner}"
    return f"robot {owner}: {kind}" + (f" {name}" if name else "")


def _reason(error: Exception) -> str:
    if isinstance(error, _Gone):
        return f"{ErrorCode.UNKNOWN_ROBOT}: its robot was deleted"
    if isinstance(error, ArenaError):
        return f"{error.code}: {error.message}"
    if isinstance(error, OSError):
        return f"{ErrorCode.INTERNAL_ERROR}: {error}"
    log.exception("a declared part failed")
    return f"{ErrorCode.INTERNAL_ERROR}: {type(error).__name__}"
