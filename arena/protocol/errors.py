"""Machine-readable error codes and the exception that carries one with a plain sentence."""

from __future__ import annotations

import enum


class ErrorCode(enum.StrEnum):
    """Every refusal Arena can give. The value is what goes on the wire."""

    # Command content
    UNKNOWN_JOINT = "UNKNOWN_JOINT"
    INVALID_VALUE = "INVALID_VALUE"
    EMPTY_COMMAND = "EMPTY_COMMAND"
    # Ownership and safety
    MASTER_ACTIVE = "MASTER_ACTIVE"
    NOT_OWNER = "NOT_OWNER"
    ESTOPPED = "ESTOPPED"
    RATE_LIMITED = "RATE_LIMITED"
    UNREACHABLE = "UNREACHABLE"  # no pose of the arm puts its hand where it was asked to go
    NO_PATH = "NO_PATH"  # no collision-free path to a planned move's goal within its budget
    STALE_COMMAND = "STALE_COMMAND"  # a stamped command arrived older than command_max_age
    COLLISION = "COLLISION"  # the move would bring links together or into the workspace's walls
    TAKEN_OVER = "TAKEN_OVER"
    MASTER_PAUSED = "MASTER_PAUSED"  # a paused master's command: it waits for a resume
    NO_MASTER = "NO_MASTER"  # a pause, resume or intervention asks for a master the robot lacks
    INTERVENTION_ACTIVE = "INTERVENTION_ACTIVE"  # one intervention at a time
    NO_INTERVENTION = "NO_INTERVENTION"  # ending an intervention when none runs
    INTERVENTION_ENDED = "INTERVENTION_ENDED"  # told to an intervening master handed back
    MASTER_LOST = "MASTER_LOST"
    SLAVE_LOST = "SLAVE_LOST"
    DRIVER_FAILED = "DRIVER_FAILED"
    SLAVE_STATUS = "SLAVE_STATUS"  # a WebSocket slave's status_update says it is not connected
    SIMULATED_FAULT = "SIMULATED_FAULT"  # injected by a mock-slave with simulateErrors
    CONTACT = "CONTACT"  # the physics twin's links touch something
    OVERLOADED = "OVERLOADED"
    LIMIT_REACHED = "LIMIT_REACHED"  # a caller holds the most robots, groups or WebSockets
    # Registry
    UNKNOWN_ROBOT = "UNKNOWN_ROBOT"
    UNKNOWN_ROBOT_TYPE = "UNKNOWN_ROBOT_TYPE"
    ROBOT_EXISTS = "ROBOT_EXISTS"
    UNKNOWN_SEQUENCE = "UNKNOWN_SEQUENCE"
    UNKNOWN_SLAVE = "UNKNOWN_SLAVE"
    INVALID_CONFIG = "INVALID_CONFIG"
    ROBOT_STOPPED = "ROBOT_STOPPED"
    # Messages and requests at the edge
    INVALID_JSON = "INVALID_JSON"
    INVALID_MESSAGE = "INVALID_MESSAGE"
    UNKNOWN_MESSAGE_TYPE = "UNKNOWN_MESSAGE_TYPE"
    MESSAGE_TOO_LARGE = "MESSAGE_TOO_LARGE"
    BINARY_NOT_SUPPORTED = "BINARY_NOT_SUPPORTED"
    INVALID_BODY = "INVALID_BODY"
    UNKNOWN_FIELD = "UNKNOWN_FIELD"  # a body or message carries a field its type does not have
    NOT_FOUND = "NOT_FOUND"
    METHOD_NOT_ALLOWED = "METHOD_NOT_ALLOWED"
    UNAUTHORIZED = "UNAUTHORIZED"
    FORBIDDEN = "FORBIDDEN"
    ORIGIN_NOT_ALLOWED = "ORIGIN_NOT_ALLOWED"
    HOST_NOT_ALLOWED = "HOST_NOT_ALLOWED"
    UNSUPPORTED_MEDIA_TYPE = "UNSUPPORTED_MEDIA_TYPE"
    INTERNAL_ERROR = "INTERNAL_ERROR"
    NOT_INSTALLED = "NOT_INSTALLED"  # the feature's extra is not installed (arena/extras.py)
    # Servo bus hardware
    PORT_NOT_FOUND = "PORT_NOT_FOUND"
    PORT_BUSY = "PORT_BUSY"
    PORT_PERMISSION_DENIED = "PORT_PERMISSION_DENIED"
    PORT_DISCONNECTED = "PORT_DISCONNECTED"
    SERVO_TIMEOUT = "SERVO_TIMEOUT"
    SERVO_CORRUPT = "SERVO_CORRUPT"
    SERVO_WRONG_MODEL = "SERVO_WRONG_MODEL"
    SERVO_OVERHEAT = "SERVO_OVERHEAT"
    SERVO_HOT = "SERVO_HOT"
    SERVO_OVERLOAD = "SERVO_OVERLOAD"
    SERVO_OVERCURRENT = "SERVO_OVERCURRENT"
    SERVO_VOLTAGE = "SERVO_VOLTAGE"
    SERVO_ANGLE = "SERVO_ANGLE"
    SERVO_OUT_OF_RANGE = "SERVO_OUT_OF_RANGE"  # reads outside the frame it may take torque in
    STALL = "STALL"  # fault (warning): a joint pushed short of its goal; Arena stopped pushing
    UNCALIBRATED = "UNCALIBRATED"
    CALIBRATION_STATE = "CALIBRATION_STATE"
    NO_HARDWARE = "NO_HARDWARE"
    NO_LEADER = "NO_LEADER"  # no leader arm (usb-master) drives the robot or waits on it
    LEADER_NOT_SIMULATED = "LEADER_NOT_SIMULATED"  # its leader is hardware, not the server's sim
    # Links to other Arena servers
    REMOTE_UNREACHABLE = "REMOTE_UNREACHABLE"
    REMOTE_REFUSED = "REMOTE_REFUSED"
    REMOTE_ESTOPPED = "REMOTE_ESTOPPED"  # the robot behind a websocket-slave is e-stopped
    # Groups
    UNKNOWN_GROUP = "UNKNOWN_GROUP"
    GROUP_EXISTS = "GROUP_EXISTS"
    # Cameras and episodes
    UNKNOWN_CAMERA = "UNKNOWN_CAMERA"
    CAMERA_EXISTS = "CAMERA_EXISTS"
    CAMERA_FAILED = "CAMERA_FAILED"
    CAMERA_RECOVERED = "CAMERA_RECOVERED"
    NO_TWIN = "NO_TWIN"  # a twin camera for a robot with no physics slave
    EPISODE_ACTIVE = "EPISODE_ACTIVE"
    NO_EPISODE = "NO_EPISODE"
    # Fleets
    ROBOT_ELSEWHERE = "ROBOT_ELSEWHERE"  # another node of the fleet owns that robot id
    NODE_LOST = "NODE_LOST"  # the node that owns the robot left the fleet or did not answer
    ESTOP_INCOMPLETE = "ESTOP_INCOMPLETE"  # a node's e-stop failed or it did not answer
    # Recordings
    INVALID_RECORDING = "INVALID_RECORDING"
    UNKNOWN_RECORDING = "UNKNOWN_RECORDING"
    # Policies as masters (specs/policy.md)
    POLICY_INVALID = "POLICY_INVALID"  # not a policy, or one the robot cannot feed
    POLICY_NOT_READY = "POLICY_NOT_READY"  # the worker did not load it in time, or exited
    POLICY_OUTPUT_INVALID = "POLICY_OUTPUT_INVALID"  # fault: an action that is not finite
    POLICY_STALLED = "POLICY_STALLED"  # fault (warning): no action due for two periods
    # Scripts as masters (specs/scripts.md)
    SCRIPT_INVALID = "SCRIPT_INVALID"  # no script of that name in the tenant's scripts folder
    SCRIPT_FAILED = "SCRIPT_FAILED"  # fault: the script raised (its file and line) or died
    NO_HIGHLIGHT = "NO_HIGHLIGHT"  # a highlight asked of a robot whose policy keeps none
    POSE_NOT_REACHED = "POSE_NOT_REACHED"  # fault (warning): an episodic reset ran out of time


class ArenaError(Exception):
    """An error with a machine-readable code and a sentence a person can act on."""

    def __init__(self, code: ErrorCode, message: str) -> None:
        super().__init__(f"{code}: {message}")
        self.code = code
        self.message = message


class Severity(enum.StrEnum):
    """How bad a reported fault is, in increasing order."""

    INFO = "info"
    WARNING = "warning"
    ERROR = "error"
    CRITICAL = "critical"

    @property
    def rank(self) -> int:
        """Position in the order info < warning < error < critical."""
        return _SEVERITY_ORDER.index(self)


_SEVERITY_ORDER = list(Severity)
