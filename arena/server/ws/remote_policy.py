"""A policy that runs on another machine (`arena policy --url`) as a master over the WebSocket:
what the server keeps of it so that it is recorded and watched as a policy the server runs
itself (specs/policy.md).

The master declares itself once (`policy`: its fps and watchdog periods). From then on its
`inference` messages go to `/robots/{id}/policy` as a local worker's do (at most a few a
period: a master cannot flood the recording), and the server runs the watchdog: once the
policy has commanded, no command for its stall window (its own `stall_periods` periods plus
`LINK_ALLOWANCE` for the network) is a `POLICY_STALLED` fault, as a local policy reports it. The
robot holds where it is meanwhile (no command, no motion), and commands that arrive too late
are the stale-command rule's business.
"""

from __future__ import annotations

import time as wallclock

import trio

from arena.protocol import messages as wire
from arena.protocol.errors import ArenaError, ErrorCode, Severity
from arena.robot.events import PolicyInferred
from arena.robot.handle import Robot
from arena.robot.links import MasterLink
from arena.robot.motion import RateLimiter

#: Seconds a remote policy's commands may be late on top of its own stall window: the jitter
#: of a link across the internet, which a policy on the server does not have.
LINK_ALLOWANCE = 0.25
#: Inference records a period a remote policy may send in a burst (one a chunk is usual).
INFERENCE_BURST = 10

UNDECLARED = ArenaError(
    ErrorCode.INVALID_MESSAGE,
    'An inference is recorded only for a master that said it runs a policy: send {"type": '
    '"policy", "data": {"fps": ...}} first.',
)


class RemotePolicy:
    """One master's policy state on the server: nothing until it declares itself."""

    def __init__(self, robot: Robot, link: MasterLink) -> None:
        self.robot = robot
        self.link = link
        self.declared: wire.PolicyData | None = None
        self.inferences = 0  # recorded
        self.dropped = 0  # over the rate
        self.stalls = 0
        self._limiter: RateLimiter | None = None
        self._last_command = -float("inf")
        self._commanded = trio.Event()

    @property
    def window(self) -> float:
        """Seconds without a command that trip the watchdog (inf before the declaration)."""
        if self.declared is None:
            return float("inf")
        return self.declared.stall_periods / self.declared.fps + LINK_ALLOWANCE

    def declare(self, data: wire.PolicyData, nursery: trio.Nursery) -> None:
        """The master runs a policy: watch it from its first command on. Said once."""
        if self.declared is not None:
            raise ArenaError(
                ErrorCode.INVALID_MESSAGE, "This master has said it runs a policy already."
            )
        self.declared = data
        self._limiter = RateLimiter(data.fps, INFERENCE_BURST, trio.current_time())
        nursery.start_soon(self._watch)

    def commanded(self) -> None:
        """The master sent commands now (the watchdog's clock)."""
        self._last_command = trio.current_time()
        self._commanded.set()

    def inferred(self, data: wire.InferenceData) -> None:
        """Record one inference; RATE_LIMITED past the policy's own rate."""
        if self.declared is None or self._limiter is None:
            raise UNDECLARED
        if self.link.detached.is_set():
            raise ArenaError(ErrorCode.NOT_OWNER, "This master no longer holds the robot.")
        if not self._limiter.allow(trio.current_time()):
            self.dropped += 1
            raise ArenaError(
                ErrorCode.RATE_LIMITED,
                f"More inference records than the policy's {self.declared.fps:g} a second: "
                "this one was not recorded.",
            )
        self.inferences += 1
        self.robot.report_inference(
            PolicyInferred(
                self.robot.robot_id,
                self.link.master_id,
                data.timestep,
                data.chunk_size,
                data.kept,
                data.latency,
                data.inference,
                data.frame_age,
                trio.current_time(),
                wallclock.time(),
            )
        )

    def _paused(self) -> bool:
        """The robot paused this master (`POST .../master/pause`, an intervention)."""
        snapshot = self.robot.snapshot()
        for peer in (snapshot.master, snapshot.paused_master):
            if peer is not None and peer.peer_id == self.link.master_id and peer.paused:
                return True
        return False

    async def _watch(self) -> None:
        """The watchdog: a fault each time the commands stop for the stall window, armed
        again by the next command (the first inference, which warms a policy up, is not a
        stall: the watch starts at the first command)."""
        window = self.window
        while not self.link.detached.is_set():
            await self._commanded.wait()
            while (due := self._last_command + window) > trio.current_time():
                await trio.sleep_until(due)
            if self.link.detached.is_set():
                return
            self._commanded = trio.Event()
            if self._paused():
                continue  # told to send nothing: silence is obedience (armed again on resume)
            self.stalls += 1
            waited = trio.current_time() - self._last_command
            self.robot.report_sensor_fault(
                self.link.master_id,
                ErrorCode.POLICY_STALLED,
                f"No command from the remote policy for {waited * 1000:.0f} ms (its link or "
                "its inference is too slow): the robot holds where it is.",
                Severity.WARNING,
            )
