"""Read-only views of a robot, for listings, status endpoints and the demo printout."""

from __future__ import annotations

from dataclasses import dataclass

from arena.robot.safety import Mode


@dataclass(frozen=True, slots=True)
class JointSnapshot:
    """One joint: commanded (virtual) and measured (real) value in degrees, with its limits."""

    name: str
    servo_id: int
    virtual_value: float
    real_value: float | None
    goal: float
    lower: float
    upper: float
    velocity: float


@dataclass(frozen=True, slots=True)
class FaultSnapshot:
    """A fault a peer reported that lasts: its code, sentence, severity, joint (None: not of
    one joint) and since when (trio time)."""

    code: str
    message: str
    severity: str
    joint: str | None
    since: float


@dataclass(frozen=True, slots=True)
class PeerSnapshot:
    """An attached master or slave. `last_error`: its loss while it lasts, else its newest
    fault (`CODE: sentence`), else None; `faults`: every fault it has that lasts."""

    peer_id: str
    role: str
    kind: str
    connected: bool = True
    last_error: str | None = None
    joining: bool = False  # a slave not yet following the robot's targets (it joins)
    description: str = ""  # a master's, in words ("replay of 'x.mcap'")
    faults: tuple[FaultSnapshot, ...] = ()
    paused: bool = False  # a master that is paused (it sends nothing; the robot holds)
    #: A driver's own figures (a policy's: loads, inferences, stalls...), None: it has none.
    figures: dict[str, float] | None = None


@dataclass(frozen=True, slots=True)
class MasterEnded:
    """The robot's last master that left: who, how (`change`: "detached" or "lost"), why, and
    its newest fault of severity error or worse as `CODE: sentence` (a script's line, a
    policy's failure), else its loss's code and reason, else None."""

    peer_id: str
    kind: str
    description: str
    change: str
    reason: str
    error: str | None
    at: float  # wall clock (seconds since the epoch)


@dataclass(frozen=True, slots=True)
class RobotSnapshot:
    """A robot at one instant."""

    robot_id: str
    name: str
    robot_type: str
    mode: Mode
    owner: str | None
    estop_reason: str | None
    master: PeerSnapshot | None
    slaves: tuple[PeerSnapshot, ...]
    joints: tuple[JointSnapshot, ...]
    #: The master an intervention paused (it waits; `master` is the intervening one).
    paused_master: PeerSnapshot | None = None

    def joint(self, name: str) -> JointSnapshot:
        """The joint called `name` (protocol name)."""
        for joint in self.joints:
            if joint.name == name:
                return joint
        raise KeyError(name)
