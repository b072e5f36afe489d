"""Stall and heat protection, without I/O: which joints stopped against something, and what
torque each servo may give now.

A servo that pushes against an obstacle (a gripper on an object, an arm on a table) holds its
goal out of reach: its load stays high and it heats (I squared R), and a gripper held shut burns
out within minutes. `ForceGuard` is fed each telemetry read (positions, loads in percent of full
torque, temperatures), with the goals the driver last sent and the bus thread's own clock, and
says what to do: a joint whose load stays at or above `stall_share` of its torque limit while it
is more than `stall_steps` short of its goal and gets no more than `stall_steps` nearer it for
`stall_time` is stalled (`Stalled`), however its goal runs on meanwhile; the driver stops
pushing and the guard lowers a stalled gripper's torque limit to `hold_torque` (it keeps its
grip, gently); a goal that backs off releases it (`pushes_on`, `release`). A servo at or
above the warm temperature (the health monitor's `hot`) gets its limit scaled by `hot_share`
until it is `cool_margin` below it. specs/force.md gives the reasons and the values.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping
from dataclasses import dataclass, field


@dataclass(frozen=True, slots=True)
class ForceSettings:
    """The thresholds of `ForceGuard` (see the module docstring)."""

    stall_time: float = 1.0
    stall_share: float = 0.5
    stall_steps: int = 20  # about 1.8 degrees of a 4096-step turn
    hold_torque: float = 25.0  # percent: LeRobot's gripper Overload_Torque (so_follower.py)
    hot: float = 55.0
    hot_share: float = 0.5
    cool_margin: float = 5.0


@dataclass(frozen=True, slots=True)
class Stalled:
    """A servo stalled: where it is, the goal it could not reach, the load it pushed with."""

    servo_id: int
    present: int
    goal: int
    load: float  # percent of full torque
    limit: float  # its torque limit then, percent


@dataclass
class _Joint:
    goal: int | None = None
    pushing_since: float | None = None
    pushing_at: int = 0  # where it was when it began to push (moving on restarts the wait)
    stalled_on: tuple[int, int] = (0, 0)  # where it stalled, and the goal it fell short of
    stalled: bool = False
    hot: bool = False


@dataclass
class ForceGuard:
    """See the module docstring. `limits`: each servo's configured torque limit (percent;
    absent: 100); `grippers`: the servos that keep a holding torque when stalled."""

    limits: Mapping[int, float]
    grippers: Collection[int] = ()
    settings: ForceSettings = field(default_factory=ForceSettings)
    #: Limits set at run time over `limits` (compliance: a hand moves the joint, so it is
    #: never taken for a stall while it lasts).
    overrides: dict[int, float] = field(default_factory=dict)
    _joints: dict[int, _Joint] = field(default_factory=dict)

    def _joint(self, servo_id: int) -> _Joint:
        return self._joints.setdefault(servo_id, _Joint())

    def stalled(self, servo_id: int) -> bool:
        """Whether the servo is stalled now (until `release`)."""
        return self._joint(servo_id).stalled

    def goal(self, servo_id: int, steps: int) -> None:
        """The driver sent `steps` as the servo's goal. A goal that runs on does not restart
        the wait: a joint held by an obstacle while its trajectory still runs is stalled as
        much as one whose goal stopped (the servo's own overload protection counts from the
        push, not from the goal's last change)."""
        self._joint(servo_id).goal = steps

    def pushes_on(self, servo_id: int, steps: int) -> bool:
        """Whether a goal `steps` for a stalled servo asks for no more than the push it
        stalled on: no more than `stall_steps` back toward the joint from the goal it fell
        short of (the rest of the move that ran into the obstacle goes on past it). The
        driver keeps such a joint stalled; a goal that backs off is a new command (`release`)."""
        present, goal = self._joint(servo_id).stalled_on
        side = 1 if goal >= present else -1  # the way it pushed
        return (goal - steps) * side <= self.settings.stall_steps

    def release(self, servo_id: int) -> None:
        """A new command for a stalled servo: it may push again (its limit comes back)."""
        joint = self._joint(servo_id)
        joint.stalled = False
        joint.pushing_since = None

    def limit(self, servo_id: int) -> float:
        """The torque limit the servo should have now (percent): its own, lowered while it is
        hot, and a stalled gripper's holding torque."""
        joint = self._joint(servo_id)
        limit = self.overrides.get(servo_id, self.limits.get(servo_id, 100.0))
        if joint.hot:
            limit *= self.settings.hot_share
        if joint.stalled and servo_id in self.grippers:
            limit = min(limit, self.settings.hold_torque)
        return limit

    def observe(
        self,
        now: float,
        positions: Mapping[int, int],
        loads: Mapping[int, float],
        temperatures: Mapping[int, float],
    ) -> list[Stalled]:
        """A telemetry read at `now` (seconds, any monotonic clock): the servos it finds
        newly stalled. Temperatures change `limit` (the caller writes what changed)."""
        found: list[Stalled] = []
        for servo_id, celsius in temperatures.items():
            joint = self._joint(servo_id)
            if celsius >= self.settings.hot:
                joint.hot = True
            elif celsius < self.settings.hot - self.settings.cool_margin:
                joint.hot = False
        for servo_id, present in positions.items():
            joint = self._joint(servo_id)
            load = loads.get(servo_id)
            if joint.stalled or joint.goal is None or load is None or servo_id in self.overrides:
                continue
            limit = self.limit(servo_id)
            pushing = (
                abs(joint.goal - present) > self.settings.stall_steps
                and load >= self.settings.stall_share * limit
            )
            if not pushing:
                joint.pushing_since = None
                continue
            toward = 1 if joint.goal > present else -1
            if (
                joint.pushing_since is None
                or (present - joint.pushing_at) * toward > self.settings.stall_steps
            ):  # (it got on toward its goal: loaded, as lifting the arm, but following it)
                joint.pushing_since, joint.pushing_at = now, present
            if now - joint.pushing_since >= self.settings.stall_time:
                joint.stalled = True
                joint.stalled_on = (present, joint.goal)
                found.append(Stalled(servo_id, present, joint.goal, load, limit))
        return found
