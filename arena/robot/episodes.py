"""Data-collection episodes of one robot: a pure record of which one is running.

An episode is a stretch of a session marked for a dataset (`arena export`), with the task a
policy should learn from it. At most one runs at a time. `discard` ends the running episode, or
with none running takes back the last one stopped, as LeRobot's "re-record" does; a discarded
episode stays in the recording (nothing recorded is ever deleted) and export skips it. An
episode still running when its robot stops (the server's shutdown, the robot deleted) is `cut`:
ended there, kept, and recorded as cut, so that export and `arena inspect` say so.
"""

from __future__ import annotations

from dataclasses import dataclass

from arena.protocol.errors import ArenaError, ErrorCode

#: Longest task text (LeRobot keeps tasks as strings in a parquet table).
MAX_TASK_CHARS = 1000


@dataclass(frozen=True, slots=True)
class Episode:
    """One episode: its number, task and start (trio time)."""

    index: int
    task: str
    started: float
    ended: float | None = None
    discarded: bool = False
    cut: bool = False  # ended because its robot stopped, not by a `stop`


class Episodes:
    """The episodes of one robot. Owned by its actor: no locking."""

    def __init__(self) -> None:
        self.active: Episode | None = None
        self.last: Episode | None = None  # the last episode that ended
        self.kept = 0
        self.discarded = 0
        #: Corrections (interventions started) in the running episode.
        self.corrections = 0
        self._next = 0

    def act(
        self, action: str, task: str, now: float, since: float = 0.0, keep: float = 0.0
    ) -> Episode:
        """`start` (with `task`), `stop`, `discard` or `highlight` (with `task`, `since` and
        `keep`), by the action's name."""
        if action == "start":
            return self.start(task, now)
        if action == "highlight":
            return self.highlight(task, max(since, now - keep), now)
        return self.stop(now) if action == "stop" else self.discard(now)

    def start(self, task: str, now: float) -> Episode:
        """Start an episode; refused while one runs."""
        if self.active is not None:
            raise ArenaError(
                ErrorCode.EPISODE_ACTIVE,
                f"Episode {self.active.index} is still running: stop or discard it first.",
            )
        task = task.strip()
        if not task or len(task) > MAX_TASK_CHARS:
            raise ArenaError(
                ErrorCode.INVALID_BODY,
                f'"task" must say what the episode shows, in 1 to {MAX_TASK_CHARS} characters.',
            )
        self.active = Episode(self._next, task, now)
        self.corrections = 0
        self._next += 1
        return self.active

    def corrected(self) -> None:
        """An intervention started: one more correction in the running episode, if one runs."""
        if self.active is not None:
            self.corrections += 1

    def running_corrections(self) -> int | None:
        """The running episode's corrections, None with no episode running."""
        return None if self.active is None else self.corrections

    def highlight(self, task: str, since: float, now: float) -> Episode:
        """Keep what happened from `since` to `now` as an episode, at once (a rollout's
        highlight: specs/policy.md). It starts no earlier than the last episode's end, so
        two never overlap; refused while an episode runs."""
        if self.last is not None and self.last.ended is not None:
            since = max(since, self.last.ended)
        since = min(since, now)
        self.start(task, since)
        return self.stop(now)

    def stop(self, now: float) -> Episode:
        """End the running episode and keep it."""
        if self.active is None:
            raise ArenaError(ErrorCode.NO_EPISODE, "No episode is running.")
        ended = Episode(self.active.index, self.active.task, self.active.started, now)
        self.active, self.last = None, ended
        self.kept += 1
        return ended

    def cut(self, now: float) -> Episode | None:
        """The robot stops: end the running episode there and keep it, marked cut (None: no
        episode runs)."""
        if self.active is None:
            return None
        episode = self.active
        ended = Episode(episode.index, episode.task, episode.started, now, cut=True)
        self.active, self.last = None, ended
        self.kept += 1
        return ended

    def discard(self, now: float) -> Episode:
        """End the running episode without keeping it, or take back the last one kept."""
        if self.active is not None:
            episode = self.active
            ended = Episode(episode.index, episode.task, episode.started, now, True)
            self.active = None
        elif self.last is not None and not self.last.discarded:
            episode = self.last
            ended = Episode(episode.index, episode.task, episode.started, episode.ended, True)
            self.kept -= 1
        else:
            raise ArenaError(ErrorCode.NO_EPISODE, "No episode to discard.")
        self.last = ended
        self.discarded += 1
        return ended

    def as_dict(self, now: float) -> dict[str, object]:
        """What `GET .../episodes` answers."""
        active = None
        if self.active is not None:
            active = {
                "index": self.active.index,
                "task": self.active.task,
                "elapsed": round(now - self.active.started, 3),
                "corrections": self.corrections,
            }
        last = None
        if self.last is not None:
            last = {
                "index": self.last.index,
                "task": self.last.task,
                "duration": round((self.last.ended or now) - self.last.started, 3),
                "discarded": self.last.discarded,
            }
        return {"active": active, "kept": self.kept, "discarded": self.discarded, "last": last}
