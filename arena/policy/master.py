"""A LeRobot policy as a robot's master: observations from what Arena measures go to a worker
process, its action chunks come back into LeRobot's async-inference queue, and one action a
control period leaves the queue as a command, through the policy rules and then every rule a
master's command meets (specs/policy.md).

Two tasks run while the master holds the robot. The control loop ticks at `fps`: it takes the
next action off the queue, checks it (finite values, the step limit), commands it, and trips
the watchdog when no action was due for `stall_periods` ticks. The inference task sends an
observation whenever the queue runs low and merges the chunk that comes back. The master is
autonomous: an e-stop detaches it, which cancels both tasks and stops the worker.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import trio

from arena.drivers.refusals import Refusals
from arena.policy.actions import ActionQueue, check_step
from arena.policy.arm import Arm as Arm
from arena.policy.arm import CameraFrames as CameraFrames
from arena.policy.arm import Inference as Inference
from arena.policy.arm import LinkArm as LinkArm
from arena.policy.arm import Shot as Shot
from arena.policy.features import (
    action_targets,
    camera_images,
    check_features,
    lerobot_state,
)
from arena.policy.process import (
    LOAD_TIMEOUT,
    PolicyProcess,
    WorkerError,
    WorkerGone,
    worker_command,
)
from arena.policy.strategy import Keeper, Rollout, Strategy, describe
from arena.policy.wire import Chunk, Loaded, Observe
from arena.protocol.errors import ArenaError, ErrorCode, Severity
from arena.robot.episodes import Episode
from arena.robot.links import MasterLink
from arena.robot.model import RobotModel
from arena.robot.motion import Command, JointGoal

log = logging.getLogger(__name__)

#: Refusals after which the policy stops for good (it never resumes by itself).
_FINAL_REFUSALS = frozenset({ErrorCode.ESTOPPED, ErrorCode.NOT_OWNER})
#: Steps over which a new chunk's first actions are blended in from the old plan (issue 57).
BLEND_STEPS = 3


class Worker(Protocol):
    """What the master needs of a policy worker (`PolicyProcess`; tests give a stand-in)."""

    async def load(self, path: Path) -> Loaded:
        """Load the policy; `WorkerError` with the reason if it cannot."""

    async def act(self, observation: Observe) -> Chunk:
        """The chunk for one observation; `WorkerGone` once the worker has ended."""

    async def close(self) -> None:
        """Stop the worker."""


@dataclass(frozen=True, slots=True)
class PolicySettings:
    """How a policy runs. LeRobot's names where LeRobot has the setting: `actions_per_chunk`
    (None: the policy's chunk length), `chunk_size_threshold`, `aggregate_fn_name`,
    `max_relative_target` (the step limit: degrees a target may lie from the measured position;
    None: off). `stall_periods`: control periods without an action that trip the watchdog;
    `load_timeout`: seconds the worker has to start and load the policy.
    `environment_state`: `observation.environment_state` of every observation (the task's
    state, which Arena does not measure; empty: none). `blend_steps`: a new chunk's first
    actions blended in from the old plan over that many steps (0: stepped to, as LeRobot);
    `interpolation_multiplier`: commands per action, interpolated from the last target to
    the action (LeRobot's name; 1: one command an action). specs/motion.md."""

    path: Path
    task: str = ""
    fps: float = 30.0
    actions_per_chunk: int | None = None
    chunk_size_threshold: float = 0.5
    aggregate_fn_name: str = "weighted_average"
    max_relative_target: float | None = 10.0
    stall_periods: int = 2
    load_timeout: float = LOAD_TIMEOUT
    environment_state: tuple[float, ...] = ()
    blend_steps: int = BLEND_STEPS
    interpolation_multiplier: int = 1
    #: The Python the worker runs in (one with LeRobot, torch and msgspec); None: Arena's own.
    python: str | None = None
    #: The rollout strategy that makes episodes of the run (None: none; `strategy.py`).
    strategy: Strategy | None = None


@dataclass(slots=True)
class PolicyCounters:
    """What a running policy has done, for its report and the tests."""

    inferences: int = 0
    sent: int = 0  # commands the robot accepted
    clamped: int = 0  # joint targets the step limit clamped
    invalid: int = 0  # actions refused for a value that is not finite
    stalls: int = 0  # times the watchdog tripped
    last_latency: float = 0.0  # seconds, the worker's own measure of its last inference
    last_chunk: int = 0  # actions in the last chunk that came back
    loads: int = 0  # times the worker loaded the policy (a pause and resume never reloads)
    pauses: int = 0  # times the robot paused the policy (`Arm.pauses`, read when shown)
    dropped: int = 0  # actions dropped at a pause (computed before it)
    episodes: int = 0  # episodes its strategy made
    resets: int = 0  # times its episodic strategy took the robot back to the start pose


class PolicyMaster:
    """Runs the policy in `settings.path` on a robot of `model`, with camera frames from
    `cameras`. `prepare` starts the worker and loads and checks the policy (the REST call
    answers only after it); `run` drives the robot; `close` stops the worker."""

    kind = "policy"
    autonomous = True  # an e-stop ends it for good
    takes_over = False

    def __init__(
        self,
        settings: PolicySettings,
        model: RobotModel,
        cameras: CameraFrames,
        start_worker: Callable[[], Awaitable[Worker]] | None = None,
    ) -> None:
        self.settings = settings
        self.model = model
        self.cameras = cameras
        self.start_worker = start_worker or functools.partial(
            PolicyProcess.start, worker_command(settings.python)
        )
        self.process: Worker | None = None
        self.loaded: Loaded | None = None
        self.queue: ActionQueue | None = None
        self.counters = PolicyCounters()
        self.refusals = Refusals()
        self._wake = trio.Event()
        self._failure: str | None = None  # the worker's last refusal or why it is gone
        self._worker_gone = False
        self._last_valid = True  # the last action passed the rules (a fault per run of bad ones)
        self._last_targets: dict[str, float] | None = None  # (interpolated from; see `_step`)
        # The watchdog waits for the worker's first answer (a chunk or a refusal): the first
        # inference, which warms the policy up, is not a stall.
        self._armed = False
        # Pauses so far: a chunk whose observation was taken before a pause is dropped.
        self._epoch = 0
        #: The recorder's side of a highlight strategy (given by the server; None: none).
        self.keeper: Keeper | None = None
        self.rollout: Rollout | None = None  # its strategy, once it runs
        self._arm: Arm | None = None
        # Its own strategy paused it (an episodic reset): the control loop holds, as for a
        # pause of the robot's, and the strategy commands meanwhile.
        self._suspended = False
        self._unsuspended = trio.Event()
        self._holding = False  # the control loop holds (paused by the robot or suspended)
        self._held = trio.Event()

    @property
    def identity(self) -> str:
        """`policy:<type>:<checkpoint>`, the source of its commands (once loaded)."""
        if self.loaded is None:
            return "policy"
        return f"policy:{self.loaded.policy_type}:{self.loaded.checkpoint}"

    @property
    def fps(self) -> float:
        """Its control steps a second."""
        return self.settings.fps

    @property
    def master_id(self) -> str:
        """The id it holds the robot under: its identity."""
        return self.identity

    def figures(self) -> dict[str, float]:
        """Its counters, shown with the robot's master (`PolicyCounters`)."""
        if self.rollout is not None:
            self.counters.episodes = self.rollout.episodes
        if self._arm is not None:
            # The robot's own count: it includes the pause just made, which the control loop
            # may not have noticed yet (`POST .../master/pause` answers with these figures).
            self.counters.pauses = self._arm.pauses
        return dataclasses.asdict(self.counters)

    @property
    def description(self) -> str:
        """What it is, in words: its identity, task and strategy."""
        task = f" ({self.settings.task!r})" if self.settings.task else ""
        strategy = describe(self.settings.strategy)
        strategy = f", {strategy}" if strategy else ""
        return f"{self.identity}{task} at {self.settings.fps:g} fps{strategy}"

    async def highlight(self) -> Episode:
        """Save the last seconds of a highlight strategy as an episode (`Rollout.highlight`);
        NO_HIGHLIGHT if the policy runs no such strategy."""
        if self.rollout is None:
            raise ArenaError(
                ErrorCode.NO_HIGHLIGHT,
                "The robot's policy runs no rollout strategy: attach it with "
                '{"strategy": {"type": "highlight", "keep_s": N, "task": "..."}}.',
            )
        return await self.rollout.highlight()

    def report(self, code: ErrorCode, message: str) -> None:
        """A warning fault of the policy (its strategy's)."""
        if self._arm is not None:
            self._fault(self._arm, code, message, Severity.WARNING)

    async def suspend(self) -> None:
        """Pause the policy for its own strategy: return once the control loop holds, its
        queue dropped (the worker stays loaded); `unsuspend` resumes it from a fresh
        observation, as a resume does."""
        self._suspended = True
        self._unsuspended = trio.Event()
        self.counters.resets += 1
        if not self._holding:
            self._held = trio.Event()
            await self._held.wait()

    def unsuspend(self) -> None:
        """End `suspend`."""
        self._suspended = False
        self._unsuspended.set()

    def _halted(self, arm: Arm) -> bool:
        return arm.paused or self._suspended

    async def _wait_running(self, arm: Arm) -> None:
        """Return once neither the robot nor the policy's strategy holds it paused."""
        while self._halted(arm):
            if arm.paused:
                await arm.wait_resumed()
            else:
                await self._unsuspended.wait()

    async def prepare(self) -> None:
        """Start the worker, load the policy and check it against the robot; POLICY_INVALID
        with the reason if the directory is not a policy or the robot cannot feed it,
        POLICY_NOT_READY if the worker exits or has not loaded it within `load_timeout`."""
        with trio.move_on_after(self.settings.load_timeout) as bound:
            await self._load()
        if bound.cancelled_caught:
            await self.close()
            raise ArenaError(
                ErrorCode.POLICY_NOT_READY,
                f"The policy worker did not load {self.settings.path} within "
                f"{self.settings.load_timeout:g} s; it was stopped.",
            )
        assert self.loaded is not None
        loaded = self.loaded
        log.info(
            "policy %s loaded in %.1f s (LeRobot %s, Python %s)",
            self.identity,
            loaded.seconds,
            loaded.lerobot,
            loaded.python,
        )

    async def _load(self) -> None:
        self.process = await self.start_worker()
        try:
            self.loaded = await self.process.load(self.settings.path)
            self.counters.loads += 1
            check_features(
                self.loaded,
                self.model,
                list(self.cameras()),
                len(self.settings.environment_state),
            )
            chunk = self.settings.actions_per_chunk or self.loaded.chunk_size
            self.queue = ActionQueue(
                chunk,
                self.settings.chunk_size_threshold,
                self.settings.aggregate_fn_name,
                blend_steps=self.settings.blend_steps,
            )
        except WorkerGone as exc:
            await self.close()
            raise ArenaError(
                ErrorCode.POLICY_NOT_READY, f"Loading {self.settings.path}: {exc}."
            ) from None
        except WorkerError as exc:
            await self.close()
            raise ArenaError(ErrorCode.POLICY_INVALID, f"{self.settings.path}: {exc}.") from None
        except BaseException:
            await self.close()
            raise

    async def close(self) -> None:
        """Stop the worker (nothing to do if it never started)."""
        if self.process is not None:
            await self.process.close()

    async def run(self, link: MasterLink) -> None:
        """Drive the robot until an e-stop, a detach, the worker's end, or the end of its
        strategy (an episodic one's last episode)."""
        arm = LinkArm(link, self.model)
        self._arm = arm
        if self.settings.strategy is None:
            await self.drive(arm)
            return
        self.rollout = Rollout(self.settings.strategy, self, link.robot, arm, self.keeper)
        async with trio.open_nursery() as nursery:

            async def driving() -> None:
                await self.drive(arm)
                nursery.cancel_scope.cancel()  # the worker ended: so does the strategy

            nursery.start_soon(driving)
            await self.rollout.run()
            nursery.cancel_scope.cancel()

    async def drive(self, arm: Arm) -> None:
        """Drive `arm` until the robot stops the policy for good or the worker ends; the
        worker is stopped on the way out."""
        if self.process is None or self.queue is None or self.loaded is None:
            raise RuntimeError("PolicyMaster.drive before prepare")
        try:
            async with trio.open_nursery() as nursery:
                nursery.start_soon(self._infer, arm, self.process, self.queue, self.loaded)
                await self._control(arm, self.queue)
                nursery.cancel_scope.cancel()
        finally:
            await self.close()

    # -- the control loop ------------------------------------------------------------------------

    async def _control(self, arm: Arm, queue: ActionQueue) -> None:
        period = 1.0 / self.settings.fps
        empty = 0
        tick = trio.current_time()
        while True:
            tick += period
            await trio.sleep_until(tick)
            if self._halted(arm):
                await self._hold(arm, queue)
                tick, empty = trio.current_time(), 0
                continue
            late = trio.current_time() - tick
            if late > period / 2:
                # Woke late (a busy machine): the next step comes a full period after this one,
                # as in LeRobot's control loop, never as a burst that makes up for lost time.
                # (A smaller delay keeps the schedule, so the rate does not drift below fps.)
                tick += late
            item = queue.next_action()
            if queue.ready_for_observation():
                self._wake.set()
            if item is None:
                if self._armed:
                    empty += 1
                if empty == self.settings.stall_periods:
                    self._stalled(arm, empty * period)
                if empty >= self.settings.stall_periods and self._worker_gone:
                    return  # nothing more will come: hand the robot back, holding
                continue
            empty = 0
            if not await self._step(arm, item[1]):
                return

    async def _hold(self, arm: Arm, queue: ActionQueue) -> None:
        """The robot paused the policy: drop what it computed, send nothing until resumed
        (the worker stays loaded), then start over from a fresh observation; its first step
        meets the step limit from the pose measured then, as every step does."""
        self._epoch += 1
        self.counters.pauses = arm.pauses
        self.counters.dropped += len(queue)
        queue.drop()
        self._holding = True
        self._held.set()
        try:
            await self._wait_running(arm)
        finally:
            self._holding = False
        self.counters.dropped += len(queue)  # (a chunk that came meanwhile is stale too)
        queue.drop()
        self._armed = False  # waiting for the fresh chunk is no stall
        self._last_targets = None  # the arm may have moved meanwhile: no interpolation from it
        self._wake.set()

    def _stalled(self, arm: Arm, waited: float) -> None:
        """The watchdog: no action was due for `stall_periods` periods; the robot holds."""
        self.counters.stalls += 1
        why = self._failure or "inference is slower than the policy's fps"
        self._fault(
            arm,
            ErrorCode.POLICY_STALLED,
            f"No action due for {waited * 1000:.0f} ms ({why}): the robot holds where it is.",
            Severity.WARNING,
        )

    async def _step(self, arm: Arm, action: tuple[float, ...]) -> bool:
        """One action through the policy rules, then as a command; False once the robot has
        stopped the policy for good."""
        names = [joint.name for joint in self.model.joints]
        check = check_step(
            names,
            action_targets(self.model, action),
            arm.measured(),
            self.settings.max_relative_target,
        )
        if check.invalid is not None:
            self.counters.invalid += 1
            if self.counters.invalid == 1 or self._last_valid:
                self._fault(
                    arm,
                    ErrorCode.POLICY_OUTPUT_INVALID,
                    f"An action was refused: {check.invalid}; nothing of it was sent.",
                    Severity.ERROR,
                )
            self._last_valid = False
            return True
        self._last_valid = True
        self.counters.clamped += len(check.clamped)
        targets = check.targets
        parts = self.settings.interpolation_multiplier
        before = self._last_targets
        self._last_targets = targets
        if parts <= 1 or before is None or arm.paused:
            return await self._send(arm, targets)
        # Interpolated: `parts` commands a period, from the last target to this action, the
        # action itself last (so it is reached within its period, not a period late).
        sub = 1.0 / (self.settings.fps * parts)
        for k in range(1, parts + 1):
            if k > 1:
                await trio.sleep(sub)
                if arm.paused:
                    return True
            w = k / parts
            part = {
                name: before[name] + w * (value - before[name]) for name, value in targets.items()
            }
            if not await self._send(arm, part):
                return False
        return True

    async def _send(self, arm: Arm, targets: dict[str, float]) -> bool:
        """One command of `targets`; False once the robot has stopped the policy for good."""
        command = Command(
            tuple(JointGoal(name, value) for name, value in targets.items()),
            source=self.identity,
        )
        result = await arm.command(command)
        if result.accepted:
            self.counters.sent += 1
            return True
        self.refusals.append((result.code, result.message))
        return result.code not in _FINAL_REFUSALS

    def _fault(self, arm: Arm, code: ErrorCode, message: str, severity: Severity) -> None:
        log.warning("policy %s: %s: %s", self.identity, code, message)
        arm.fault(self.identity, code, message, severity)

    # -- inference -------------------------------------------------------------------------------

    async def _infer(self, arm: Arm, process: Worker, queue: ActionQueue, loaded: Loaded) -> None:
        """Send an observation whenever the control loop says the queue is low."""
        period = 1.0 / self.settings.fps
        self._wake.set()  # the first observation goes at once
        while True:
            await self._wake.wait()
            self._wake = trio.Event()
            if self._halted(arm):
                await self._wait_running(arm)
                continue  # the control loop wakes this task once it has dropped the queue
            if not queue.ready_for_observation():
                # a wake-up of the control loop's from while the last inference ran: the chunk
                # it brought has filled the queue since (LeRobot checks the queue as it sends)
                continue
            shots = self.cameras()
            jpegs = {name: None if shot is None else shot.jpeg for name, shot in shots.items()}
            images, missing = camera_images(jpegs, loaded)
            if missing:
                self._failure = f"no frame yet from camera {', '.join(missing)}"
                await trio.sleep(period)
                self._wake.set()
                continue
            step = queue.observation_step
            observation = Observe(
                step,
                lerobot_state(self.model, arm.measured()),
                images,
                self.settings.task,
                self.settings.environment_state,
            )
            sent = trio.current_time()
            captured = [s.captured for n, s in shots.items() if s is not None and n in images]
            epoch = self._epoch
            try:
                # (never cancelled half-way: a read cut short would leave the worker unusable)
                chunk = await process.act(observation)
            except WorkerError as exc:
                self._failure = str(exc)
                self._armed = True
                if isinstance(exc, WorkerGone):
                    self._worker_gone = True
                    return
                await trio.sleep(period)  # the policy failed this once: try again, paced
                self._wake.set()
                continue
            if epoch != self._epoch or self._halted(arm):
                self.counters.dropped += len(chunk.actions)
                continue  # observed before a pause: stale (the resume asks afresh)
            self._failure = None
            self._armed = True
            self.counters.inferences += 1
            self.counters.last_latency = chunk.latency
            self.counters.last_chunk = len(chunk.actions)
            kept = queue.add_chunk(chunk.timestep, chunk.actions)
            inference = Inference(
                chunk.timestep,
                len(chunk.actions),
                kept,
                trio.current_time() - sent,
                chunk.latency,
                sent - min(captured) if captured else None,
            )
            arm.inferred(self.identity, inference)
