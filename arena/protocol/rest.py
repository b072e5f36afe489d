"""REST request bodies, as typed structs (validated at the edge; exported to OpenAPI)."""

from __future__ import annotations

from typing import Annotated, Literal, TypeAlias

import msgspec

from arena.protocol.messages import JointValue, MoveData

#: The tenant of API keys, of robots created without one, and of tokens without the claim.
DEFAULT_TENANT = "default"
#: A tenant is a plain name (it also names its recording files).
TENANT_PATTERN = r"^[A-Za-z0-9_.-]{1,64}$"


#: A robot's id: 1-64 letters, digits, '.', '_' or '-', starting with a letter or digit.
RobotId = Annotated[str, msgspec.Meta(pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")]
#: A robot's display name: one line of 1-128 characters (no control characters).
RobotName = Annotated[
    str, msgspec.Meta(min_length=1, max_length=128, pattern=r"^[^\x00-\x1f\x7f]*$")
]


class CreateRobotBody(msgspec.Struct, omit_defaults=True, forbid_unknown_fields=True):
    """`POST /api/robots`: a robot type, a display name and, optionally, the id to use and
    the tenant it belongs to (default: the caller's, `default` for API keys)."""

    robot_type: str = "so-arm100"
    name: RobotName | None = None
    id: RobotId | None = None
    tenant: Annotated[str, msgspec.Meta(pattern=TENANT_PATTERN)] | None = None


#: Seconds a REST move may be waited for (`wait`).
MAX_WAIT = 120.0


class JointsBody(msgspec.Struct, omit_defaults=True, forbid_unknown_fields=True):
    """`PUT /api/robots/{id}/joints`: manual control. `duration` is in milliseconds. `wait`:
    seconds to hold the answer until the arm is on its goals (`arrived`), a collision stop or
    an e-stop ends the move short (COLLISION, ESTOPPED), or the time runs out (`arrived`
    false, and `why`); absent: answered at acceptance."""

    joints: list[JointValue]
    duration: float | None = None
    wait: Annotated[float, msgspec.Meta(gt=0, le=MAX_WAIT)] | None = None


class ReasonBody(msgspec.Struct, omit_defaults=True, forbid_unknown_fields=True):
    """An optional reason (e-stop)."""

    reason: str | None = None


class MockSlaveBody(
    msgspec.Struct,
    tag="mock-slave",
    tag_field="type",
    omit_defaults=True,
    forbid_unknown_fields=True,
):
    """A simulated arm. Delays in milliseconds."""

    simulateLatency: float = 0.0
    responseDelay: float = 0.0
    simulateErrors: bool = False
    errorRate: float = 0.1
    seed: int = 0


#: The fastest joining speed (deg/s) a slave or a robot type may ask for: joining is slow.
MAX_JOIN_SPEED = 90.0
#: A joint's name as a key of a per-joint setting (the robot type decides which exist).
JointKey = Annotated[str, msgspec.Meta(min_length=1, max_length=64)]
#: Percent of a servo's full torque: above 0 (a servo given none cannot hold itself up).
TorquePercent = Annotated[float, msgspec.Meta(gt=0, le=100)]
MAX_TORQUE_LIMITS = 32  # joints a `torqueLimit` may name

#: A name of a file or folder in a tenant's folder (a calibration, a policy): letters,
#: digits, `_-.`, not starting with a dot (so never `..`, never a path).
FILE_NAME = r"[A-Za-z0-9_-][A-Za-z0-9_.-]{0,63}"

#: A calibration: a file's name (`FILE_NAME`), or a LeRobot calibration file: `lerobot:ID`
#: (found in LeRobot's folder) or a path ending in `.json`.
CalibrationName = Annotated[
    str,
    msgspec.Meta(
        pattern=rf"^({FILE_NAME}|lerobot:{FILE_NAME}|[^\x00-\x1f]*\.json)$",
        max_length=1024,
    ),
]


class UsbSlaveBody(
    msgspec.Struct,
    tag="usb-slave",
    tag_field="type",
    omit_defaults=True,
    forbid_unknown_fields=True,
):
    """An arm on a servo bus (its family the robot type's). No `port`: find the adapter by USB
    id; no `baudRate`: the robot type's.

    `estop`: what the servos do on an e-stop, `hold` (torque kept, goal = present) or
    `torque-off`. `calibration`: the calibration's name (default: the robot's id).
    `joinSpeed`: deg/s at which the arm is brought to the robot's pose when it joins a robot
    that is elsewhere (default: the robot type's `join_speed`). `torqueLimit`: percent of full
    torque per joint (over the robot type's caps: its gripper's). `stallTime`: seconds a joint
    may push short of its goal at a high load before it counts as stalled (specs/force.md).
    """

    port: str | None = None
    baudRate: Annotated[int, msgspec.Meta(gt=0)] | None = None
    rate: Annotated[float, msgspec.Meta(gt=0, le=2000)] = 250.0
    estop: Literal["hold", "torque-off"] = "hold"
    calibration: CalibrationName | None = None
    joinSpeed: Annotated[float, msgspec.Meta(gt=0, le=MAX_JOIN_SPEED)] | None = None
    torqueLimit: (
        Annotated[dict[JointKey, TorquePercent], msgspec.Meta(max_length=MAX_TORQUE_LIMITS)] | None
    ) = None
    stallTime: Annotated[float, msgspec.Meta(ge=0.1, le=60)] = 1.0


class ComplianceBody(msgspec.Struct, forbid_unknown_fields=True):
    """Hand guiding: the `joints` (names or aliases) of the robot's usb-slave give at most
    `torque` percent of full torque, so a person can move them; their motion is recorded as a
    master's commands (`source: "hand-guide"`). specs/force.md."""

    joints: Annotated[list[JointKey], msgspec.Meta(min_length=1, max_length=MAX_TORQUE_LIMITS)]
    torque: TorquePercent


#: Where another Arena server listens: ws(s):// or http(s)://, host and port.
ServerUrl = Annotated[str, msgspec.Meta(pattern=r"^(ws|wss|http|https)://[^\s/?#]+/?$")]
#: A robot id on another server.
RemoteRobotId = Annotated[str, msgspec.Meta(pattern=r"^[A-Za-z0-9_.:-]{1,64}$")]


class RemoteLinkBody(msgspec.Struct, omit_defaults=True, forbid_unknown_fields=True):
    """What both remote drivers share: where, which robot, the key, heartbeats, backoff.

    `heartbeat`: seconds between heartbeats; `reconnectInitial`/`reconnectMax`: the first and
    the longest wait between reconnection attempts (doubling, with 20 % jitter).
    """

    url: ServerUrl
    robotId: RemoteRobotId | None = None
    apiKey: str | None = None
    heartbeat: Annotated[float, msgspec.Meta(gt=0, le=3600.0)] = 30.0
    reconnectInitial: Annotated[float, msgspec.Meta(gt=0, le=60)] = 0.5
    reconnectMax: Annotated[float, msgspec.Meta(gt=0, le=600)] = 30.0


class WebSocketSlaveBody(RemoteLinkBody, tag="websocket-slave", tag_field="type"):
    """Forward this robot's targets to `robotId` on another Arena server, as its master
    (`takeover`: displace a master there). Its real joint values come back as ours."""

    takeover: bool = False


class RemoteServerBody(RemoteLinkBody, tag="remote-server", tag_field="type"):
    """Take the commands another Arena server issues for its robot `robotId` (default: this
    robot's id), as this robot's master; our real joint values go back as that robot's.
    `takeover`: displace this robot's master (else MASTER_ACTIVE while it has one)."""

    takeover: bool = False


class PhysicsSlaveBody(
    msgspec.Struct,
    tag="physics-slave",
    tag_field="type",
    omit_defaults=True,
    forbid_unknown_fields=True,
):
    """The arm simulated by MuJoCo (the `physics` extra): `rate` steps a second; `estop` as a
    usb-slave's; `realtime` false steps inside the event loop instead of a worker thread (for
    tests on an autojumping virtual clock)."""

    rate: Annotated[float, msgspec.Meta(ge=100, le=5000)] = 500.0
    estop: Literal["hold", "torque-off"] = "hold"
    realtime: bool = True


SlaveBody: TypeAlias = MockSlaveBody | UsbSlaveBody | WebSocketSlaveBody | PhysicsSlaveBody


class CalibrationBody(msgspec.Struct, omit_defaults=True, forbid_unknown_fields=True):
    """Calibration steps. `slave`: which hardware slave (when the robot has several);
    `rest` (start only): the pose the arm is put in, degrees by joint (default: the twin's);
    `writeHoming` (finish only): also store the offsets in the servos."""

    slave: str | None = None
    rest: dict[str, Annotated[float, msgspec.Meta(ge=-360, le=360)]] | None = None
    writeHoming: bool = False


class SequenceMasterBody(
    msgspec.Struct,
    tag="mock-sequence",
    tag_field="type",
    omit_defaults=True,
    forbid_unknown_fields=True,
):
    """The demo-sequence master: which sequences (default: all), loop, auto start, and
    `takeover`: it displaces the robot's master unless told `false` (the seed's demo sequences
    take over by themselves), then MASTER_ACTIVE while the robot has one."""

    sequences: list[str] | None = None
    loop: bool = False
    autoStart: bool = True
    takeover: bool = True


class ReplayBody(msgspec.Struct, omit_defaults=True, forbid_unknown_fields=True):
    """`POST /api/robots/{id}/replay`: which file and robot, speed, loop, window (seconds
    from the robot's first recorded command), `takeover` (displace the robot's master; else
    MASTER_ACTIVE while it has one)."""

    recording: str
    source_robot: str | None = None
    speed: Annotated[float, msgspec.Meta(ge=0.01, le=1000)] = 1.0
    loop: bool = False
    start: Annotated[float, msgspec.Meta(ge=0)] | None = None
    end: Annotated[float, msgspec.Meta(gt=0)] | None = None
    takeover: bool = False


class ReplayMasterBody(ReplayBody, tag="replay", tag_field="type"):
    """The `replay` master config: a `ReplayBody` with its type."""


class UsbMasterBody(
    msgspec.Struct,
    tag="usb-master",
    tag_field="type",
    omit_defaults=True,
    forbid_unknown_fields=True,
):
    """A leader arm on a servo bus (its family the robot type's), moved by hand (torque stays
    off). No `baudRate`: the robot type's.

    `rate`: Hz at which it is read; `deadband`: degrees a joint must move before a new command
    goes out, unless it is plainly moving (three encoder steps the same way in a row: a move
    is sent from its start); `calibration`: the leader's calibration name (default:
    `<robot id>-leader`); `takeover`: displace the robot's master (else MASTER_ACTIVE while it
    has one);
    `actuated`: the leader's servos take torque: it is first driven to the follower's pose at
    the robot's joining speed, then goes limp for the hand (no jerk when it takes over).
    """

    port: str | None = None
    baudRate: Annotated[int, msgspec.Meta(gt=0)] | None = None
    rate: Annotated[float, msgspec.Meta(gt=0, le=2000)] = 250.0
    deadband: Annotated[float, msgspec.Meta(ge=0, le=10)] = 0.5
    calibration: CalibrationName | None = None
    takeover: bool = False
    actuated: bool = False


#: A strategy's task: what its episodes show (as `EpisodeBody`'s).
StrategyTask = Annotated[str, msgspec.Meta(min_length=1, max_length=1000)]
#: Longest episode, reset and highlight window a strategy may ask for (seconds: an hour).
MAX_STRATEGY_SECONDS = 3600.0
#: Longest window a highlight keeps in memory (seconds): the server holds its events and
#: camera frames while the recorder is off (specs/policy.md, "Rollout strategies").
MAX_HIGHLIGHT_SECONDS = 300.0
#: Most episodes an episodic strategy runs.
MAX_EPISODES = 10_000


class EpisodicStrategy(
    msgspec.Struct, tag="episodic", tag_field="type", omit_defaults=True, forbid_unknown_fields=True
):
    """LeRobot's `episodic` rollout: `episodes` episodes of `episode_s` seconds with `task`;
    between two, the policy paused, the robot taken back to `start_pose` (joint name to
    degrees, or the gripper's value; default: the pose at attach) at the robot's join speed
    within `reset_s` seconds. The master ends after the last."""

    episodes: Annotated[int, msgspec.Meta(ge=1, le=MAX_EPISODES)]
    episode_s: Annotated[float, msgspec.Meta(gt=0, le=MAX_STRATEGY_SECONDS)]
    task: StrategyTask
    reset_s: Annotated[float, msgspec.Meta(ge=0, le=MAX_STRATEGY_SECONDS)] = 10.0
    start_pose: Annotated[dict[JointKey, float], msgspec.Meta(max_length=32)] | None = None


class SentryStrategy(
    msgspec.Struct, tag="sentry", tag_field="type", omit_defaults=True, forbid_unknown_fields=True
):
    """LeRobot's `sentry` rollout: the policy runs on, a new episode of `task` every
    `episode_s` seconds."""

    episode_s: Annotated[float, msgspec.Meta(gt=0, le=MAX_STRATEGY_SECONDS)]
    task: StrategyTask


class HighlightStrategy(
    msgspec.Struct,
    tag="highlight",
    tag_field="type",
    omit_defaults=True,
    forbid_unknown_fields=True,
):
    """LeRobot's `highlight` rollout: the last `keep_s` seconds are kept, and `POST
    .../highlight` saves them as an episode of `task`; nothing else is one."""

    keep_s: Annotated[float, msgspec.Meta(gt=0, le=MAX_HIGHLIGHT_SECONDS)]
    task: StrategyTask


StrategyBody: TypeAlias = EpisodicStrategy | SentryStrategy | HighlightStrategy


class PolicyMasterBody(
    msgspec.Struct,
    tag="policy",
    tag_field="type",
    omit_defaults=True,
    forbid_unknown_fields=True,
):
    """A LeRobot 0.4 policy run as the master in a worker process (specs/policy.md). `path`:
    the name of the policy's folder in the robot's tenant's policy folder (a path, to a
    folder anywhere on the server, only from the whole server's admin). LeRobot's names for
    LeRobot's settings:
    `actions_per_chunk` (default: the policy's chunk length), `chunk_size_threshold`,
    `aggregate_fn_name`; `max_relative_target`: the step limit in degrees (null: off);
    `stall_periods`: control periods without an action before the watchdog trips; `takeover`:
    displace the robot's master (else MASTER_ACTIVE while it has one); `environment_state`:
    the task's state for a policy that takes `observation.environment_state` (a reach
    target, say), the same in every observation of the run; `blend_steps`: a new chunk's
    first actions blended in from the old plan over that many steps (0: none);
    `interpolation_multiplier`: commands per action, interpolated (LeRobot's name; `fps`
    times it at most the robot's command rate); `python`: the program that runs
    this policy's worker instead of the server's (a LeRobot of another version; only from the
    whole server's admin: it names a program to run); `strategy`: a rollout strategy
    (`episodic`, `sentry`, `highlight`) that makes episodes of the run."""

    path: Annotated[str, msgspec.Meta(min_length=1, max_length=4096)]
    task: Annotated[str, msgspec.Meta(max_length=1000)] = ""
    fps: Annotated[float, msgspec.Meta(ge=1, le=200)] = 30.0
    actions_per_chunk: Annotated[int, msgspec.Meta(ge=1, le=10_000)] | None = None
    chunk_size_threshold: Annotated[float, msgspec.Meta(ge=0, le=1)] = 0.5
    aggregate_fn_name: Literal["weighted_average", "latest_only", "average", "conservative"] = (
        "weighted_average"
    )
    max_relative_target: Annotated[float, msgspec.Meta(gt=0, le=360)] | None = 10.0
    stall_periods: Annotated[int, msgspec.Meta(ge=1, le=1000)] = 2
    environment_state: Annotated[list[float], msgspec.Meta(max_length=64)] = []
    blend_steps: Annotated[int, msgspec.Meta(ge=0, le=100)] = 3
    interpolation_multiplier: Annotated[int, msgspec.Meta(ge=1, le=20)] = 1
    python: Annotated[str, msgspec.Meta(min_length=1, max_length=4096)] | None = None
    takeover: bool = False
    strategy: StrategyBody | None = None


class ScriptMasterBody(
    msgspec.Struct,
    tag="script",
    tag_field="type",
    omit_defaults=True,
    forbid_unknown_fields=True,
):
    """A Python script run as the master in a worker process (specs/scripts.md). `path`: the
    name of a `.py` file in the robot's tenant's scripts folder (never a path: a script is
    code, and only what the server's owner put there runs); `takeover`: displace the robot's
    master (else MASTER_ACTIVE while it has one)."""

    path: Annotated[str, msgspec.Meta(min_length=1, max_length=4096)]
    takeover: bool = False


MasterBody: TypeAlias = (
    SequenceMasterBody
    | ReplayMasterBody
    | UsbMasterBody
    | RemoteServerBody
    | PolicyMasterBody
    | ScriptMasterBody
)


class InterventionBody(msgspec.Struct, omit_defaults=True, forbid_unknown_fields=True):
    """`POST .../intervention`: `master`, the intervening master's config (any master's, as
    `POST .../master` takes it: a leader arm's `usb-master`, say); none: the caller
    intervenes itself, over `PUT .../joints`."""

    master: MasterBody | None = None


class LeaderJoint(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """A simulated leader arm's joint and where to move it (the robot's units)."""

    name: JointKey
    value: float


#: The longest smooth move of a simulated leader's joints (milliseconds).
MAX_LEADER_MOVE_MS = 60_000.0


class LeaderJointsBody(msgspec.Struct, omit_defaults=True, forbid_unknown_fields=True):
    """`PUT .../leader/joints`: the robot's simulated leader arm moved as a hand moves it,
    `duration` milliseconds (0: at once), its usb-master then driving the robot."""

    joints: Annotated[list[LeaderJoint], msgspec.Meta(min_length=1, max_length=MAX_TORQUE_LIMITS)]
    duration: Annotated[float, msgspec.Meta(ge=0, le=MAX_LEADER_MOVE_MS)] = 0.0


class HandBackBody(msgspec.Struct, omit_defaults=True, forbid_unknown_fields=True):
    """`DELETE .../intervention`: `resume` false leaves the paused master paused."""

    resume: bool = True


#: A group id: like a robot id.
GroupId = Annotated[str, msgspec.Meta(pattern=r"^[A-Za-z0-9_.-]{1,64}$")]


class GroupBody(msgspec.Struct, omit_defaults=True, forbid_unknown_fields=True):
    """`POST /api/groups`: a group one master can drive. `stopTogether`: an e-stop of any
    member e-stops them all."""

    id: GroupId
    members: Annotated[list[RobotId], msgspec.Meta(min_length=1, max_length=256)]
    stopTogether: bool = False


#: Three coordinates in metres.
Point = Annotated[list[float], msgspec.Meta(min_length=3, max_length=3)]


class BoxBody(msgspec.Struct, omit_defaults=True, forbid_unknown_fields=True):
    """A keep-out box: its corners in metres (the base link's frame, z up) and a name."""

    min: Point
    max: Point
    name: str | msgspec.UnsetType = msgspec.UNSET


class WorkspaceBody(msgspec.Struct, omit_defaults=True, forbid_unknown_fields=True):
    """`PUT /api/robots/{id}/workspace`: the collision guard's floor (null: none), margin,
    policy and keep-out boxes. What is left out keeps the robot type's own (its table among
    them; specs/collision.md)."""

    floor: float | msgspec.UnsetType | None = msgspec.UNSET
    margin: float | msgspec.UnsetType = msgspec.UNSET
    policy: str | msgspec.UnsetType = msgspec.UNSET  # checked by the workspace: one list
    keep_out: list[BoxBody] | msgspec.UnsetType = msgspec.UNSET


class CameraBody(msgspec.Struct, forbid_unknown_fields=True):
    """`POST /api/robots/{id}/cameras`: a camera to attach (`source`: `test-pattern`,
    `file:PATH`, looped, a V4L2 device such as `/dev/video0`, or `twin`: the robot's physics
    slave rendered). Unnamed, `fps`, `width` and `height` are 30, 640, 480 (a twin: 5, 96, 96)."""

    name: Annotated[str, msgspec.Meta(pattern=r"^[A-Za-z0-9_-]{1,32}$")]
    source: Annotated[str, msgspec.Meta(min_length=1, max_length=4096)]
    fps: Annotated[int, msgspec.Meta(ge=1, le=60)] | None = None
    width: Annotated[int, msgspec.Meta(ge=16, le=1920)] | None = None
    height: Annotated[int, msgspec.Meta(ge=16, le=1080)] | None = None


class EpisodeBody(msgspec.Struct, forbid_unknown_fields=True):
    """`POST /api/robots/{id}/episodes/start`: what the episode shows (the task a policy
    learns from it)."""

    task: Annotated[str, msgspec.Meta(min_length=1, max_length=1000)]


class TeleopBoxBody(msgspec.Struct, forbid_unknown_fields=True):
    """An axis-aligned box (metres, the robot's base frame): its lowest and highest corner."""

    min: Annotated[
        list[Annotated[float, msgspec.Meta(ge=-10, le=10)]],
        msgspec.Meta(min_length=3, max_length=3),
    ]
    max: Annotated[
        list[Annotated[float, msgspec.Meta(ge=-10, le=10)]],
        msgspec.Meta(min_length=3, max_length=3),
    ]


class TeleopBody(msgspec.Struct, omit_defaults=True, forbid_unknown_fields=True):
    """`PUT /api/robots/{id}/teleop`: where `ee_velocity` may take the hand, and the dead-man
    time in milliseconds (how long after the last message the hand stops). Left out: kept."""

    box: TeleopBoxBody | None = None
    deadman: Annotated[float, msgspec.Meta(gt=0, le=2000)] | None = None


#: `POST /api/robots/{id}/move`: the master message `move`'s data (`MoveData`).
MoveBody: TypeAlias = MoveData
