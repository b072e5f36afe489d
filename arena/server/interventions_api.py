"""REST for pausing a robot's master and for interventions: a human corrects a running master
(a policy, a sequence, a replay) and hands the robot back (specs/safety-state-machine.md, "Pause,
resume and intervention").

`POST .../master/pause` and `.../master/resume` pause and resume whichever master drives.
`POST .../intervention` pauses it and lets another drive: the master its body configures (a
leader arm, say), or with `{}` the caller itself over `PUT .../joints`; `DELETE
.../intervention` hands back. Every refusal comes from the robot's safety table.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from quart import Blueprint, current_app, g

from arena.protocol.errors import ArenaError, ErrorCode
from arena.protocol.rest import HandBackBody, InterventionBody, MasterBody, ReplayMasterBody
from arena.robot import safety
from arena.robot.handle import Robot
from arena.robot.links import MasterDriver
from arena.server import convert
from arena.server.access import server_admin
from arena.server.base import ArenaApp, read_body
from arena.server.drivers import camera_frames, make_master, tenant_folder
from arena.server.manual import OPERATOR_KIND, operator_id
from arena.server.planned_moves import equip_script
from arena.server.recordings_api import off_the_loop, readable_recording

blueprint = Blueprint("interventions", __name__)


def _app() -> ArenaApp:
    return current_app  # type: ignore[return-value]


def _answer(outcome: safety.Outcome) -> None:
    """A refusal of the safety table as the caller's error."""
    if isinstance(outcome, safety.Refused):
        raise ArenaError(outcome.code, outcome.message)


async def build_master(app: ArenaApp, robot: Robot, body: MasterBody) -> MasterDriver:
    """The master driver a REST body configures, as `POST .../master` builds it (a replay's
    recording read off the loop)."""
    if isinstance(body, ReplayMasterBody):
        await readable_recording(app, g.principal, body.recording, field="recording")
    driver: MasterDriver = await off_the_loop(
        make_master,
        body,
        app.recorder.folder,
        robot.model,
        tenant_folder(Path(app.arena_config.calibration_dir), robot.tenant),
        robot.robot_id,
        camera_frames(app.cameras, robot.robot_id),
        server_admin(g.principal),  # the whole server's admin: any calibration, any policy
        tenant_folder(Path(app.arena_config.policy_dir), robot.tenant),
        app.arena_config.policy_python,
        tenant_folder(Path(app.arena_config.script_dir), robot.tenant),
    )
    equip_script(app, driver)
    return driver


@blueprint.post("/api/robots/<robot_id>/master/pause")
async def pause(robot_id: str) -> dict[str, Any]:
    """Pause the robot's master: it sends nothing, the robot holds where it is."""
    robot = _app().manager.get(robot_id)
    _answer(await robot.pause())
    return convert.robot_status(robot)


@blueprint.post("/api/robots/<robot_id>/master/resume")
async def resume(robot_id: str) -> dict[str, Any]:
    """Resume the paused master (a policy from a fresh observation)."""
    robot = _app().manager.get(robot_id)
    _answer(await robot.resume())
    return convert.robot_status(robot)


@blueprint.post("/api/robots/<robot_id>/intervention")
async def intervene(robot_id: str) -> tuple[dict[str, Any], int]:
    """Pause the running master and let another drive: the master `master` configures, or
    the caller over `PUT .../joints`."""
    app = _app()
    robot = app.manager.get(robot_id)
    body: InterventionBody = await read_body(InterventionBody, optional=True)
    _check_can_intervene(robot)  # before any hardware is opened or any policy loaded
    if body.master is None:
        link = await robot.connect_master(
            operator_id(g.principal),
            kind=OPERATOR_KIND,
            description=f"operator {g.principal.audit_name()!r} over REST",
            intervene=True,
        )
        return _intervention(robot, link.master_id), 201
    driver = await build_master(app, robot, body.master)
    prepare = getattr(driver, "prepare", None)
    if prepare is not None:
        await prepare()  # hardware, a policy's weights: the caller's error, now
    try:
        master_id = await robot.attach_master(
            driver, master_id=getattr(driver, "master_id", None), intervene=True
        )
    except BaseException:
        close = getattr(driver, "close", None)
        if close is not None:
            await close()
        raise
    app.sim_leaders.follow(robot, master_id, driver)
    return _intervention(robot, master_id), 201


@blueprint.delete("/api/robots/<robot_id>/intervention")
async def hand_back(robot_id: str) -> dict[str, Any]:
    """End the intervention; the paused master resumes unless `{"resume": false}`."""
    robot = _app().manager.get(robot_id)
    body: HandBackBody = await read_body(HandBackBody, optional=True)
    _answer(await robot.end_intervention(body.resume))
    return convert.robot_status(robot)


def _check_can_intervene(robot: Robot) -> None:
    """NO_MASTER or INTERVENTION_ACTIVE said at once (the robot's table decides again)."""
    snapshot = robot.snapshot()
    if snapshot.paused_master is not None and snapshot.master is not None:
        raise ArenaError(
            ErrorCode.INTERVENTION_ACTIVE,
            f"Master {snapshot.master.peer_id!r} is intervening while "
            f"{snapshot.paused_master.peer_id!r} waits: end the intervention first.",
        )
    if snapshot.master is None:
        raise ArenaError(
            ErrorCode.NO_MASTER, "The robot has no master to pause, resume or correct."
        )


def _intervention(robot: Robot, master_id: str) -> dict[str, Any]:
    status = convert.robot_status(robot)
    return {"intervening": master_id} | status
