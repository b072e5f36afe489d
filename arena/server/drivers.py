"""Drivers from their REST configs: `{"type": "mock-slave", ...}` -> a driver object. It lives in
the server because it composes every driver package with the recordings (replay), and turns each
validated body into the driver's own config (`drivers/config.py`): no driver sees a body."""

from __future__ import annotations

import importlib.util
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from arena.drivers.config import RemoteLinkConfig, UsbMasterConfig, UsbSlaveConfig
from arena.drivers.mock_slave import MockSlave, MockSlaveConfig
from arena.drivers.sequence_master import SequenceMaster
from arena.drivers.sequences import demo_sequences, get_sequence
from arena.drivers.servo_arm import family_of
from arena.extras import install_line
from arena.policy.master import CameraFrames, PolicyMaster, PolicySettings, Shot
from arena.protocol.errors import ArenaError, ErrorCode
from arena.protocol.rest import (
    DEFAULT_TENANT,
    MasterBody,
    MockSlaveBody,
    PhysicsSlaveBody,
    PolicyMasterBody,
    RemoteLinkBody,
    RemoteServerBody,
    ReplayMasterBody,
    SequenceMasterBody,
    SlaveBody,
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


def calibration_folder(root: Path, tenant: str) -> Path:
    """A tenant's calibration files: `root/<tenant>/` (the default tenant's are `root`
    itself, where they were before tenants). A tenant never reads another's by naming it."""
    if tenant == DEFAULT_TENANT:
        return root
    if tenant.startswith("."):  # (a tenant's name may hold dots: never `..`)
        raise ArenaError(
            ErrorCode.INVALID_CONFIG, f"Tenant {tenant!r} cannot have a calibration folder."
        )
    return root / tenant


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
        if not anywhere:
            raise ArenaError(
                ErrorCode.FORBIDDEN,
                f"Calibration {name!r}: a path or `lerobot:` names a file outside this "
                "tenant's calibration folder, which only an admin of the default tenant with "
                "every robot in scope may; give a calibration name instead.",
            )
        return resolve_lerobot(name, model.robot_type, family_of(model), leader=leader)
    return (folder or Path("calibration")) / f"{name or robot_id}.json"


def usb_slave_config(body: UsbSlaveBody) -> UsbSlaveConfig:
    """A usb-slave's settings from its body."""
    return UsbSlaveConfig(body.port, body.baudRate, body.rate, body.estop, body.joinSpeed)


def usb_master_config(body: UsbMasterBody) -> UsbMasterConfig:
    """A usb-master's settings from its body."""
    return UsbMasterConfig(body.port, body.baudRate, body.rate, body.deadband)


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


def _policy(
    body: PolicyMasterBody, model: RobotModel | None, cameras: CameraFrames
) -> PolicyMaster:
    if model is None:
        raise ArenaError(ErrorCode.INVALID_CONFIG, "A policy master needs the robot's model.")
    # Looked for, not imported: LeRobot and torch belong in the worker, never in the server.
    if importlib.util.find_spec("lerobot") is None:
        raise ArenaError(
            ErrorCode.NOT_INSTALLED,
            f"A policy master needs LeRobot, which is not installed: {install_line('lerobot')}",
        )
    settings = PolicySettings(
        # On the server's machine: a relative path from the folder the server started in,
        # made whole here so that every answer and log line names the folder it means.
        path=Path(body.path).expanduser().absolute(),
        task=body.task,
        fps=body.fps,
        actions_per_chunk=body.actions_per_chunk,
        chunk_size_threshold=body.chunk_size_threshold,
        aggregate_fn_name=body.aggregate_fn_name,
        max_relative_target=body.max_relative_target,
        stall_periods=body.stall_periods,
        environment_state=tuple(body.environment_state),
    )
    return PolicyMaster(settings, model, cameras)


def make_master(
    body: MasterBody,
    recordings: Path | None = None,
    model: RobotModel | None = None,
    calibration_dir: Path | None = None,
    robot_id: str = "robot",
    cameras: CameraFrames = dict,
    calibration_anywhere: bool = False,
) -> MasterDriver:
    """Build a master driver from its config (`recordings`: where replay finds its files;
    a leader arm's calibration is `calibration_dir/<name>.json`, default `<robot_id>-leader`,
    a path or `lerobot:ID` only with `calibration_anywhere` (as `make_slave`); `cameras`:
    the robot's newest frames, for a policy). It takes over from the robot's master only if
    the config asks (`takeover`)."""
    driver = _master(
        body, recordings, model, calibration_dir, robot_id, cameras, calibration_anywhere
    )
    driver.takes_over = body.takeover
    return driver


def _master(
    body: MasterBody,
    recordings: Path | None,
    model: RobotModel | None,
    calibration_dir: Path | None,
    robot_id: str,
    cameras: CameraFrames,
    calibration_anywhere: bool,
) -> MasterDriver:
    if isinstance(body, PolicyMasterBody):
        return _policy(body, model, cameras)
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
