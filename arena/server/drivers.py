"""Drivers from their REST configs: `{"type": "mock-slave", ...}` -> a driver object. It lives in
the server because it composes every driver package with the recordings (replay), and turns each
validated body into the driver's own config (`drivers/config.py`): no driver sees a body."""

from __future__ import annotations

import importlib.util
import os
import re
from collections.abc import Iterator
from contextlib import contextmanager
from itertools import islice
from pathlib import Path

from arena.drivers.config import RemoteLinkConfig, UsbMasterConfig, UsbSlaveConfig
from arena.drivers.mock_slave import MockSlave, MockSlaveConfig
from arena.drivers.sequence_master import SequenceMaster
from arena.drivers.sequences import demo_sequences, get_sequence
from arena.drivers.servo_arm import family_of
from arena.extras import install_line
from arena.policy.master import CameraFrames, PolicyMaster, PolicySettings, Shot
from arena.policy.strategy import Episodic, Highlight, Sentry, Strategy, check_pose
from arena.protocol.errors import ArenaError, ErrorCode
from arena.protocol.rest import (
    DEFAULT_TENANT,
    FILE_NAME,
    EpisodicStrategy,
    HighlightStrategy,
    MasterBody,
    MockSlaveBody,
    PhysicsSlaveBody,
    PolicyMasterBody,
    RemoteLinkBody,
    RemoteServerBody,
    ReplayMasterBody,
    ScriptMasterBody,
    SentryStrategy,
    SequenceMasterBody,
    SlaveBody,
    StrategyBody,
    UsbMasterBody,
    UsbSlaveBody,
    WebSocketSlaveBody,
)
from arena.recording.mcap_file import read_recording
from arena.recording.recorder import existing_recording
from arena.recording.replay import ReplayMaster, pick_robot, recorded_commands
from arena.robot.handle import Robot
from arena.robot.links import MasterDriver, SlaveDriver
from arena.robot.model import RobotModel
from arena.script.master import ScriptMaster, ScriptSettings
from arena.sensors.camera import Cameras
from arena.servo.lerobot_calibration import is_lerobot_reference
from arena.servo.lerobot_calibration import resolve as resolve_lerobot


async def attach_rest_master(robot: Robot, driver: MasterDriver) -> str:
    """Attach a master asked for over REST; a refusal because the robot has a master says
    which field asks for takeover."""
    try:
        return await robot.attach_master(driver, master_id=getattr(driver, "master_id", None))
    except ArenaError as error:
        if error.code is ErrorCode.MASTER_ACTIVE:
            raise ArenaError(
                error.code, f'{error.message} Send "takeover": true in the body to do so.'
            ) from None
        raise


def tenant_folder(root: Path, tenant: str) -> Path:
    """A tenant's own folder of files it names (its calibrations, its policies):
    `root/<tenant>/`, the default tenant's `root` itself (where its files were before
    tenants). A tenant never reaches another's file by naming it."""
    if tenant == DEFAULT_TENANT:
        return root
    if tenant.startswith("."):  # (a tenant's name may hold dots: never `..`)
        raise ArenaError(ErrorCode.INVALID_CONFIG, f"Tenant {tenant!r} cannot have a folder.")
    return root / tenant


def outside_tenant_folder(what: str, value: str, anywhere: bool, instead: str) -> None:
    """A value that names a file outside the tenant's folder (a path): FORBIDDEN unless
    `anywhere` (the whole server's admin). Said before anything is looked up, in words that
    depend on nothing but the value: the answer never tells whether such a file exists."""
    if not anywhere:
        raise ArenaError(
            ErrorCode.FORBIDDEN,
            f"{what} {value!r} names a file outside this tenant's folder, which only an "
            f"admin of the default tenant with every robot in scope may; {instead}.",
        )


def in_tenant_folder(folder: Path, name: str, what: str) -> Path:
    """`folder/name` for a `name` of a file in the tenant's folder (no path, no `..`: the
    bodies' patterns say so already); FORBIDDEN if a symbolic link leads it out of the folder."""
    if "/" in name or "\x00" in name or name.startswith("."):
        raise ArenaError(ErrorCode.INVALID_VALUE, f"{what} {name!r} is not a file's name.")
    path = folder / name
    if not inside(path, folder):
        raise ArenaError(
            ErrorCode.FORBIDDEN,
            f"{what} {name!r} is a symbolic link out of this tenant's folder, which is never "
            "followed; put the file itself there.",
        )
    return path


def inside(path: Path, folder: Path) -> bool:
    """`path`, its symbolic links followed, lies in `folder` (itself resolved)."""
    return path.resolve().is_relative_to(folder.resolve())


def _calibration_file(
    folder: Path | None,
    name: str | None,
    robot_id: str,
    model: RobotModel,
    leader: bool = False,
    anywhere: bool = False,
) -> Path:
    """`folder/<name>.json`, or the LeRobot file a path or `lerobot:ID` names: only when
    `anywhere` (the whole server's admin), as it reads or overwrites any file of that form."""
    if name is not None and is_lerobot_reference(name):
        outside_tenant_folder("Calibration", name, anywhere, "give a calibration name instead")
        return resolve_lerobot(name, model.robot_type, family_of(model), leader=leader)
    file = f"{name or robot_id}.json"
    return in_tenant_folder(folder or Path("calibration"), file, "Calibration")


def usb_slave_config(body: UsbSlaveBody) -> UsbSlaveConfig:
    """A usb-slave's settings from its body."""
    return UsbSlaveConfig(
        body.port,
        body.baudRate,
        body.rate,
        body.estop,
        body.joinSpeed,
        dict(body.torqueLimit or {}),
        body.stallTime,
    )


def usb_master_config(body: UsbMasterBody) -> UsbMasterConfig:
    """A usb-master's settings from its body."""
    return UsbMasterConfig(body.port, body.baudRate, body.rate, body.deadband, body.actuated)


def remote_link_config(body: RemoteLinkBody, takeover: bool) -> RemoteLinkConfig:
    """A remote link's settings from its body (`takeover`: the body's, where it has one)."""
    return RemoteLinkConfig(
        url=body.url,
        robot_id=body.robotId,
        api_key=body.apiKey,
        heartbeat=body.heartbeat,
        reconnect_initial=body.reconnectInitial,
        reconnect_max=body.reconnectMax,
        takeover=takeover,
    )


def _mock_slave_config(body: MockSlaveBody) -> MockSlaveConfig:
    """A mock slave's settings from its body; delays and the error rate checked."""
    config = MockSlaveConfig(
        simulate_latency=body.simulateLatency,
        response_delay=body.responseDelay,
        simulate_errors=body.simulateErrors,
        error_rate=body.errorRate,
        seed=body.seed,
    )
    if not (0 <= config.simulate_latency <= 60_000 and 0 <= config.response_delay <= 60_000):
        raise ArenaError(ErrorCode.INVALID_CONFIG, "Delays must be between 0 and 60000 ms.")
    if not 0 <= config.error_rate <= 1:
        raise ArenaError(ErrorCode.INVALID_CONFIG, "errorRate must be between 0 and 1.")
    return config


def make_slave(
    body: SlaveBody,
    model: RobotModel | None = None,
    calibration_dir: Path | None = None,
    robot_id: str = "robot",
    *,
    calibration_anywhere: bool = False,
) -> SlaveDriver:
    """Build a slave driver from its config.

    Hardware slaves need the robot's `model`; their calibration file is
    `calibration_dir/<name>.json` (the robot's tenant's folder: `calibration_folder`), the
    name defaulting to `robot_id`; a path or `lerobot:ID` only with `calibration_anywhere`.
    """
    if isinstance(body, UsbSlaveBody):
        from arena.drivers.usb_slave import UsbSlave

        if model is None:
            raise ArenaError(ErrorCode.INVALID_CONFIG, "A usb-slave needs the robot's model.")
        calibration = _calibration_file(
            calibration_dir, body.calibration, robot_id, model, anywhere=calibration_anywhere
        )
        slave = UsbSlave(usb_slave_config(body), model, calibration)
        slave.holder = f"the usb-slave of robot {robot_id!r}"
        return slave
    if isinstance(body, PhysicsSlaveBody):
        from arena.drivers.physics import PhysicsSettings, PhysicsSlave
        from arena.extras import require

        require("physics", "A physics-slave")  # here, not when the driver starts: a 501, no 201
        return PhysicsSlave(
            PhysicsSettings(rate=body.rate, estop=body.estop, realtime=body.realtime)
        )
    if isinstance(body, MockSlaveBody):
        return MockSlave(_mock_slave_config(body))
    if isinstance(body, WebSocketSlaveBody):
        from arena.drivers.remote import WebSocketSlave

        if body.robotId is None:
            raise ArenaError(
                ErrorCode.INVALID_CONFIG, "A websocket-slave needs the remote robotId."
            )
        return WebSocketSlave(remote_link_config(body, body.takeover))
    # (the type's name only: a config may hold an API key, which must not reach any log)
    raise ArenaError(ErrorCode.INVALID_CONFIG, f"Unsupported slave type {type(body).__name__}.")


@contextmanager
def _about(field: str) -> Iterator[None]:
    """Errors raised inside name the body's `field` they are about."""
    try:
        yield
    except ArenaError as error:
        raise ArenaError(error.code, f"`{field}`: {error.message}") from None


def _replay(body: ReplayMasterBody, recordings: Path) -> ReplayMaster:
    """A replay of `body.recording`; every refusal names the field it is about."""
    if body.start is not None and body.end is not None and body.end <= body.start:
        raise ArenaError(
            ErrorCode.INVALID_VALUE, f"`end` ({body.end} s) must be after `start` ({body.start} s)."
        )
    with _about("recording"):
        recording = read_recording(existing_recording(recordings, body.recording))
    source = pick_robot(recording, body.source_robot, named="`source_robot`")
    with _about("source_robot"):
        commands = recorded_commands(recording, source, body.start, body.end)
    if not commands:
        raise ArenaError(
            ErrorCode.INVALID_VALUE,
            f"`start`/`end`: {body.recording} holds no command of {source!r} from "
            f"{body.start or 0} s to {'the end' if body.end is None else f'{body.end} s'}.",
        )
    return ReplayMaster(commands, speed=body.speed, loop=body.loop, name=body.recording)


def camera_frames(cameras: Cameras, robot_id: str) -> CameraFrames:
    """The newest frame of each camera of robot `robot_id`, as a policy master reads them."""

    def frames() -> dict[str, Shot | None]:
        return {
            camera.spec.name: None
            if camera.latest is None
            else Shot(camera.latest.jpeg, camera.latest.time)
            for camera in cameras.of(robot_id)
        }

    return frames


#: Entries of a policy's folder looked at for links out of the tenant's folder (LeRobot saves
#: about eight files): a folder with more is refused rather than read for long.
MAX_POLICY_ENTRIES = 1000


def policy_folder(value: str, folder: Path | None, anywhere: bool) -> Path:
    """The folder a policy master's `path` means, made whole (every answer and log line
    names it in full). A name (`FILE_NAME`) is a folder of the tenant's policy folder
    `folder`, neither it nor any file in it a symbolic link out of that folder; anything
    else is a path on the server's machine (a relative one from the folder the server started
    in), only for the whole server's admin (`anywhere`). Runs off the loop (it reads the
    disk)."""
    if not re.fullmatch(FILE_NAME, value):
        outside_tenant_folder("Policy", value, anywhere, "give the name of a policy's folder")
        return Path(value).expanduser().absolute()
    folder = folder or Path("policies")
    path = in_tenant_folder(folder, value, "Policy")
    if not (path / "config.json").is_file():  # (nothing else: another tenant's folder is not one)
        raise ArenaError(
            ErrorCode.POLICY_INVALID,
            f"No policy {value!r} in this tenant's policy folder {folder}: a policy is a "
            f"folder of its own there ({folder / value}/config.json, model.safetensors and "
            "its processors' files, as LeRobot saves them).",
        )
    with os.scandir(path) as entries:
        listed = list(islice(entries, MAX_POLICY_ENTRIES + 1))
    if len(listed) > MAX_POLICY_ENTRIES:
        raise ArenaError(
            ErrorCode.POLICY_INVALID,
            f"Policy {value!r}: more than {MAX_POLICY_ENTRIES} files in its folder.",
        )
    for entry in listed:
        if entry.is_symlink() and not inside(Path(entry.path), folder):
            raise ArenaError(
                ErrorCode.FORBIDDEN,
                f"Policy {value!r}: {entry.name} is a symbolic link out of this tenant's "
                "folder, which is never followed; put the file itself there.",
            )
    return path.absolute()


def _policy(
    body: PolicyMasterBody,
    model: RobotModel | None,
    cameras: CameraFrames,
    folder: Path | None,
    anywhere: bool,
    python: str | None,
) -> PolicyMaster:
    path = policy_folder(body.path, folder, anywhere)  # first: a refusal tells nothing more
    if body.python is not None:
        if not anywhere:
            raise ArenaError(
                ErrorCode.FORBIDDEN,
                '"python" names a program for the server to run, which only an admin of the '
                "default tenant with every robot in scope may; leave it out (the server's own "
                "policy Python runs the worker).",
            )
        if not (os.path.isfile(body.python) and os.access(body.python, os.X_OK)):
            raise ArenaError(
                ErrorCode.INVALID_VALUE,
                f'"python" {body.python!r} is not a program on the server: give the path of '
                "a Python with LeRobot, torch and msgspec.",
            )
        python = body.python
    if model is None:
        raise ArenaError(ErrorCode.INVALID_CONFIG, "A policy master needs the robot's model.")
    # Looked for, not imported: LeRobot and torch belong in the worker, never in the server
    # (a worker in a Python of the user's has its own).
    if python is None and importlib.util.find_spec("lerobot") is None:
        raise ArenaError(
            ErrorCode.NOT_INSTALLED,
            f"A policy master needs LeRobot, which is not installed: {install_line('lerobot')}",
        )
    rate = body.fps * body.interpolation_multiplier
    if rate > model.safety.command_rate:
        raise ArenaError(
            ErrorCode.INVALID_CONFIG,
            f"fps times interpolation_multiplier is {rate:g} commands/s, over the robot's "
            f"command rate ({model.safety.command_rate:g}/s): lower one of them.",
        )
    settings = PolicySettings(
        path=path,
        task=body.task,
        fps=body.fps,
        actions_per_chunk=body.actions_per_chunk,
        chunk_size_threshold=body.chunk_size_threshold,
        aggregate_fn_name=body.aggregate_fn_name,
        max_relative_target=body.max_relative_target,
        stall_periods=body.stall_periods,
        environment_state=tuple(body.environment_state),
        blend_steps=body.blend_steps,
        interpolation_multiplier=body.interpolation_multiplier,
        python=python,
        strategy=_strategy(body.strategy, model),
    )
    return PolicyMaster(settings, model, cameras)


def script_file(value: str, folder: Path) -> Path:
    """The script a script master's `path` names: a `.py` file of the tenant's scripts folder
    `folder`, neither a path nor a symbolic link out of the folder (FORBIDDEN, for everyone: a
    script is code, and only what the server's owner put in the folder runs). Runs off the
    loop (it reads the disk)."""
    if not re.fullmatch(FILE_NAME, value):
        raise ArenaError(
            ErrorCode.FORBIDDEN,
            f"Script {value!r} is not the name of a file in this tenant's scripts folder: a "
            "script is code, and only a file the server's owner put there runs (give its "
            "name, e.g. pick.py).",
        )
    if not value.endswith(".py"):
        raise ArenaError(
            ErrorCode.SCRIPT_INVALID, f"Script {value!r}: a script's name ends in .py."
        )
    path = in_tenant_folder(folder, value, "Script")
    if not path.is_file():
        raise ArenaError(
            ErrorCode.SCRIPT_INVALID,
            f"No script {value!r} in this tenant's scripts folder {folder}: put the file there "
            f"({folder / value}).",
        )
    return path.resolve()


def _strategy(body: StrategyBody | None, model: RobotModel) -> Strategy | None:
    """A policy's rollout strategy from its body; a start pose is checked against the robot
    (INVALID_VALUE naming the joint)."""
    if body is not None and not body.task.strip():
        raise ArenaError(
            ErrorCode.INVALID_VALUE,
            '"strategy.task" must say what its episodes show (it is blank).',
        )
    if isinstance(body, EpisodicStrategy):
        pose = None
        if body.start_pose is not None:
            names = [joint.name for joint in model.joints]
            limits = {joint.name: (joint.lower, joint.upper) for joint in model.joints}
            # A joint's alias names it too, as in a command.
            canonical = {}
            for name, value in body.start_pose.items():
                joint = model.joint(name)
                canonical[joint.name if joint is not None else name] = value
            check_pose(names, limits, canonical)
            pose = canonical
        return Episodic(body.episodes, body.episode_s, body.task.strip(), body.reset_s, pose)
    if isinstance(body, SentryStrategy):
        return Sentry(body.episode_s, body.task.strip())
    if isinstance(body, HighlightStrategy):
        return Highlight(body.keep_s, body.task.strip())
    return None


def make_master(
    body: MasterBody,
    recordings: Path | None = None,
    model: RobotModel | None = None,
    calibration_dir: Path | None = None,
    robot_id: str = "robot",
    cameras: CameraFrames = dict,
    anywhere: bool = False,
    policy_dir: Path | None = None,
    policy_python: str | None = None,
    script_dir: Path | None = None,
) -> MasterDriver:
    """Build a master driver from its config (`recordings`: where replay finds its files;
    a leader arm's calibration is `calibration_dir/<name>.json`, default `<robot_id>-leader`,
    a path or `lerobot:ID` only with `anywhere` (as `make_slave`); `cameras`: the robot's
    newest frames, for a policy, which is a folder of `policy_dir` (the robot's tenant's
    folder: `tenant_folder`), a path only with `anywhere`), run by `policy_python` (None:
    Arena's own Python); a script is a file of `script_dir` (the tenant's folder too). It
    takes over from the robot's master only if the config asks (`takeover`)."""
    if isinstance(body, PolicyMasterBody):
        driver: MasterDriver = _policy(body, model, cameras, policy_dir, anywhere, policy_python)
    elif isinstance(body, ScriptMasterBody):
        path = script_file(body.path, script_dir or Path("scripts"))
        if model is None:
            raise ArenaError(ErrorCode.INVALID_CONFIG, "A script master needs the robot's model.")
        driver = ScriptMaster(ScriptSettings(path), model)  # (its hand_mover: the caller's)
    else:
        driver = _master(body, recordings, model, calibration_dir, robot_id, anywhere)
    driver.takes_over = body.takeover
    return driver


def _master(
    body: MasterBody,
    recordings: Path | None,
    model: RobotModel | None,
    calibration_dir: Path | None,
    robot_id: str,
    calibration_anywhere: bool,
) -> MasterDriver:
    if isinstance(body, UsbMasterBody):
        from arena.drivers.usb_master import UsbMaster

        if model is None:
            raise ArenaError(ErrorCode.INVALID_CONFIG, "A usb-master needs the robot's model.")
        name = body.calibration or f"{robot_id}-leader"
        master = UsbMaster(
            usb_master_config(body),
            model,
            _calibration_file(
                calibration_dir, name, robot_id, model, True, anywhere=calibration_anywhere
            ),
        )
        master.holder = f"the usb-master of robot {robot_id!r}"
        return master
    if isinstance(body, ReplayMasterBody):
        if recordings is None:
            raise ArenaError(ErrorCode.INVALID_CONFIG, "This server keeps no recordings.")
        return _replay(body, recordings)
    if isinstance(body, SequenceMasterBody):
        ids = body.sequences if body.sequences else list(demo_sequences())
        sequences = [get_sequence(i) for i in ids]
        if model is not None:
            for sequence in sequences:
                sequence.check_against(model)
        return SequenceMaster(sequences, loop=body.loop, auto_start=body.autoStart)
    if isinstance(body, RemoteServerBody):
        from arena.drivers.remote import RemoteServerMaster

        return RemoteServerMaster(remote_link_config(body, body.takeover), robot_id)
    raise ArenaError(ErrorCode.INVALID_CONFIG, f"Unsupported master type {type(body).__name__}.")
