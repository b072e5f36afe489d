"""The pure parts of running a policy: the action queue of LeRobot's async inference and the
policy rules one action step meets before it is a command. No trio, no I/O, no clock.

The queue follows LeRobot's `RobotClient` (lerobot/async_inference/robot_client.py), with its
settings' names: an observation goes to the policy when the queue holds at most
`chunk_size_threshold` of a chunk; a chunk's actions are timed from the step the observation was
taken at; those already due are dropped, and those the queue still holds are merged with
`aggregate_fn_name`'s function. As in LeRobot, a new chunk replaces the queue: what it holds
beyond the new chunk's end is dropped. Beyond LeRobot: the first `blend_steps` actions of a new
chunk are blended from the old plan (the queue's action for that step, else the last action
taken) to the new one, so a chunk that disagrees with the arm's motion is eased into instead
of stepped to (issue 57; specs/motion.md).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

Action = tuple[float, ...]

#: LeRobot's aggregate functions (async_inference/configs.py), by their names: how an action of
#: a new chunk is merged with the queue's action for the same step.
AGGREGATE_FUNCTIONS: dict[str, Callable[[float, float], float]] = {
    "weighted_average": lambda old, new: 0.3 * old + 0.7 * new,
    "latest_only": lambda old, new: new,
    "average": lambda old, new: 0.5 * old + 0.5 * new,
    "conservative": lambda old, new: 0.7 * old + 0.3 * new,
}


@dataclass
class ActionQueue:
    """Timed actions waiting for their control step (timesteps count control steps)."""

    actions_per_chunk: int
    chunk_size_threshold: float = 0.5
    aggregate_fn_name: str = "weighted_average"
    latest_action: int = -1  # the step of the last action taken off the queue
    queue: dict[int, Action] = field(default_factory=dict)
    #: Steps over which a new chunk is blended in (0: none; see the module docstring).
    blend_steps: int = 0
    last_taken: Action | None = None  # the last action taken off the queue

    def __post_init__(self) -> None:
        if self.actions_per_chunk < 1:
            raise ValueError("actions_per_chunk must be at least 1")
        if not 0 <= self.chunk_size_threshold <= 1:
            raise ValueError("chunk_size_threshold must be between 0 and 1")
        if self.aggregate_fn_name not in AGGREGATE_FUNCTIONS:
            raise ValueError(f"unknown aggregate_fn_name {self.aggregate_fn_name!r}")
        if self.blend_steps < 0:
            raise ValueError("blend_steps must be at least 0")

    def __len__(self) -> int:
        return len(self.queue)

    @property
    def observation_step(self) -> int:
        """The step an observation taken now belongs to (LeRobot's `max(latest_action, 0)`)."""
        return max(self.latest_action, 0)

    def ready_for_observation(self) -> bool:
        """Whether the queue is low enough that the policy should be asked again."""
        return len(self.queue) / self.actions_per_chunk <= self.chunk_size_threshold

    def add_chunk(self, first_step: int, actions: Sequence[Action]) -> int:
        """Take a chunk whose first action belongs to `first_step`; returns the actions kept."""
        merge = AGGREGATE_FUNCTIONS[self.aggregate_fn_name]
        future: dict[int, Action] = {}
        for index, action in enumerate(actions[: self.actions_per_chunk]):
            step = first_step + index
            if step <= self.latest_action:
                continue  # its time has passed
            old = self.queue.get(step)
            if old is None or len(old) != len(action):
                future[step] = tuple(action)
            else:
                future[step] = tuple(merge(a, b) for a, b in zip(old, action, strict=True))
        if self.blend_steps:
            self._blend(future)
        self.queue = future
        return len(future)

    def _blend(self, future: dict[int, Action]) -> None:
        """Ease the first `blend_steps` actions of `future` in from the old plan: action k
        (from 1) is the old one moved k / (blend_steps + 1) of the way to the new one."""
        held = self.last_taken
        for k, step in enumerate(sorted(future)[: self.blend_steps], start=1):
            old = self.queue.get(step, held)
            new = future[step]
            if old is None or len(old) != len(new):
                continue
            w = k / (self.blend_steps + 1)
            future[step] = tuple(a + w * (b - a) for a, b in zip(old, new, strict=True))

    def drop(self) -> None:
        """Forget every action waiting (a pause: what was computed before it is stale, and
        so is the last action taken, which a blend would start from)."""
        self.queue = {}
        self.last_taken = None

    def next_action(self) -> tuple[int, Action] | None:
        """Take the earliest action off the queue (None when it is empty)."""
        if not self.queue:
            return None
        step = min(self.queue)
        self.latest_action = step
        action = self.last_taken = self.queue.pop(step)
        return step, action


@dataclass(frozen=True, slots=True)
class StepCheck:
    """What the policy rules made of one action: the targets to command (Arena's units, by
    joint), the joints the step limit clamped, or why nothing may be sent (`invalid`)."""

    targets: dict[str, float]
    clamped: tuple[str, ...] = ()
    invalid: str | None = None


def check_step(
    joints: Sequence[str],
    action: Sequence[float],
    measured: Sequence[float],
    max_relative_target: float | None,
) -> StepCheck:
    """Apply the policy rules to one action (already in Arena's units, in `joints`' order).

    A value that is not a finite number refuses the whole step (nothing of it is sent). Each
    target is then kept within `max_relative_target` of the joint's measured value (None: no
    step limit), the clamped joints named.
    """
    if len(action) != len(joints):
        return StepCheck(
            {}, invalid=f"the action has {len(action)} values for {len(joints)} joints"
        )
    bad = [name for name, value in zip(joints, action, strict=True) if not math.isfinite(value)]
    if bad:
        return StepCheck({}, invalid=f"not a finite number for {', '.join(bad)}")
    targets: dict[str, float] = {}
    clamped: list[str] = []
    for name, value, now in zip(joints, action, measured, strict=True):
        if max_relative_target is not None and abs(value - now) > max_relative_target:
            value = now + math.copysign(max_relative_target, value - now)
            clamped.append(name)
        targets[name] = value
    return StepCheck(targets, tuple(clamped))
