"""The idle turn: doing a waiting task's next step at once, in the caller's task.

Everything that changes a robot goes through its actor's inbox, in order (shared/DESIGN.md,
principle 1). The one exception is this: while a task waits with nothing queued for it, an item
handed to it now would be its very next step, so the caller may take that step itself. The answer
is the same and comes in the same order (nothing is queued, so nothing is overtaken); what is saved
is two task switches per command, the largest cost of the command path.

Two tasks open a turn, and nothing else takes one:

- the robot's actor, while it is blocked on an empty inbox (`Actor` opens it with the wait's
  cancel scope, whose deadline is its next timer: a motion tick or a heartbeat deadline). The
  robot handle takes it for `Robot.command_now` / `command_run_now` / `estop_now` and a link's
  heartbeat; `estop_together` (the manager's "e-stop all") takes it through `estop_now`.
- a slave's reader, while it waits on an empty `LatestMailbox` (the turn is the mailbox's
  `turn`): the actor then hands a target or notice straight to the reader's `deliver_now` (the
  server's slave writer writes it to an idle socket) instead of waking the reader for it.

Whoever queues an item for the task closes the turn first, and the task closes it when it wakes:
an item that went the long way is never overtaken. specs/architecture.md, "The actor and its one
exception", says why this is safe.
"""

from __future__ import annotations

import trio


class IdleTurn:
    """The turn of a task that waits with nothing queued; see the module's docstring."""

    __slots__ = ("_wait", "is_open")

    def __init__(self) -> None:
        self.is_open = False
        self._wait: trio.CancelScope | None = None  # the waiter's own timer, if it has one

    def open(self, wait: trio.CancelScope | None = None) -> None:
        """The task waits with nothing queued (and wakes at `wait`'s deadline, if given)."""
        self._wait = wait
        self.is_open = True

    def close(self) -> None:
        """An item was queued for the task, or it woke: its next step is its own again."""
        self.is_open = False
        self._wait = None

    def now(self) -> float | None:
        """The time, if the turn is open and the task's timer is not due; else None (queue the
        item instead). A due timer goes first: its step comes before the caller's."""
        if not self.is_open:
            return None
        now = trio.current_time()
        wait = self._wait
        return now if wait is None or now < wait.deadline else None

    def wake_at(self, deadline: float) -> None:
        """After a step taken in the turn: the task's timer is now `deadline`, the one it would
        set itself (a command taken may have started a motion, which needs its next tick, or
        put off a tick a stream on time does not need)."""
        wait = self._wait
        if wait is not None:
            wait.deadline = deadline
