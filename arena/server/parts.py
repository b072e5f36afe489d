"""Robots and their parts made from their bodies: the one way, for REST and for the declared
setup of the configuration file (`arena.server.declared`, specs/declared-setup.md). Each
function does what its REST route does once the request is read; the routes call them, and so
does the declared setup, so a robot from the file is built exactly as one made by hand.

`arena.server.base.Parts` remembers the body each live part was made from, whoever made it, so that
`GET /api/config` can write the running setup back in the file's form.
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import TYPE_CHECKING

import msgspec
import trio

from arena.policy.master import PolicyMaster
from arena.protocol.errors import ArenaError, ErrorCode
from arena.protocol.rest import (
    DEFAULT_TENANT,
    CameraBody,
    CreateRobotBody,
    GroupBody,
    MasterBody,
    PolicyMasterBody,
    ReplayMasterBody,
    SlaveBody,
    WorkspaceBody,
)
from arena.robot.groups import Group
from arena.robot.handle import Robot
from arena.robot.workspace import Workspace, workspace_from_json, workspace_to_json
from arena.sensors.camera import Camera, CameraSpec, Opener
from arena.server.auth import refuse
from arena.server.drivers import (
    attach_rest_master,
    camera_frames,
    make_master,
    make_slave,
    tenant_folder,
)
from arena.server.identity import Principal, Role
from arena.server.planned_moves import equip_script
from arena.server.recordings_api import off_the_loop

if TYPE_CHECKING:
    from arena.server.base import ArenaApp

#: Who the configuration file acts as: the whole server's admin (it names any file).
FILE_PRINCIPAL = Principal("configuration file", Role.ADMIN, DEFAULT_TENANT)


async def create_robot(app: ArenaApp, principal: Principal, body: CreateRobotBody) -> Robot:
    """`POST /api/robots`: the fleet, the caller's tenant and scope and the tenant's robot
    count checked, then the robot created."""
    if app.fleet is not None and body.id is not None:
        owner = await app.fleet.owner_elsewhere(body.id)
        if owner is not None:
            raise ArenaError(
                ErrorCode.ROBOT_ELSEWHERE,
                f"Robot id {body.id!r} is taken in fleet {app.fleet.fleet!r}: node "
                f"{owner!r} owns it.",
            )
    tenant = body.tenant or principal.tenant
    if principal is not FILE_PRINCIPAL and (
        tenant != principal.tenant or not (body.id is None or principal.covers(body.id))
    ):
        refuse(app, "scope")
        raise ArenaError(
            ErrorCode.FORBIDDEN,
            f"{principal.name!r} may create robots of tenant {principal.tenant!r} only"
            + ("" if principal.robots is None else f", with ids like {principal.robots}")
            + ".",
        )
    if principal.robots is not None and body.id is None:
        raise ArenaError(ErrorCode.INVALID_BODY, 'Give the robot an "id" within your scope.')
    most = app.arena_config.max_robots
    if sum(robot.tenant == tenant for robot in app.manager.robots()) >= most:
        raise ArenaError(
            ErrorCode.LIMIT_REACHED,
            f"Tenant {tenant!r} has {most} robots, the most allowed (max_robots): "
            "delete one first.",
        )
    app.parts.forget(body.id or "")  # (a robot of that id deleted earlier)
    return await app.manager.create_robot(body.robot_type, body.name, body.id, tenant=tenant)


async def delete_robot(app: ArenaApp, robot: Robot) -> None:
    """`DELETE /api/robots/{id}`: its drivers stopped, the robot forgotten (its past stays
    its tenant's)."""
    app.access.tenants[robot.robot_id] = robot.tenant
    await app.manager.delete(robot.robot_id)
    app.metrics.retire(robot)
    app.parts.forget(robot.robot_id)
    app.sim_leaders.forget(robot.robot_id)


async def attach_slave(
    app: ArenaApp,
    robot: Robot,
    body: SlaveBody,
    anywhere: bool,
    slave_id: str | None = None,
) -> str:
    """`POST /api/robots/{id}/slaves`: the driver built, its hardware opened (a missing or
    busy port raises here, before anything is attached), then attached; its id."""
    driver = make_slave(
        body,
        robot.model,
        tenant_folder(Path(app.arena_config.calibration_dir), robot.tenant),
        robot.robot_id,
        calibration_anywhere=anywhere,
    )
    prepare = getattr(driver, "prepare", None)
    if prepare is not None:
        await prepare()
    slave_id = await robot.attach_slave(driver, slave_id)
    app.hardware.add(robot.robot_id, slave_id, driver)
    app.parts.slaves.setdefault(robot.robot_id, {})[slave_id] = body
    return slave_id


async def attach_master(app: ArenaApp, robot: Robot, body: MasterBody, anywhere: bool) -> str:
    """`POST /api/robots/{id}/master`: the driver built (a replay reads its recording in a
    thread), its hardware opened unless another master holds the robot and the body does not
    take over, then attached; its id. (A replay's recording is checked by the caller.)"""
    driver = await off_the_loop(
        make_master,
        body,
        app.recorder.folder,
        robot.model,
        tenant_folder(Path(app.arena_config.calibration_dir), robot.tenant),
        robot.robot_id,
        camera_frames(app.cameras, robot.robot_id),
        anywhere,
        tenant_folder(Path(app.arena_config.policy_dir), robot.tenant),
        app.arena_config.policy_python,
        tenant_folder(Path(app.arena_config.script_dir), robot.tenant),
    )
    equip_script(app, driver)
    if isinstance(body, PolicyMasterBody) and body.strategy is not None:
        running = robot.episodes.active
        if running is not None:  # said before the policy loads
            raise ArenaError(
                ErrorCode.EPISODE_ACTIVE,
                f"Episode {running.index} is running: a rollout strategy makes its own "
                "episodes; stop or discard it first.",
            )
        if isinstance(driver, PolicyMaster):
            driver.keeper = app.recorder.keeper(robot.robot_id)
    prepare = getattr(driver, "prepare", None)
    if prepare is not None:
        holder = robot.snapshot().master
        if holder is not None and not driver.takes_over:
            raise ArenaError(  # say so before opening any hardware
                ErrorCode.MASTER_ACTIVE,
                f"Master {holder.peer_id!r} already drives this robot. "
                'Send "takeover": true in the body to replace it.',
            )
        await prepare()
    try:
        master_id = await attach_rest_master(robot, driver)
    except BaseException:
        close = getattr(driver, "close", None)
        if close is not None:
            await close()  # refused (another master holds the robot): free the port
        raise
    app.sim_leaders.follow(robot, master_id, driver)
    if not isinstance(body, ReplayMasterBody):  # (a replay is an act, not a part)
        app.parts.masters[robot.robot_id] = (master_id, body)
    return master_id


async def attach_camera(app: ArenaApp, robot: Robot, body: CameraBody) -> Camera:
    """`POST /api/robots/{id}/cameras`: its source opened first (a wrong device raises
    here), then started."""
    spec = CameraSpec.of(body.name, body.source, body.fps, body.width, body.height)
    opener = None
    if spec.twin is not None:
        spec.check()  # a bad body is refused before the twin is looked for
        opener = await twin_opener(app, robot, spec, spec.twin)
    return await app.cameras.attach(robot, spec, opener)


#: How long a twin camera waits for a physics slave just attached to build its simulation.
TWIN_READY_TIMEOUT = 10.0


async def twin_opener(app: ArenaApp, robot: Robot, spec: CameraSpec, slave_id: str) -> Opener:
    """How to open a camera of the robot's physics slave (NO_TWIN when it has none)."""
    from arena.drivers.twin_camera import twin_recipe

    attached = {slave.peer_id for slave in robot.snapshot().slaves}
    twin = app.hardware.twin(robot.robot_id, slave_id, attached)
    with trio.move_on_after(TWIN_READY_TIMEOUT):
        await twin.ready.wait()
    return functools.partial(twin_recipe, twin, spec.width, spec.height, spec.fps)


def camera_body(camera: Camera) -> CameraBody:
    """The body that makes the camera again."""
    spec = camera.spec
    return CameraBody(spec.name, spec.source, spec.fps, spec.width, spec.height)


async def set_workspace(
    robot: Robot, body: WorkspaceBody, base: Workspace | None = None
) -> Workspace:
    """`PUT /api/robots/{id}/workspace` (`base`: what a field left out keeps; REST gives the
    robot type's own, so a body of boxes alone keeps the type's table); a declared setup's
    workspace (no base: what is left out is none, as TOML has no null)."""
    data = msgspec.to_builtins(body)
    if base is not None:
        data = {**workspace_to_json(base), **data}
    try:
        workspace = workspace_from_json(data)
    except ValueError as exc:
        raise ArenaError(ErrorCode.INVALID_BODY, f"Invalid workspace: {exc}.") from None
    await robot.set_workspace(workspace)
    return workspace


def create_group(app: ArenaApp, body: GroupBody, tenant: str) -> Group:
    """`POST /api/groups` (the caller's sight of each member checked by the caller)."""
    most = app.arena_config.max_groups
    if len(app.groups.all(tenant)) >= most and app.groups.find(body.id, tenant) is None:
        raise ArenaError(
            ErrorCode.LIMIT_REACHED,
            f"Tenant {tenant!r} has {most} groups, the most allowed (max_groups): "
            "delete one first.",
        )
    return app.groups.create(body.id, body.members, body.stopTogether, tenant)
