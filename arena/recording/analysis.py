"""Offline debugging: summaries, timelines and exports of a recording (cut or unfinished too)."""

from __future__ import annotations

import csv
import io
import json
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Any

from arena.protocol.errors import ArenaError, ErrorCode
from arena.recording.mcap_file import RecordedMessage, Recording

#: A slave that leaves its robot's targets unanswered longer than this (seconds) is a gap.
GAP_SECONDS = 1.0
#: What a gap is, in the words `arena inspect` prints.
GAP_MEANING = f"a slave left targets unanswered for over {GAP_SECONDS:g} s"


def _seconds(message: RecordedMessage, origin: int) -> float:
    return (message.log_time - origin) / 1e9


def summarize(recording: Recording) -> dict[str, Any]:
    """Robots, time span, per-topic counts and rates, gaps, e-stops, faults, tracking error.

    `messages` counts every message of the file, Arena's records and Foxglove's view
    (`arena_messages`, `view_messages`), as `arena recover` writes them.
    """
    messages = recording.messages
    summary: dict[str, Any] = {
        "file": recording.path.name,
        "truncated": recording.truncated,
        "in_progress": recording.in_progress,
        "messages": recording.message_count,
        "arena_messages": len(messages),
        "view_messages": len(recording.views),
        "robots": {},
    }
    if not messages:
        return summary
    origin = min(m.log_time for m in messages)
    end = max(m.log_time for m in messages)
    summary["start_ns"], summary["end_ns"] = origin, end
    summary["duration_s"] = round((end - origin) / 1e9, 6)
    by_topic: dict[str, list[int]] = defaultdict(list)
    for message in messages:
        by_topic[message.topic].append(message.log_time)
    for view in recording.views:
        by_topic[view.topic].append(view.log_time)
    topics = {}
    for name, times in sorted(by_topic.items()):
        span = (max(times) - min(times)) / 1e9
        topics[name] = {
            "count": len(times),
            "rate_hz": round((len(times) - 1) / span, 3) if span > 0 else None,
        }
    summary["topics"] = topics
    summary["gaps"] = find_gaps(messages, origin)
    summary["estops"] = [
        {
            "robot": m.robot_id,
            "at_s": round(_seconds(m, origin), 3),
            "reason": m.data["estop_reason"],
        }
        for m in messages
        if m.kind == "state" and m.data["mode"] == "estopped"
    ]
    summary["faults"] = [
        {
            "robot": m.robot_id,
            "at_s": round(_seconds(m, origin), 3),
            "code": m.data["code"],
            "severity": m.data["severity"],
            "joint": m.data["joint"],
            "message": m.data["message"],
        }
        for m in messages
        if m.kind == "fault" and not m.data.get("cleared")
    ]
    # Who did what (issue 49): each caller's action, and the masters they connected as.
    summary["audit"] = [
        {
            "robot": m.robot_id,
            "at_s": round(_seconds(m, origin), 3),
            "user": m.data["user"],
            "action": m.data["action"],
            "detail": m.data["detail"],
        }
        for m in messages
        if m.kind == "audit"
    ]
    summary["users"] = sorted({entry["user"] for entry in summary["audit"]})
    summary["episodes"] = list_episodes(messages, origin, end)
    summary["refused_commands"] = sum(
        1 for m in messages if m.kind == "command" and not m.data["accepted"]
    )
    for robot_id in dict.fromkeys(m.robot_id for m in messages):
        meta = recording.metadata.get(f"robot/{robot_id}", {})
        summary["robots"][robot_id] = {
            "robot_type": meta.get("robot_type"),
            "tracking_error_deg": tracking_errors(messages, robot_id),
        }
    return summary


def list_episodes(messages: list[RecordedMessage], origin: int, end: int) -> list[dict[str, Any]]:
    """Every episode, in the order they started: its robot, index and task, when it started
    and how long it ran (seconds), and how it `ended`: `stop`, `discard`, `cut` (its robot
    stopped first: a server shutdown, the robot deleted) or `file` (the file ends first: a
    killed server). A kept episode taken back later says `discard`."""
    found: dict[tuple[str, int], dict[str, Any]] = {}
    started: dict[tuple[str, int], int] = {}
    for message in messages:
        if message.kind != "episode":
            continue
        key = (message.robot_id, int(message.data["index"]))
        if message.data["change"] == "start":
            started[key] = message.log_time
            found[key] = {
                "robot": message.robot_id,
                "index": key[1],
                "task": message.data["task"],
                "at_s": round(_seconds(message, origin), 3),
                "seconds": None,
                "ended": "file",
            }
        elif key in found:
            entry = found[key]
            if entry["seconds"] is None:
                entry["seconds"] = round((message.log_time - started[key]) / 1e9, 3)
            entry["ended"] = message.data["change"]
    for key, entry in found.items():
        if entry["seconds"] is None:
            entry["seconds"] = round((end - started[key]) / 1e9, 3)
    return list(found.values())


def find_gaps(messages: list[RecordedMessage], origin: int) -> list[dict[str, Any]]:
    """The real gaps: each time a robot sent its slaves targets and a slave reported no joint
    state for more than `GAP_SECONDS` (the slave, its link or the recording lost it).

    A robot at rest is silent on every topic: that is no gap. A slave is expected to answer
    from its first joint state (one that never reports, a display, is not) until it is
    detached or lost; an e-stop forgives what it left unanswered. A gap still open at the end
    of the file ends there.
    """
    gaps: list[dict[str, Any]] = []
    # robot -> slave -> log time of the first target it has not answered yet (None: none)
    waiting: dict[str, dict[str, int | None]] = defaultdict(dict)

    def answered(robot: str, slave: str, at: int, until: str) -> None:
        since = waiting[robot].get(slave)
        if since is not None and (at - since) / 1e9 > GAP_SECONDS:
            gaps.append(
                {
                    "robot": robot,
                    "slave": slave,
                    "from_s": round((since - origin) / 1e9, 3),
                    "seconds": round((at - since) / 1e9, 3),
                    "until": until,
                }
            )
        waiting[robot][slave] = None

    for message in messages:
        robot, data, at = message.robot_id, message.data, message.log_time
        slaves = waiting[robot]
        if message.kind == "targets":
            for slave, since in slaves.items():
                if since is None:
                    slaves[slave] = at
        elif message.kind == "joint_states":
            answered(robot, data["slave_id"], at, "joint state")
        elif (
            message.kind == "peer"
            and data["role"] == "slave"
            and data["change"] in ("detached", "lost")
            and data["peer_id"] in slaves
        ):
            answered(robot, data["peer_id"], at, data["change"])
            del slaves[data["peer_id"]]
        elif message.kind == "state" and data["mode"] == "estopped":
            slaves.update(dict.fromkeys(slaves))
    end = max((m.log_time for m in messages), default=origin)
    for robot, slaves in waiting.items():
        for slave in list(slaves):
            answered(robot, slave, end, "end of file")
    return sorted(gaps, key=lambda gap: gap["from_s"])


@dataclass
class JointSeries:
    """One robot's joints over a recording: (seconds, degrees) points, and e-stop instants."""

    virtual: dict[str, list[tuple[float, float]]] = field(default_factory=dict)
    real: dict[str, list[tuple[float, float]]] = field(default_factory=dict)
    estops: list[float] = field(default_factory=list)

    @property
    def joints(self) -> list[str]:
        """Joint names in the order they first appear."""
        return list(dict.fromkeys([*self.virtual, *self.real]))


def joint_series(recording: Recording, robot_id: str) -> JointSeries:
    """Targets (virtual) and measured (real) values of each joint, seconds from the robot's start.

    Raises `ArenaError(UNKNOWN_ROBOT)` when the robot is not in the recording.
    """
    mine = [m for m in recording.messages if m.robot_id == robot_id]
    if not mine:
        raise ArenaError(ErrorCode.UNKNOWN_ROBOT, f"No robot {robot_id!r} in the recording.")
    origin = min(float(m.data["t"]) for m in mine)
    series = JointSeries()
    for message in mine:
        at = float(message.data["t"]) - origin
        if message.kind in ("targets", "joint_states"):
            into = series.virtual if message.kind == "targets" else series.real
            for joint, value in message.data["joints"].items():
                into.setdefault(joint, []).append((at, value))
        elif message.kind == "state" and message.data["mode"] == "estopped":
            series.estops.append(at)
    return series


def thin(points: list[tuple[float, float]], most: int) -> list[tuple[float, float]]:
    """At most `most` points, evenly picked, the first and the last always kept (for plots)."""
    if len(points) <= most:
        return points
    if most < 2:
        return points[-most:] if most > 0 else []
    step = (len(points) - 1) / (most - 1)
    return [points[round(i * step)] for i in range(most)]


def tracking_errors(messages: list[RecordedMessage], robot_id: str) -> dict[str, float]:
    """Largest |virtual - real| per joint: each measured value against the latest target."""
    virtual: dict[str, float] = {}
    worst: dict[str, float] = {}
    for message in messages:
        if message.robot_id != robot_id:
            continue
        if message.kind == "targets":
            virtual.update(message.data["joints"])
        elif message.kind == "joint_states":
            for joint, real in message.data["joints"].items():
                if joint in virtual:
                    error = abs(virtual[joint] - real)
                    worst[joint] = round(max(worst.get(joint, 0.0), error), 6)
    return worst


def timeline(
    recording: Recording,
    robot: str | None = None,
    start: float | None = None,
    end: float | None = None,
) -> list[str]:
    """The events in order, one readable line each (seconds from the start of the file)."""
    if not recording.messages:
        return []
    origin = min(m.log_time for m in recording.messages)
    lines = []
    users: dict[str, str] = {}  # a master's peer id -> who connected it
    for message in recording.messages:
        if message.kind == "audit" and message.data["action"].startswith("connect"):
            users[message.data["detail"]] = message.data["user"]
        at = _seconds(message, origin)
        if robot is not None and message.robot_id != robot:
            continue
        if (start is not None and at < start) or (end is not None and at > end):
            continue
        said = _describe(message)
        if message.kind == "command" and message.data["source"] in users:
            said += f" (by {users[message.data['source']]})"
        lines.append(f"{at:10.3f}  {message.robot_id:<14} {message.kind:<12} {said}")
    return lines


def _describe(message: RecordedMessage) -> str:
    """One record in words: each kind has its own sentence; a kind this reader does not know
    (a newer server's) is its fields, so that no record stops the timeline."""
    data = message.data
    kind = message.kind
    if kind == "command":
        joints = " ".join(f"{j['name']}={j['value']:g}" for j in data["joints"])
        verdict = "accepted" if data["accepted"] else f"refused {data['code']}"
        if data["accepted"] and data.get("clamped"):
            verdict = "clamped " + ", ".join(
                f"{c['joint']} {c['requested']:g} -> {c['applied']:g}" for c in data["clamped"]
            )
        duration = f" over {data['duration']:g} ms" if data.get("duration") else ""
        return f"from {data['source']}: {joints}{duration} -> {verdict}"
    if kind in ("targets", "joint_states"):
        values = " ".join(f"{k}={v:.2f}" for k, v in data["joints"].items())
        origin = f"{data['slave_id']}: " if kind == "joint_states" else ""
        return origin + values
    if kind == "state":
        extra = f" ({data['estop_reason']})" if data["estop_reason"] else ""
        owner = f" owner={data['owner']}" if data["owner"] else ""
        return f"{data['mode']}{owner}{extra} <- {data['cause']}"
    if kind == "fault":
        joint = f" on {data['joint']}" if data.get("joint") else ""
        if data.get("cleared"):
            return f"over: {data['code']} of {data['peer_id']}{joint}: {data['message']}"
        return f"{data['severity']} {data['code']} from {data['peer_id']}{joint}: {data['message']}"
    if kind == "audit":
        detail = f" ({data['detail']})" if data["detail"] else ""
        return f"{data['user']}: {data['action']}{detail}"
    if kind == "peer":
        code = f" {data['code']}" if data.get("code") else ""  # (a refusal's; older files: none)
        change = f"{data['change']}{code} {data['reason']}".rstrip()
        return f"{data['role']} {data['peer_id']} ({data['kind']}) {change}"
    if kind == "episode":
        return f"{data['change']} episode {data['index']}: {data['task']}"
    if kind == "policy":
        age = data.get("frame_age")
        frame = "" if age is None else f", frame {age * 1000:.0f} ms old"
        return (
            f"{data['policy']} step {data['timestep']}: chunk {data['chunk_size']} "
            f"({data['kept']} kept) in {data['latency'] * 1000:.1f} ms{frame}"
        )
    return " ".join(f"{key}={value}" for key, value in data.items() if key != "t")


def export(recording: Recording, fmt: str, topic: str | None = None) -> str:
    """The messages as JSON lines or CSV (one column per field; joints flattened)."""
    chosen = [m for m in recording.messages if topic is None or m.topic == topic]
    if fmt == "jsonl":
        return "".join(
            json.dumps({"topic": m.topic, "log_time": m.log_time, **m.data}) + "\n" for m in chosen
        )
    rows = [_flatten(m) for m in chosen]
    columns = list(dict.fromkeys(key for row in rows for key in row))
    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=columns)
    writer.writeheader()
    writer.writerows(rows)
    return out.getvalue()


def _flatten(message: RecordedMessage) -> dict[str, Any]:
    row: dict[str, Any] = {"topic": message.topic, "log_time": message.log_time}
    for key, value in message.data.items():
        if key == "joints" and isinstance(value, dict):
            row.update({f"joint.{name}": v for name, v in value.items()})
        elif key == "joints" and isinstance(value, list):
            row.update({f"joint.{j['name']}": j["value"] for j in value})
        elif isinstance(value, dict | list):
            row[key] = json.dumps(value)
        else:
            row[key] = value
    return row
