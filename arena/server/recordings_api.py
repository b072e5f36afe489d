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
from arena.protocol.rest import DEFAULT_TENANT, ReplayBody, ReplayMasterBody
from arena.recording.analysis import joint_series, summarize, thin
from arena.recording.mcap_file import SUFFIX, read_recording, tenant_in_name
from arena.recording.recorder import Recorder, check_name, existing_recording
from arena.server.access import Contents, reads_recordings
from arena.server.base import ArenaApp, read_body, record_audit_now
from arena.server.drivers import attach_rest_master, make_master
from arena.server.identity import Principal

blueprint = Blueprint("recordings", __name__)
T = TypeVar("T")


def _app() -> ArenaApp:
    return current_app  # type: ignore[return-value]


#: What each finished file read so far holds, by path, with the size and time it had.
_CONTENTS: dict[Path, tuple[tuple[int, int], Contents]] = {}
_MOST_REMEMBERED = 4096


def contents_of(recorder: Recorder, path: Path) -> Contents:
    """Whose a file is and the robots it holds: its `arena` metadata's `tenant` (else the
    tenant its name says; None in a default-named file of an older version with robots,
    which may mix tenants) and its `robot/ID` metadata (a file
    being written: the robots of its tenant the recorder follows; None when that cannot be
    told). Reads the file's summary, or the whole file when it has none: call it off the
    loop."""
    # (`path` may be resolved, the recorder's relative to where the server started)
    writing = {p.resolve(): whose for p, whose in recorder.current_files.items()}
    tenant = writing.get(path.resolve())
    if tenant is not None:
        followed = recorder.writer.robots.items()
        return Contents(tenant, frozenset(r for r, m in followed if m.get("tenant") == tenant))
    try:
        stat = path.stat()
    except OSError:
        return Contents(None, None)
    key = (stat.st_size, stat.st_mtime_ns)
    known = _CONTENTS.get(path)
    if known is not None and known[0] == key:
        return known[1]
    found: set[str] = set()
    tenant = None
    try:
        with path.open("rb") as stream:
            for metadata in make_reader(stream).iter_metadata():
                if metadata.name.startswith("robot/"):
                    found.add(metadata.name[len("robot/") :])
                elif metadata.name == "arena":
                    tenant = metadata.metadata.get("tenant")
    except Exception:  # cut short or not MCAP: what it holds is not known
        found, tenant = set(), None
    if len(_CONTENTS) >= _MOST_REMEMBERED:
        _CONTENTS.clear()
    named = tenant_in_name(path.name)
    if tenant is None and named is not None and (named != DEFAULT_TENANT or not found):
        # Not said yet (a new file, its metadata not flushed) or not at all: a file named
        # for a tenant is that tenant's, whatever it holds so far; a default-named one
        # with no robots yet is the default tenant's.
        tenant = named
    contents = Contents(tenant, frozenset(found) or None)
    _CONTENTS[path] = (key, contents)
    return contents


def recorder_status(app: ArenaApp, principal: Principal) -> dict[str, Any]:
    """What the recorder is doing, as the caller may see it: the counts and error of the
    caller's tenant's files, and `file` the one being written that the caller may read."""
    recorder = app.recorder
    theirs = _files_seen(app, principal, recorder.current_files)
    return {**recorder.status(principal.tenant), "file": theirs[0] if theirs else None}


def _files_seen(app: ArenaApp, principal: Principal, files: dict[Path, str]) -> list[str]:
    """The names of those of `files` (being written) the caller may read, sorted."""
    recorder = app.recorder
    return sorted(
        path.name
        for path in files
        if app.access.sees_recording(principal, contents_of(recorder, path))
    )


async def readable_recording(
    app: ArenaApp, principal: Principal, name: str, field: str = ""
) -> Path:
    """The recording `name`, if the caller may read it (its tenant's, every robot in scope);
    else UNKNOWN_RECORDING, worded as for a file that does not exist (and naming the body's
    `field` it came from, if any)."""
    try:
        path = existing_recording(app.recorder.folder, name)
        contents = await off_the_loop(contents_of, app.recorder, path)
        if not app.access.sees_recording(principal, contents):
            raise ArenaError(ErrorCode.UNKNOWN_RECORDING, f"No recording called {name!r}.")
    except ArenaError as error:
        if not field:
            raise
        raise ArenaError(error.code, f"`{field}`: {error.message}") from None
    return path


def _whole_server(principal: Principal) -> None:
    """Recording is on or off for every tenant at once: only the whole server's admin (a
    caller of the default tenant who sees all of it) switches it, never a tenant's, which
    would stop the others' recording too."""
    if not reads_recordings(principal):
        raise ArenaError(
            ErrorCode.FORBIDDEN,
            "Recording is switched on or off for the whole server, every tenant at once: "
            f"only an admin of the default tenant with every robot in scope may, and "
            f"{principal.name!r} is confined to a tenant or some robots.",
        )


async def _existing(name: str) -> Path:
    return await readable_recording(_app(), g.principal, name)


@blueprint.get("/api/recordings")
async def list_recordings() -> dict[str, Any]:
    """Every recording in the folder, newest first, and what the recorder is doing."""
    app = _app()
    recorder = app.recorder
    files = sorted(recorder.folder.glob(f"*{SUFFIX}"), key=lambda p: p.name, reverse=True)
    contents = await off_the_loop(lambda: [contents_of(recorder, path) for path in files])
    principal: Principal = g.principal
    files = [
        p for p, c in zip(files, contents, strict=True) if app.access.sees_recording(principal, c)
    ]
    writing = {path.resolve() for path in recorder.current_files}
    return {
        "recorder": recorder_status(app, principal),
        "recordings": [
            {"name": p.name, "bytes": p.stat().st_size, "active": p.resolve() in writing}
            for p in files
        ],
    }


@blueprint.post("/api/recordings")
async def start_recording() -> tuple[dict[str, Any], int]:
    """Start recording (a new file begins with the next message)."""
    _whole_server(g.principal)
    app = _app()
    await app.recorder.start()
    return recorder_status(app, g.principal), 201


@blueprint.post("/api/recordings/<name>/stop")
async def stop_recording(name: str) -> dict[str, Any]:
    """Stop recording (every tenant's: one switch for the server); `name` must be a file
    being written that the caller may read (or `current`). `stopped` names the file the
    stop finished that the caller may read: the caller is of the default tenant (only the
    whole server's admin stops), which writes one file at a time."""
    principal: Principal = g.principal
    _whole_server(principal)
    app = _app()
    recorder = app.recorder
    if name != "current":
        check_name(recorder.folder, name)
        writing = await off_the_loop(_files_seen, app, principal, recorder.current_files)
        if name not in writing:
            raise ArenaError(ErrorCode.UNKNOWN_RECORDING, f"{name!r} is not being recorded.")
    record_audit_now()  # (into the files this stop closes: after it, nowhere)
    closed = await recorder.stop()
    stopped = await off_the_loop(_files_seen, app, principal, closed)
    return {**recorder_status(app, principal), "stopped": stopped[0] if stopped else None}


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
