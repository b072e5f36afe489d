"""The spans of time in one robot's recording that an export cuts it into: its kept episodes
(`episodes_of`) and its corrections (`corrections_of`: an intervening master drove while the
running master waited, paused), each as a `Span` of MCAP log time. Pure: messages in, spans
out (specs/lerobot.md)."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from arena.recording.mcap_file import RecordedMessage


@dataclass(frozen=True)
class Span:
    """One episode: its index and task, its ends in log time (ns), and how it ended: `stop`
    (someone stopped it), `cut` (its robot stopped first: the server shut down, or the robot
    was deleted) or `file` (the file ended before it did: a killed server)."""

    index: int
    task: str
    start: int
    end: int
    ended: str = "stop"

    @property
    def complete(self) -> bool:
        """True when someone stopped it: it is as long as they meant it to be."""
        return self.ended == "stop"


def episodes_of(messages: Sequence[RecordedMessage], default_task: str) -> list[Span]:
    """The kept episodes of one robot's messages (time-ordered). With no episode records the
    whole recording is one episode; an episode the file cut short ends at its last message."""
    if not messages:
        return []
    last = messages[-1].log_time
    marks = [m for m in messages if m.kind == "episode"]
    if not marks:
        return [Span(0, default_task, messages[0].log_time, last)]
    open_: dict[int, RecordedMessage] = {}
    spans: dict[int, Span] = {}
    discarded: set[int] = set()
    for mark in marks:
        index, change = int(mark.data["index"]), mark.data["change"]
        if change == "start":
            open_[index] = mark
        elif index in open_:
            start = open_.pop(index)
            ended = "cut" if change == "cut" else "stop"
            task = str(start.data["task"])
            spans[index] = Span(index, task, start.log_time, mark.log_time, ended)
            if change == "discard":
                discarded.add(index)
        elif change == "discard":
            discarded.add(index)  # a kept episode taken back
    for index, start in open_.items():
        spans[index] = Span(index, str(start.data["task"]), start.log_time, last, "file")
    return [spans[i] for i in sorted(spans) if i not in discarded]


def episode_notes(spans: Iterable[Span]) -> list[str]:
    """What an export says of the episodes that nobody stopped (each is kept as it is)."""
    notes = []
    for span in spans:
        if span.ended == "file":
            notes.append(f"episode {span.index} has no stop: it ends where the file does")
        elif span.ended == "cut":
            notes.append(
                f"episode {span.index} was cut short: its robot stopped (a server shutdown, "
                "the robot deleted) before the episode was stopped"
            )
    return notes


@dataclass(frozen=True)
class Correction:
    """One intervention: `master` drove from `start` (its first accepted command after the
    intervention started) to `end` (the intervention's end, or the file's), log time in ns,
    within the episode `episode`."""

    episode: Span
    master: str
    start: int
    end: int


def corrections_of(messages: Sequence[RecordedMessage], spans: Sequence[Span]) -> list[Correction]:
    """The corrections within the kept episodes `spans` (time-ordered messages): each
    intervention from the first command its master had accepted to its end, clipped to its
    episode; one that never commanded corrected nothing."""
    found: list[Correction] = []
    open_: dict[str, int | None] = {}  # intervening master -> its first command (None: none yet)
    last = messages[-1].log_time if messages else 0
    windows: list[tuple[str, int, int]] = []
    for message in messages:
        if message.kind == "intervention":
            master = str(message.data["master"])
            if message.data["change"] == "started":
                open_[master] = None
            elif master in open_:
                first = open_.pop(master)
                if first is not None:
                    windows.append((master, first, message.log_time))
        elif message.kind == "command" and message.data["accepted"]:
            source = str(message.data["source"])
            if source in open_ and open_[source] is None:
                open_[source] = message.log_time
    windows += [(master, first, last) for master, first in open_.items() if first is not None]
    for master, start, end in sorted(windows, key=lambda window: window[1]):
        for span in spans:
            begin, stop = max(start, span.start), min(end, span.end)
            if begin < stop:
                found.append(Correction(span, master, begin, stop))
    return found


def commanding(corrections: Sequence[Correction], at: int) -> bool:
    """Whether an intervening master commanded at log time `at` (a frame LeRobot marks
    `intervention`)."""
    return any(c.start <= at < c.end for c in corrections)


def correction_spans(corrections: Sequence[Correction]) -> list[Span]:
    """Each correction as an episode of its own (`--corrections-only`), with its episode's
    task, numbered in order."""
    return [
        Span(number, c.episode.task, c.start, c.end, c.episode.ended)
        for number, c in enumerate(corrections)
    ]
