"""The mock-sequence master: plays sequences onto a robot with their recorded timing."""

from __future__ import annotations

import logging
from collections.abc import Iterable

import trio

from arena.drivers.refusals import Refusals
from arena.drivers.sequences import Sequence
from arena.protocol.errors import ErrorCode
from arena.robot.links import MasterLink

log = logging.getLogger(__name__)

#: Refusals after which a sequence stops rather than skipping the keyframe.
_FINAL_REFUSALS = frozenset({ErrorCode.ESTOPPED, ErrorCode.NOT_OWNER})


#: The shortest time one round of a looping sequence master takes (seconds).
MIN_LOOP_PERIOD = 0.02


class SequenceMaster:
    """Plays `sequences` in order, once or forever (`loop`).

    With `auto_start` off it claims the robot and waits for `start()`. Attaching it takes the
    robot over (the seed's "automatic master takeover"; `POST .../master` turns that off unless
    asked). It is autonomous: an e-stop ends it for good, and it never resumes by itself.
    """

    kind = "mock-sequence"
    autonomous = True
    takes_over = True  # the seed's sequences take the robot over from its master

    def __init__(
        self, sequences: Iterable[Sequence], *, loop: bool = False, auto_start: bool = True
    ) -> None:
        self.sequences = tuple(sequences)
        if not self.sequences:
            raise ValueError("a sequence master needs at least one sequence")
        self.loop = loop
        self._started = trio.Event()
        if auto_start:
            self._started.set()
        self.playing: str | None = None
        self.refusals = Refusals()

    @property
    def description(self) -> str:
        """What it plays, in words (told to a master it takes over from, shown with the
        robot's master)."""
        names = ", ".join(repr(sequence.id) for sequence in self.sequences)
        what = f"sequence {names}" if len(self.sequences) == 1 else f"sequences {names}"
        return f"{what} in a loop" if self.loop else what

    def start(self) -> None:
        """Begin playing (for a master created with `auto_start=False`)."""
        self._started.set()

    async def run(self, link: MasterLink) -> None:
        """Issue every keyframe at its time; return when done (unless looping)."""
        await self._started.wait()
        try:
            while True:
                started = trio.current_time()
                for sequence in self.sequences:
                    if not await self._play(link, sequence):
                        return
                if not self.loop:
                    return
                # A loop of (nearly) no duration would spin a core: pace every round.
                await trio.sleep_until(started + MIN_LOOP_PERIOD)
        finally:
            self.playing = None

    async def _play(self, link: MasterLink, sequence: Sequence) -> bool:
        """Play one sequence; False if the robot stopped it (e-stop, lost ownership)."""
        self.playing = sequence.id
        # The master's own clock: it stands still while the robot has it paused.
        start = trio.current_time() - link.paused_time(trio.current_time())
        for keyframe in sequence.keyframes:
            await link.sleep_until(start + keyframe.at)
            result = await link.command(keyframe.command)
            if not result.accepted:
                self.refusals.append((result.code, result.message))
                log.warning("sequence %s: keyframe refused: %s", sequence.id, result.message)
                if result.code in _FINAL_REFUSALS:
                    return False  # stopped for good: never resume by itself
                # Otherwise (a rate limit, say) keep going with the next keyframe.
        await link.sleep_until(start + sequence.total_duration)
        return True
