"""A robot's events as messages to one WebSocket peer: state changes at once, joint states
paced by a token bucket (and carried by the acks of the commands that caused them)."""

from __future__ import annotations

import contextlib
import math
from collections.abc import Awaitable, Callable

import msgspec
import trio

from arena.protocol import messages as wire
from arena.robot.events import (
    FaultReported,
    JointStatesReceived,
    MotionStopped,
    RobotEvent,
    StateChanged,
    TargetsSent,
)
from arena.robot.handle import Robot
from arena.robot.mailbox import EventQueue
from arena.server import convert
from arena.server.ws.backpressure import Encoded, Outgoing
from arena.server.ws.connection import CLOSE_NORMAL, Connection

#: The events a `RobotEventForwarder` makes messages of (its queue takes no others).
FORWARDED = (StateChanged, JointStatesReceived, TargetsSent)
#: ... and for a viewer, faults as they happen and end, and motions the collision guard
#: stopped on their way (`fault` messages: the dashboard's sliders are told so).
FORWARDED_TO_VIEWERS = (*FORWARDED, FaultReported, MotionStopped)
#: Events a peer's queue holds before the oldest are dropped (the newest state wins).
QUEUE_LENGTH = 256


class RobotEventForwarder:
    """State changes at once; joint states once per `joint_states_interval` on average.

    Joint states are paced by a token bucket of two intervals: at most one per interval on
    average and two at once, so that a client commanding at that rate gets one with every
    acknowledgment despite jitter (a late command followed by one on time) without a separate
    write. `name_robot` adds the robot's id to them (a group master hears from several).

    Besides its own task (`run`), the connection's reader can take what is ready right after
    answering a command (`handling_command`, `take_due`), so that the acknowledgment and the
    joint states it caused leave in one write, and the task is not woken for them.

    The task sends pending joint states one interval after the bucket would allow them, so a
    command that comes before then carries them. Sending them as soon as allowed locks a
    client that commands at the interval's own rate, after any stall that made two of its
    commands arrive together, into a phase where every joint state leaves in a write of its
    own a few milliseconds before the command that could have carried it. The bucket never
    refills at that rate, so the phase lasts as long as the client.
    """

    def __init__(
        self,
        connection: Connection,
        robot: Robot,
        events: EventQueue[RobotEvent],
        name_robot: bool = False,
        on_robot_gone: Callable[[str], Awaitable[None]] | None = None,
    ) -> None:
        self.connection = connection
        self.robot = robot
        self.events = events
        self.name_robot = name_robot
        self.on_robot_gone = on_robot_gone
        self.interval = connection.app.arena_config.joint_states_interval
        self.pending = False  # joint values changed since the last joint_states sent
        self.next_send = -math.inf
        self.joint_states = convert.JointStatesView(robot)
        self._waiting: trio.CancelScope | None = None  # the task's wait, while it waits

    async def run(self) -> None:
        """Forward until the robot is gone."""
        while True:
            batch: list[RobotEvent] = []
            with trio.CancelScope(deadline=self._deadline()) as self._waiting:
                try:
                    batch = [await self.events.get(), *self.events.drain()]
                except trio.EndOfChannel:  # the robot is gone
                    if self.on_robot_gone is not None:
                        await self.on_robot_gone(self.robot.robot_id)
                    else:
                        await self.connection.close(CLOSE_NORMAL, "robot deleted")
                    return
            self._waiting = None
            for message in self._messages(batch):
                await self.connection.send(message)

    def handling_command(self) -> contextlib.AbstractContextManager[None]:
        """Around a command whose events the reader will `take_due` itself."""
        return self.events.holding_wakes()

    def take_due(self) -> list[Outgoing]:
        """What is ready to go now, taken from the queue (the task then finds it empty)."""
        if not (self.events or self.pending):  # most commands of a burst: nothing new to say
            return []
        messages = self._messages(self.events.drain())
        if self._waiting is not None:  # joint states held back: the task sends them when due
            deadline = self._deadline()
            if deadline != self._waiting.deadline:  # (setting it costs even when unchanged)
                self._waiting.deadline = deadline
        return messages

    def _deadline(self) -> float:
        return self.next_send + self.interval if self.pending else math.inf

    def _messages(self, batch: list[RobotEvent]) -> list[Outgoing]:
        out: list[Outgoing] = []
        changed = moved = False
        for event in batch:  # (a loop: two `any` generators cost more, per command)
            kind = type(event)
            changed = changed or kind is StateChanged
            moved = moved or kind is TargetsSent or kind is JointStatesReceived
            if kind is FaultReported:  # (only a viewer's queue takes them)
                out.append(convert.fault(event))  # type: ignore[arg-type]
            elif kind is MotionStopped:  # (likewise)
                out.append(convert.stop_fault(event))  # type: ignore[arg-type]
        if changed:
            state = convert.state(self.robot.snapshot())
            if self.name_robot:  # the newest of each member's is kept for a peer behind
                out.append(Encoded(f"state:{self.robot.robot_id}", wire.encode(state)))
            else:
                out.append(state)
        self.pending = self.pending or (moved and self.connection.wants_joint_states)
        now = trio.current_time()
        if self.pending and now >= self.next_send:
            states = self.joint_states.message()
            if self.name_robot:
                named = msgspec.to_builtins(states) | {"robot_id": self.robot.robot_id}
                text = msgspec.json.encode(named).decode()
                out.append(Encoded(f"joint_states:{self.robot.robot_id}", text))
            else:
                out.append(states)
            self.pending = False
            # The time the bucket holds a token again (it holds at most two).
            self.next_send = max(self.next_send + self.interval, now)
        return out
