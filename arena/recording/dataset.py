"""Recordings to LeRobot datasets and back (`arena export --format lerobot`, `arena
import-dataset`); the mapping is written down in specs/lerobot.md.

The sampling is pure (`episodes_of`, `Track`, `frames_of`): one dataset frame every 1/fps of
the recording's clock (MCAP log time), each value the newest recorded at or before that time.
Writing and reading the dataset itself is LeRobot's own code (`LeRobotDataset.create`,
`add_frame`, `save_episode`, `finalize`; `LeRobotDataset(repo_id, root=...)`), imported only
here and only when asked for: it brings torch. Install it with `pip install 'arena[lerobot]'`.
"""

from __future__ import annotations

import bisect
import json
import sys
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from arena.extras import install_line, require
from arena.protocol.errors import ArenaError, ErrorCode
from arena.recording import images
from arena.recording.dataset_output import camera_shapes, nothing_left_on_failure
from arena.recording.mcap_file import RecordedMessage, Recording, read_recording
from arena.recording.records import camera_of_topic
from arena.recording.spans import (
    Span,
    commanding,
    correction_spans,
    corrections_of,
    episode_notes,
    episodes_of,
)
from arena.robot.model import JointSpec, RobotModel

#: LeRobot's feature names for the so100 follower's joints, by the names Arena gives them
#: (Arena's joint aliases for the so-arm100 are these names).
FEATURE_SUFFIX = ".pos"
#: Gripper values in LeRobot run 0 (closed) to 100 (open), over the joint's range.
GRIPPER_RANGE = 100.0
ROBOT_TYPES = {"so-arm100": "so100_follower", "so-101": "so101_follower"}
DEFAULT_TASK = "teleoperation"
#: A policy master's commands have this source (`policy:<type>:<checkpoint>`, specs/policy.md).
POLICY_SOURCE = "policy:"
#: LeRobot names a dataset recorded with a policy driving `eval_...`, and only such a one.
EVAL_PREFIX = "eval_"
#: LeRobot's feature for the task's state (what Arena does not measure: a reach target).
ENVIRONMENT = "observation.environment_state"
#: The feature LeRobot's DAgger rollouts write: true where the human's correction commanded.
INTERVENTION = "intervention"


def feature_names(model: RobotModel) -> list[str]:
    """LeRobot's names of the robot's joints (`shoulder_pan.pos`, ...), in servo order."""
    return [
        (joint.aliases[0] if joint.aliases else joint.name) + FEATURE_SUFFIX
        for joint in model.joints
    ]


def _is_gripper(joint: JointSpec) -> bool:
    return "gripper" in joint.aliases


def to_dataset(joint: JointSpec, degrees: float) -> float:
    """Arena's wire degrees to LeRobot's value (`use_degrees=True`: degrees; gripper 0-100)."""
    if _is_gripper(joint):
        return (degrees - joint.lower) / (joint.upper - joint.lower) * GRIPPER_RANGE
    return degrees


def from_dataset(joint: JointSpec, value: float) -> float:
    """LeRobot's value back to Arena's wire degrees (the inverse of `to_dataset`)."""
    if _is_gripper(joint):
        return joint.lower + value / GRIPPER_RANGE * (joint.upper - joint.lower)
    return value


@dataclass
class Track:
    """A step function of time: the newest value at or before each time."""

    times: list[int] = field(default_factory=list)
    values: list[Any] = field(default_factory=list)

    def add(self, at: int, value: Any) -> None:
        """Append a value (times must not go backwards)."""
        self.times.append(at)
        self.values.append(value)

    def at(self, when: int) -> Any:
        """The value at `when` (None before the first)."""
        found = bisect.bisect_right(self.times, when) - 1
        return self.values[found] if found >= 0 else None

    @property
    def first(self) -> int | None:
        """When the first value came."""
        return self.times[0] if self.times else None


def commanded(messages: Iterable[RecordedMessage], joints: Sequence[str]) -> Track:
    """What the master asked for, joint by joint, after each accepted command (clamped values
    as applied); a joint no command has named yet follows the robot's own targets."""
    current: dict[str, float] = {}
    commanded_joints: set[str] = set()
    track = Track()
    for message in messages:
        if message.kind == "targets":
            for name, value in message.data["joints"].items():
                if name not in commanded_joints:
                    current[name] = float(value)
        elif message.kind == "command" and message.data["accepted"]:
            applied = {c["joint"]: c["applied"] for c in message.data.get("clamped") or []}
            for goal in message.data["joints"]:
                name = goal["name"]
                current[name] = float(applied.get(name, goal["value"]))
                commanded_joints.add(name)
        else:
            continue
        if all(name in current for name in joints):
            track.add(message.log_time, tuple(current[name] for name in joints))
    return track


def measured(messages: Iterable[RecordedMessage], joints: Sequence[str], slave: str) -> Track:
    """The slave's reported joint values over time (once every joint has been reported)."""
    current: dict[str, float] = {}
    track = Track()
    for message in messages:
        if message.kind == "joint_states" and message.data["slave_id"] == slave:
            current.update({k: float(v) for k, v in message.data["joints"].items()})
            if all(name in current for name in joints):
                track.add(message.log_time, tuple(current[name] for name in joints))
    return track


def policies_in(messages: Iterable[RecordedMessage], spans: Sequence[Span]) -> list[str]:
    """The policies (`policy:<type>:<checkpoint>`) whose commands the robot accepted within
    the episodes `spans`: those whose run the dataset evaluates."""
    found = {
        str(message.data["source"])
        for message in messages
        if message.kind == "command"
        and message.data["accepted"]
        and str(message.data["source"]).startswith(POLICY_SOURCE)
        and any(span.start <= message.log_time <= span.end for span in spans)
    }
    return sorted(found)


def dataset_name(repo_id: str | None, robot_id: str, policies: Sequence[str]) -> str:
    """The dataset's name: `repo_id`, else `arena/ROBOT`, or `arena/eval_ROBOT` when a policy
    drove the episodes. As LeRobot's `lerobot-record` has it, a name starts with `eval_` if
    and only if a policy drove: an explicit name that breaks the rule is refused."""
    if repo_id is None:
        return f"arena/{EVAL_PREFIX if policies else ''}{robot_id}"
    evaluation = repo_id.rsplit("/", 1)[-1].startswith(EVAL_PREFIX)
    if policies and not evaluation:
        raise ArenaError(
            ErrorCode.INVALID_VALUE,
            f"{', '.join(policies)} drove these episodes: an evaluation dataset's name starts "
            f"with {EVAL_PREFIX!r} (--repo-id .../{EVAL_PREFIX}{repo_id.rsplit('/', 1)[-1]}).",
        )
    if evaluation and not policies:
        raise ArenaError(
            ErrorCode.INVALID_VALUE,
            f"--repo-id {repo_id} starts with {EVAL_PREFIX!r}, which names an evaluation "
            "dataset, but no policy drove these episodes.",
        )
    return repo_id


def busiest_slave(messages: Iterable[RecordedMessage]) -> str | None:
    """The slave that reported joint states most often (the arm being recorded)."""
    counts: dict[str, int] = {}
    for message in messages:
        if message.kind == "joint_states":
            slave = str(message.data["slave_id"])
            counts[slave] = counts.get(slave, 0) + 1
    return max(counts, key=lambda s: counts[s]) if counts else None


def frame_times(span: Span, fps: int, earliest: int) -> list[int]:
    """Sample times of an episode: every 1/fps from its start (or from `earliest`, when the
    data begins later) up to its end."""
    start = max(span.start, earliest)
    if start > span.end:
        return []
    step = 1e9 / fps
    count = int((span.end - start) / step + 1e-6) + 1
    return [start + round(k * step) for k in range(count)]


@dataclass
class RobotSession:
    """One robot's recorded messages and camera frames, from one or more files."""

    robot_id: str
    model: RobotModel
    messages: list[RecordedMessage]
    cameras: dict[str, Track]  # camera name -> JPEG bytes over time
    truncated: list[str]  # files cut short, or still being written: why, by name


def load_session(paths: Sequence[Path], robot_id: str) -> RobotSession:
    """Read the files (in time order) and keep what concerns `robot_id`."""
    from arena.robot.model import load_robot_model

    recordings: list[Recording] = [read_recording(path) for path in paths]
    messages: list[RecordedMessage] = []
    frames: dict[str, list[tuple[int, bytes]]] = {}
    robot_type: str | None = None
    seen: set[str] = set()
    for recording in recordings:
        for message in recording.messages:
            seen.add(message.robot_id)
            if message.robot_id == robot_id:
                messages.append(message)
        for view in recording.views:
            camera = camera_of_topic(view.topic)
            if camera is not None and camera[0] == robot_id:
                frames.setdefault(camera[1], []).append((view.log_time, view.data))
        metadata = recording.metadata.get(f"robot/{robot_id}")
        if metadata is not None:
            robot_type = metadata.get("robot_type", robot_type)
    names = ", ".join(p.name for p in paths)
    if not messages:
        held = ", ".join(sorted(seen)) or "no robot at all"
        raise ArenaError(
            ErrorCode.UNKNOWN_ROBOT,
            f"Robot {robot_id!r} (--robot) is not in {names}: it holds {held}.",
        )
    messages.sort(key=lambda m: m.log_time)
    cameras: dict[str, Track] = {}
    for name, found in frames.items():
        track = Track()
        for at, data in sorted(found, key=lambda f: f[0]):
            track.add(at, images.decode(data).data)
        cameras[name] = track
    model = load_robot_model(robot_type or "so-arm100")
    truncated = [
        f"{r.path.name} "
        + ("is still being written" if r.in_progress else "was cut short (a crash?)")
        for r in recordings
        if r.truncated or r.in_progress
    ]
    return RobotSession(robot_id, model, messages, cameras, truncated)


@dataclass
class DatasetFrame:
    """One dataset frame: action and state in LeRobot's units, the camera images as JPEG."""

    at: int
    action: list[float]
    state: list[float]
    jpegs: dict[str, bytes]


def frames_of(session: RobotSession, span: Span, fps: int, slave: str) -> list[DatasetFrame]:
    """The dataset frames of one episode."""
    joints = [joint.name for joint in session.model.joints]
    action = commanded(session.messages, joints)
    state = measured(session.messages, joints, slave)
    starts = [action.first, state.first, *(track.first for track in session.cameras.values())]
    if any(start is None for start in starts):
        return []
    earliest = max(s for s in starts if s is not None)
    specs = session.model.joints
    found = []
    for at in frame_times(span, fps, earliest):
        found.append(
            DatasetFrame(
                at,
                [to_dataset(j, v) for j, v in zip(specs, action.at(at), strict=True)],
                [to_dataset(j, v) for j, v in zip(specs, state.at(at), strict=True)],
                {name: track.at(at) for name, track in session.cameras.items()},
            )
        )
    return found


# -- LeRobot ---------------------------------------------------------------------------------


def _lerobot() -> Any:
    require("lerobot", "A LeRobot dataset")
    try:
        from lerobot.datasets import lerobot_dataset
    except ImportError as exc:  # a LeRobot other than 0.4
        raise ArenaError(
            ErrorCode.NOT_INSTALLED,
            f"LeRobot datasets need LeRobot 0.4: {install_line('lerobot')} ({exc})",
        ) from None
    return lerobot_dataset


class _JpegDecoder:
    """JPEG to RGB arrays, each distinct frame decoded once (a frame repeats when the
    dataset's rate is above the camera's)."""

    def __init__(self) -> None:
        import av

        self._av = av
        self._codec: Any = av.CodecContext.create("mjpeg", "r")
        self._last: tuple[bytes, Any] | None = None

    def rgb(self, jpeg: bytes) -> Any:
        if self._last is not None and self._last[0] is jpeg:
            return self._last[1]
        (frame,) = self._codec.decode(self._av.Packet(jpeg))
        image = frame.to_ndarray(format="rgb24")
        self._last = (jpeg, image)
        return image


@dataclass
class ExportReport:
    """What an export wrote."""

    root: Path
    repo_id: str
    fps: int
    episodes: list[tuple[int, str, int]]  # (recorded index, task, frames)
    cameras: list[str]
    notes: list[str]
    policies: list[str] = field(default_factory=list)  # an evaluation of these (`eval_...`)


def export_lerobot(
    paths: Sequence[Path],
    robot_id: str,
    root: Path,
    *,
    fps: int = 30,
    repo_id: str | None = None,
    slave: str | None = None,
    task: str = DEFAULT_TASK,
    say: Callable[[str], None] = lambda line: print(line, file=sys.stderr),
    environment: Mapping[int, Sequence[float]] | None = None,
    corrections_only: bool = False,
) -> ExportReport:
    """Write a LeRobotDataset (v3.0, with LeRobot's own writer) of one robot's episodes;
    an evaluation dataset (`eval_...`) when a policy drove them. `environment`: the task's
    state of each episode (by its recorded index), which Arena does not measure (a reach
    target): `observation.environment_state` of its every frame; an episode it does not name
    is left out. Episodes with corrections (an intervening master drove) get the feature
    `intervention` (bool, (1,)), true where it commanded; `corrections_only`: each correction
    is an episode of its own, and nothing else is written."""
    lerobot = _lerobot()  # before any work: a missing LeRobot is said first
    if not 1 <= fps <= 1000:
        raise ArenaError(ErrorCode.INVALID_VALUE, "--fps must be 1 to 1000.")
    if root.exists() and any(root.iterdir()):
        raise ArenaError(ErrorCode.INVALID_VALUE, f"{root} (-o) exists and is not empty.")
    session = load_session(paths, robot_id)
    notes = [f"{why}: exported up to its last record" for why in session.truncated]
    if not session.cameras:
        notes.append(
            f"no camera was recorded for {robot_id!r}: the dataset has action and state only"
        )
    slave = slave or busiest_slave(session.messages)
    if slave is None:
        raise ArenaError(
            ErrorCode.INVALID_RECORDING,
            f"No slave of {robot_id!r} reported joint states: there is no observation.state.",
        )
    spans = episodes_of(session.messages, task)
    if not spans:
        raise ArenaError(ErrorCode.INVALID_RECORDING, f"No kept episode of {robot_id!r}.")
    notes += episode_notes(spans)
    for line in notes:
        say(f"note: {line}")
    if environment is not None:
        spans = [span for span in spans if span.index in environment]
    corrections = corrections_of(session.messages, spans)
    if corrections_only:
        if not corrections:
            raise ArenaError(ErrorCode.INVALID_RECORDING, f"No correction of {robot_id!r}.")
        spans = correction_spans(corrections)
        if environment is not None:  # each correction has its episode's state, by its number
            environment = {
                span.index: environment[c.episode.index]
                for span, c in zip(spans, corrections, strict=True)
            }
    frames = [(span, frames_of(session, span, fps, slave)) for span in spans]
    if corrections_only:  # a correction ends where its master stopped commanding: no frame there
        frames = [(span, [f for f in found if f.at < span.end]) for span, found in frames]
    frames = [(span, found) for span, found in frames if found]
    # LeRobot's writer cannot finish a dataset that mixes video episodes of one frame with
    # longer ones (the one-frame episodes' image stats come out short): those are left out.
    if session.cameras and any(len(found) > 1 for _, found in frames):
        for span, found in frames:
            if len(found) == 1:
                line = f"episode {span.index} has one frame at {fps} fps: left out"
                notes.append(line)
                say(f"note: {line}")
        frames = [(span, found) for span, found in frames if len(found) > 1]
    if not frames:
        raise ArenaError(ErrorCode.INVALID_RECORDING, "The episodes hold no complete frame.")
    policies = policies_in(session.messages, [span for span, _ in frames])
    repo_id = dataset_name(repo_id, robot_id, policies)
    decoder = _JpegDecoder()
    jpegs = [(span.index, [frame.jpegs for frame in found]) for span, found in frames]
    shapes = camera_shapes(jpegs, lambda jpeg: decoder.rgb(jpeg).shape)  # one size each
    names = feature_names(session.model)
    features: dict[str, Any] = {
        "action": {"dtype": "float32", "shape": (len(names),), "names": names},
        "observation.state": {"dtype": "float32", "shape": (len(names),), "names": names},
    }
    sizes = {len(values) for values in (environment or {}).values()}
    if len(sizes) > 1:
        raise ArenaError(
            ErrorCode.INVALID_VALUE, "Every episode's environment state needs one size."
        )
    for size in sizes:
        features[ENVIRONMENT] = {"dtype": "float32", "shape": (size,), "names": None}
    if corrections:
        features[INTERVENTION] = {"dtype": "bool", "shape": (1,), "names": None}
    for name, shape in shapes.items():
        features[f"observation.images.{name}"] = {
            "dtype": "video",
            "shape": tuple(shape),
            "names": ["height", "width", "channels"],
        }
    import numpy as np

    dataset = lerobot.LeRobotDataset.create(
        repo_id,
        fps,
        features,
        root=root,
        robot_type=ROBOT_TYPES.get(session.model.robot_type, session.model.robot_type),
        use_videos=True,
        streaming_encoding=bool(shapes),
    )
    written = []
    with nothing_left_on_failure(root):
        try:
            for span, found in frames:
                for frame in found:
                    values: dict[str, Any] = {
                        "action": np.asarray(frame.action, dtype=np.float32),
                        "observation.state": np.asarray(frame.state, dtype=np.float32),
                        "task": span.task,
                    }
                    if environment is not None:
                        values[ENVIRONMENT] = np.asarray(environment[span.index], dtype=np.float32)
                    if corrections:
                        flag = commanding(corrections, frame.at)
                        values[INTERVENTION] = np.asarray([flag], dtype=bool)
                    for name, jpeg in frame.jpegs.items():
                        values[f"observation.images.{name}"] = decoder.rgb(jpeg)
                    dataset.add_frame(values)
                dataset.save_episode()
                written.append((span.index, span.task, len(found)))
        finally:
            dataset.finalize()
    info = {
        "source": [p.name for p in paths],
        "robot": robot_id,
        "slave": slave,
        "policies": policies,
        "corrections": [[c.episode.index, c.master] for c in corrections],
    }
    (root / "meta" / "arena.json").write_text(json.dumps(info, indent=2), encoding="utf-8")
    return ExportReport(root, repo_id, fps, written, sorted(shapes), notes, policies)


def import_lerobot(
    root: Path,
    episode: int,
    out: Path,
    *,
    repo_id: str | None = None,
    robot_id: str = "dataset-arm",
    robot_type: str = "so-arm100",
) -> int:
    """Turn one episode of a LeRobot dataset into a recording `arena replay` plays: its
    actions become accepted commands at their timestamps, its states the joint states of a
    slave `dataset`. Returns the number of frames."""
    from arena.recording.mcap_file import write_recording
    from arena.robot.model import load_robot_model

    lerobot = _lerobot()
    meta_path = root / "meta" / "info.json"
    if not meta_path.is_file():
        raise ArenaError(
            ErrorCode.INVALID_RECORDING, f"{root} is not a LeRobot dataset (no meta/info.json)."
        )
    repo_id = repo_id or f"local/{root.name}"
    try:
        dataset = lerobot.LeRobotDataset(
            repo_id, root=root, episodes=[episode], video_backend="pyav"
        )
    except (IndexError, KeyError, ValueError) as exc:
        raise ArenaError(
            ErrorCode.INVALID_VALUE, f"Cannot read episode {episode} of {root}: {exc}"
        ) from None
    table = dataset.hf_dataset.with_format(None)
    rows = [row for row in table if int(row["episode_index"]) == episode]
    if not rows:
        raise ArenaError(ErrorCode.INVALID_VALUE, f"{root} has no episode {episode} (--episode).")
    model = load_robot_model(robot_type)
    names = feature_names(model)
    action_names = list(dataset.meta.features["action"]["names"] or names)
    state_names = list((dataset.meta.features.get("observation.state") or {}).get("names") or [])
    if sorted(action_names) != sorted(names):
        raise ArenaError(
            ErrorCode.INVALID_VALUE,
            f"The dataset's actions are {action_names}; a {robot_type} needs {names}.",
        )
    specs = {name: joint for name, joint in zip(names, model.joints, strict=True)}
    tasks = dataset.meta.tasks
    task_of = {
        int(index): str(task) for task, index in zip(tasks.index, tasks["task_index"], strict=True)
    }
    recording = Recording(out)
    recording.metadata["arena"] = {
        "server": "arena",
        "source": f"lerobot:{root}",
        "episode": str(episode),
    }
    recording.metadata[f"robot/{robot_id}"] = {
        "robot_type": robot_type,
        "name": f"{root.name} episode {episode}",
        "urdf": model.urdf_path.read_text(encoding="utf-8"),
    }
    base = time.time_ns()
    task = task_of.get(int(rows[0]["task_index"]), DEFAULT_TASK)

    def add(kind: str, at: float, data: dict[str, Any]) -> None:
        recording.messages.append(
            RecordedMessage(
                f"/robots/{robot_id}/{kind}", robot_id, kind, base + round(at * 1e9), data
            )
        )

    add("episode", 0.0, {"t": 0.0, "change": "start", "index": 0, "task": task, "started": 0.0})
    for row in rows:
        at = float(row["timestamp"])
        joints = [
            {"name": specs[name].name, "value": from_dataset(specs[name], float(value))}
            for name, value in zip(action_names, row["action"], strict=True)
        ]
        add(
            "command",
            at,
            {
                "t": at,
                "source": "dataset",
                "joints": joints,
                "duration": None,
                "label": "dataset",
                "accepted": True,
                "code": None,
                "message": "",
                "clamped": [],
            },
        )
        if state_names and "observation.state" in row:
            state = {
                specs[name].name: from_dataset(specs[name], float(value))
                for name, value in zip(state_names, row["observation.state"], strict=True)
                if name in specs
            }
            add("joint_states", at, {"t": at, "slave_id": "dataset", "joints": state})
    end = float(rows[-1]["timestamp"])
    add("episode", end, {"t": end, "change": "stop", "index": 0, "task": task, "started": 0.0})
    write_recording(recording, out)
    return len(rows)
