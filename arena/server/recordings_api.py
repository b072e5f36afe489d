"""REST for recordings: list, start, stop, summary, download, and replay onto a robot."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import msgspec
import trio
from mcap.reader import make_reader
from quart import Blueprint, current_app, g, request, send_file

from arena.protocol.errors import ArenaError, ErrorCode
from arena.protocol.rest import ReplayBody, ReplayMasterBody
from arena.recording.analysis import joint_series, summarize, thin
from arena.recording.mcap_file import SUFFIX, read_recording
from arena.recording.recorder import Recorder, check_name, existing_recording
from arena.server.access import reads_recordings
from arena.server.base import ArenaApp, read_body
from arena.server.drivers import attach_rest_master, make_master
from arena.server.identity import Principal

blueprint = Blueprint("recordings", __name__)
T = TypeVar("T")


def _app() -> ArenaApp:
    return current_app  # type: ignore[return-value]


#: Robots of each finished file read so far, by path, with the size and time they had.
_ROBOTS: dict[Path, tuple[tuple[int, int], frozenset[str] | None]] = {}
_MOST_REMEMBERED = 4096


def robots_of(recorder: Recorder, path: Path) -> frozenset[str] | None:
    """The robots a file holds (its `robot/ID` metadata; the file being written: every robot
    the recorder follows), None when that cannot be told. Reads the file's summary, or the
    whole file when it has none: call it off the loop."""
    if path == recorder.current_file:
        return frozenset(recorder.writer.robots)
    try:
        stat = path.stat()
    except OSError:
        return None
    key = (stat.st_size, stat.st_mtime_ns)
    known = _ROBOTS.get(path)
    if known is not None and known[0] == key:
        return known[1]
    found: set[str] = set()
    try:
        with path.open("rb") as stream:
            for metadata in make_reader(stream).iter_metadata():
                if metadata.name.startswith("robot/"):
                    found.add(metadata.name[len("robot/") :])
    except Exception:  # cut short or not MCAP: which robots it holds is not known
        found = set()
    if len(_ROBOTS) >= _MOST_REMEMBERED:
        _ROBOTS.clear()
    robots = frozenset(found) or None
    _ROBOTS[path] = (key, robots)
    return robots


async def readable_recording(
    app: ArenaApp, principal: Principal, name: str, field: str = ""
) -> Path:
    """The recording `name`, if the caller may read it (each of its robots is one it sees);
    else UNKNOWN_RECORDING, worded as for a file that does not exist (and naming the body's
    `field` it came from, if any)."""
    try:
        path = existing_recording(app.recorder.folder, name)
        robots = await off_the_loop(robots_of, app.recorder, path)
        if not app.access.sees_recording(principal, robots):
            raise ArenaError(ErrorCode.UNKNOWN_RECORDING, f"No recording called {name!r}.")
    except ArenaError as error:
        if not field:
            raise
        raise ArenaError(error.code, f"`{field}`: {error.message}") from None
    return path


def _whole_server(principal: Principal) -> None:
    """Recording is on or off for every tenant at once: only a caller who sees the whole
    default tenant switches it."""
    if not reads_recordings(principal):
        raise ArenaError(
            ErrorCode.FORBIDDEN,
            f"Recording is on or off for the whole server; {principal.name!r} is confined to "
            "a tenant or some robots.",
        )


async def _existing(name: str) -> Path:
    return await readable_recording(_app(), g.principal, name)


@blueprint.get("/api/recordings")
async def list_recordings() -> dict[str, Any]:
    """Every recording in the folder, newest first, and what the recorder is doing."""
    app = _app()
    recorder = app.recorder
    files = sorted(recorder.folder.glob(f"*{SUFFIX}"), key=lambda p: p.name, reverse=True)
    robots = await off_the_loop(lambda: [robots_of(recorder, path) for path in files])
    files = [
        p for p, r in zip(files, robots, strict=True) if app.access.sees_recording(g.principal, r)
    ]
    current = recorder.current_file
    return {
        "recorder": recorder.status(),
        "recordings": [
            {
                "name": p.name,
                "bytes": p.stat().st_size,
                "active": current is not None and p == current,
            }
            for p in files
        ],
    }


@blueprint.post("/api/recordings")
async def start_recording() -> tuple[dict[str, Any], int]:
    """Start recording (a new file begins with the next message)."""
    _whole_server(g.principal)
    recorder = _app().recorder
    await recorder.start()
    return recorder.status(), 201


@blueprint.post("/api/recordings/<name>/stop")
async def stop_recording(name: str) -> dict[str, Any]:
    """Stop recording; `name` must be the file being written (or `current`)."""
    _whole_server(g.principal)
    recorder = _app().recorder
    current = recorder.current_file
    if name != "current":
        path = check_name(recorder.folder, name)
        if current is None or path != current.resolve():
            raise ArenaError(ErrorCode.UNKNOWN_RECORDING, f"{name!r} is not being recorded.")
    stopped = await recorder.stop()
    return {**recorder.status(), "stopped": stopped.name if stopped else None}


#: Recordings read at once for requests: each takes memory in proportion to its file.
_LOADS = trio.CapacityLimiter(2)


async def off_the_loop(work: Callable[..., T], *args: Any) -> T:
    """Run `work` (reading and digesting a recording) in a thread, a bounded number at once,
    so that no robot waits on a large file."""
    return await trio.to_thread.run_sync(work, *args, limiter=_LOADS)


def _summary(path: Path) -> dict[str, Any]:
    return summarize(read_recording(path))


@blueprint.get("/api/recordings/<name>")
async def recording_summary(name: str) -> dict[str, Any]:
    """Robots, span, counts, gaps, e-stops, faults and tracking errors of one recording."""
    return await off_the_loop(_summary, await _existing(name))


#: Most points per joint series a plot request may ask for.
MAX_PLOT_POINTS = 5000


def _plot_points(raw: str) -> int:
    """The `points` query parameter, checked before any file is read."""
    # ASCII digits only, and short: str.isdigit() accepts "²" and int() refuses huge strings.
    if not (raw.isascii() and raw.isdigit() and len(raw) <= 6) or not (
        2 <= int(raw) <= MAX_PLOT_POINTS
    ):
        raise ArenaError(
            ErrorCode.INVALID_VALUE, f"points must be a whole number from 2 to {MAX_PLOT_POINTS}."
        )
    return int(raw)


@blueprint.get("/api/recordings/<name>/joints")
async def recording_joints(name: str) -> dict[str, Any]:
    """One robot's joints over the recording, thinned for a plot (`?robot=`, `?points=`)."""
    most = _plot_points(request.args.get("points", "300"))
    path = await _existing(name)
    return await off_the_loop(_joints, path, request.args.get("robot"), most)


def _joints(path: Path, robot: str | None, most: int) -> dict[str, Any]:
    recording = read_recording(path)
    robots = sorted({m.robot_id for m in recording.messages if m.robot_id})
    robot_id = robot or (robots[0] if robots else "")
    series = joint_series(recording, robot_id)
    return {
        "recording": path.name,
        "robot": robot_id,
        "robots": robots,
        "joints": [
            {
                "name": joint,
                "virtual": thin(series.virtual.get(joint, []), most),
                "real": thin(series.real.get(joint, []), most),
            }
            for joint in series.joints
        ],
        "estops": series.estops,
    }


@blueprint.get("/api/recordings/<name>/file")
async def download_recording(name: str) -> Any:
    """The MCAP file itself."""
    return await send_file(
        await _existing(name),
        mimetype="application/octet-stream",
        as_attachment=True,
        attachment_filename=name,
    )


@blueprint.post("/api/robots/<robot_id>/replay")
async def replay(robot_id: str) -> tuple[dict[str, Any], int]:
    """Replay a recording's commands onto `robot_id` as its master."""
    app = _app()
    robot = app.manager.get(robot_id)
    body: ReplayBody = await read_body(ReplayBody)
    await readable_recording(app, g.principal, body.recording, field="recording")
    config = ReplayMasterBody(**msgspec.structs.asdict(body))
    driver = await off_the_loop(make_master, config, app.recorder.folder)
    master_id = await attach_rest_master(robot, driver)
    return {"robot": robot_id, "master": master_id, "recording": body.recording}, 201
