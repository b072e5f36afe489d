"""The setup a configuration file declares: robots with their slaves, master, cameras and
workspace, and groups (specs/declared-setup.md). Read and checked whole before anything moves;
written back in the same form (`to_toml`) for `GET /api/config`.

Every part is the body its REST route takes (`arena.protocol.rest`), validated by the same
structs, so a file says nothing REST could not. A refusal is one line naming the file's line:
`tomllib` gives no positions, so `key_lines` scans the text for where each table and key is
(headers `[a.b]` and `[[a.b]]`, and `key = ...` lines, counting the arrays of tables), and an
error's path (`robots[1].slaves[0].port`) is looked up there, its nearest enclosing key when
the value itself is inline.
"""

from __future__ import annotations

import json
import math
import re
import tomllib
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

import msgspec

from arena.protocol.errors import ArenaError, ErrorCode
from arena.protocol.rest import (
    TENANT_PATTERN,
    CameraBody,
    GroupBody,
    MasterBody,
    PhysicsSlaveBody,
    PolicyMasterBody,
    ReplayMasterBody,
    RobotId,
    RobotName,
    ScriptMasterBody,
    SequenceMasterBody,
    SlaveBody,
    WorkspaceBody,
)
from arena.sensors.camera import CameraSpec

#: Path of a value in the file: keys and array indexes, as tomllib's dicts nest them.
KeyPath = tuple[str | int, ...]
#: The top-level keys that declare the setup (the others are server settings).
SETUP_KEYS = ("robots", "groups")
#: Settings never written back by `GET /api/config` (keys stay where they are kept).
SECRET_SETTINGS = ("api_keys", "viewer_keys")
#: A slave's id: as a robot's.
SlaveId = Annotated[str, msgspec.Meta(pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")]
#: Most robots and groups a file may declare (as many as a tenant may have).
MAX_DECLARED = 256


class _RobotTable(msgspec.Struct, forbid_unknown_fields=True):
    """One `[[robots]]` table (its slaves read one by one: each has an `id` besides its body)."""

    id: RobotId
    robot_type: str = "so-arm100"
    name: RobotName | None = None
    tenant: Annotated[str, msgspec.Meta(pattern=TENANT_PATTERN)] | None = None
    workspace: WorkspaceBody | None = None
    slaves: Annotated[list[dict[str, Any]], msgspec.Meta(max_length=16)] = []
    master: MasterBody | None = None
    cameras: Annotated[list[CameraBody], msgspec.Meta(max_length=16)] = []


@dataclass(frozen=True)
class DeclaredRobot:
    """A robot as the file declares it; each part the body its REST route takes."""

    robot_id: str
    robot_type: str
    name: str | None
    tenant: str | None
    workspace: WorkspaceBody | None
    slaves: dict[str, SlaveBody]
    master: MasterBody | None
    cameras: dict[str, CameraBody]

    @property
    def identity(self) -> tuple[str, str | None, str | None]:
        """What makes the robot itself (a change re-creates it and every part of it)."""
        return (self.robot_type, self.name, self.tenant)


@dataclass(frozen=True)
class Setup:
    """A file's server settings and declared setup, with where each key is in the file."""

    path: str
    settings: dict[str, Any]
    robots: dict[str, DeclaredRobot] = field(default_factory=dict)
    groups: dict[str, GroupBody] = field(default_factory=dict)
    lines: dict[KeyPath, int] = field(default_factory=dict, compare=False)

    def error(self, where: KeyPath, message: str) -> ArenaError:
        """INVALID_CONFIG: `FILE:LINE: where: message`, on one line."""
        return refusal(self.path, self.lines, where, message)


def refusal(path: str, lines: Mapping[KeyPath, int], where: KeyPath, message: str) -> ArenaError:
    """INVALID_CONFIG naming the file, the line of `where` (or of its nearest enclosing key
    found) and the path, in one line."""
    line = None
    for end in range(len(where), 0, -1):
        line = lines.get(where[:end])
        if line is not None:
            break
    place = f"{path}:{line}" if line is not None else path
    text = " ".join(message.split())
    return ArenaError(ErrorCode.INVALID_CONFIG, f"{place}: {dotted(where)}: {text}")


def dotted(where: KeyPath) -> str:
    """`robots[1].slaves[0].port` of `("robots", 1, "slaves", 0, "port")`."""
    text = ""
    for part in where:
        text += f"[{part}]" if isinstance(part, int) else (f".{part}" if text else part)
    return text or "(top)"


# -- where keys are -------------------------------------------------------------------------

_BARE = r"[A-Za-z0-9_-]+"
_QUOTED = r'"(?:[^"\\]|\\.)*"|\'[^\']*\''
_KEY = rf"(?:{_BARE}|{_QUOTED})(?:\s*\.\s*(?:{_BARE}|{_QUOTED}))*"
_ARRAY_HEADER = re.compile(rf"^\[\[\s*({_KEY})\s*\]\]")
_TABLE_HEADER = re.compile(rf"^\[\s*({_KEY})\s*\]")
_ASSIGNMENT = re.compile(rf"^({_KEY})\s*=")
_PART = re.compile(rf"{_BARE}|{_QUOTED}")


def _keys(text: str) -> list[str]:
    return [json.loads(p) if p[0] == '"' else p.strip("'") for p in _PART.findall(text)]


def key_lines(text: str) -> dict[KeyPath, int]:
    """Line (from 1) of each table header and key assignment of a TOML text, by the path
    tomllib gives its value. Lines inside multi-line strings are skipped."""
    lines: dict[KeyPath, int] = {}
    counts: dict[KeyPath, int] = {}  # each array of tables: its elements so far
    table: KeyPath = ()
    closing = ""  # the quotes that end the multi-line string we are in
    for number, raw in enumerate(text.splitlines(), 1):
        line = raw.strip()
        if closing:
            if closing in line:
                closing = ""
            continue
        if not line or line.startswith("#"):
            continue
        if found := _ARRAY_HEADER.match(line):
            array = _resolve(_keys(found.group(1)), counts)
            counts[array] = counts.get(array, 0) + 1
            table = (*array, counts[array] - 1)
            lines.setdefault(array, number)
            lines[table] = number
        elif found := _TABLE_HEADER.match(line):
            table = _resolve(_keys(found.group(1)), counts)
            lines[table] = number
        elif found := _ASSIGNMENT.match(line):
            lines[(*table, *_keys(found.group(1)))] = number
            rest = line[found.end() :]
            for quotes in ('"""', "'''"):
                if rest.lstrip().startswith(quotes) and rest.count(quotes) == 1:
                    closing = quotes
    return lines


def _resolve(names: list[str], counts: Mapping[KeyPath, int]) -> KeyPath:
    """A header's path: each array of tables it passes through at its newest element."""
    path: KeyPath = ()
    for index, name in enumerate(names):
        path = (*path, name)
        if path in counts and index < len(names) - 1:
            path = (*path, counts[path] - 1)
    return path


# -- reading ----------------------------------------------------------------------------------


def read_toml(path: str) -> tuple[str, dict[str, Any]]:
    """The text of the file and its values; INVALID_CONFIG (with tomllib's line) if it cannot
    be read."""
    try:
        text = Path(path).read_text(encoding="utf-8")
        return text, tomllib.loads(text)
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ArenaError(ErrorCode.INVALID_CONFIG, f"Cannot read {path}: {exc}") from exc


def parse_setup(path: str, text: str, data: Mapping[str, Any], settings: Iterable[str]) -> Setup:
    """The file's settings (names of `settings` only) and declared setup, every field of
    every part validated; references are checked by `check_references`."""
    lines = key_lines(text)
    known = set(settings)
    for key in data:
        if key not in known and key not in SETUP_KEYS:
            raise refusal(path, lines, (key,), f"unknown setting {key!r}")
    robots: dict[str, DeclaredRobot] = {}
    tables = _tables(path, lines, data, "robots")
    for index, table in enumerate(tables):
        robot = _robot(path, lines, table, index)
        if robot.robot_id in robots:
            raise refusal(path, lines, ("robots", index, "id"), "a robot of this id comes earlier")
        robots[robot.robot_id] = robot
    groups: dict[str, GroupBody] = {}
    for index, table in enumerate(_tables(path, lines, data, "groups")):
        group = _convert(path, lines, ("groups", index), table, GroupBody)
        if group.id in groups:
            raise refusal(path, lines, ("groups", index, "id"), "a group of this id comes earlier")
        groups[group.id] = group
    own = {key: value for key, value in data.items() if key not in SETUP_KEYS}
    return Setup(path, own, robots, groups, lines)


def _tables(
    path: str, lines: Mapping[KeyPath, int], data: Mapping[str, Any], key: str
) -> list[dict[str, Any]]:
    tables = data.get(key, [])
    if not isinstance(tables, list) or not all(isinstance(t, dict) for t in tables):
        raise refusal(path, lines, (key,), f"write each as a table of its own: [[{key}]]")
    if len(tables) > MAX_DECLARED:
        raise refusal(path, lines, (key,), f"at most {MAX_DECLARED}")
    return tables


_AT = re.compile(r" - at `\$(.*)`$")
_STEP = re.compile(r"\.(\w+)|\[(\d+)\]")
_UNKNOWN = re.compile(r"unknown field `([^`]+)`")


def _convert(
    path: str, lines: Mapping[KeyPath, int], where: KeyPath, value: object, kind: Any
) -> Any:
    """`value` as `kind` (a body struct); its errors name the file's line and the field."""
    try:
        return msgspec.convert(value, kind)
    except msgspec.ValidationError as exc:
        message = str(exc)
        at = _AT.search(message)
        inner: KeyPath = ()
        if at is not None:
            message = message[: at.start()]
            inner = tuple(n if n else int(i) for n, i in _STEP.findall(at.group(1)))
        unknown = _UNKNOWN.search(message)
        if unknown is not None:
            inner = (*inner, unknown.group(1))
        raise refusal(path, lines, (*where, *inner), message) from None


def _robot(
    path: str, lines: Mapping[KeyPath, int], table: dict[str, Any], index: int
) -> DeclaredRobot:
    where: KeyPath = ("robots", index)
    robot = _convert(path, lines, where, table, _RobotTable)
    slaves: dict[str, SlaveBody] = {}
    for number, raw in enumerate(robot.slaves):
        at = (*where, "slaves", number)
        body = dict(raw)
        slave_id = _convert(path, lines, (*at, "id"), body.pop("id", None), SlaveId | None)
        slave = _convert(path, lines, at, body, SlaveBody)
        tag = type(slave).__struct_config__.tag
        slave_id = slave_id or _free_id(str(tag), slaves)
        if slave_id in slaves:
            raise refusal(path, lines, (*at, "id"), "a slave of this id comes earlier")
        slaves[slave_id] = slave
    cameras: dict[str, CameraBody] = {}
    for number, camera in enumerate(robot.cameras):
        if camera.name in cameras:
            raise refusal(
                path, lines, (*where, "cameras", number, "name"), "a camera of this name earlier"
            )
        try:  # what no camera can be is said now, not retried for ever
            CameraSpec.of(
                camera.name, camera.source, camera.fps, camera.width, camera.height
            ).check()
        except ArenaError as error:
            raise refusal(path, lines, (*where, "cameras", number), error.message) from None
        cameras[camera.name] = camera
    return DeclaredRobot(
        robot.id,
        robot.robot_type,
        robot.name,
        robot.tenant,
        robot.workspace,
        slaves,
        robot.master,
        cameras,
    )


def _free_id(base: str, taken: Mapping[str, object]) -> str:
    """`base`, or `base-2`, `base-3`... : the first not taken (a slave given no id)."""
    number = 1
    name = base
    while name in taken:
        number += 1
        name = f"{base}-{number}"
    return name


def check_references(
    setup: Setup,
    policy_dir: str,
    recordings_dir: str,
    anywhere: bool = True,
    script_dir: str = "scripts",
) -> None:
    """Every name the setup uses names something: a robot type, a group's members, a
    twin camera's physics slave, a sequence, a policy's folder, a script, a replay's
    recording."""
    from arena.drivers.sequences import get_sequence
    from arena.recording.recorder import existing_recording
    from arena.robot.model import load_robot_model
    from arena.server.drivers import policy_folder, script_file, tenant_folder

    models = {}
    for index, robot in enumerate(setup.robots.values()):
        where: KeyPath = ("robots", index)
        try:
            models[robot.robot_id] = load_robot_model(robot.robot_type)
        except ArenaError as error:
            raise setup.error((*where, "robot_type"), error.message) from None
        for number, camera in enumerate(robot.cameras.values()):
            twin = re.fullmatch(r"twin(?::(.*))?", camera.source)
            if twin is None:
                continue
            physics = [
                sid for sid, body in robot.slaves.items() if isinstance(body, PhysicsSlaveBody)
            ]
            named = twin.group(1)
            if (named is None and len(physics) != 1) or (named and named not in physics):
                raise setup.error(
                    (*where, "cameras", number, "source"),
                    f"{camera.source!r} names no physics-slave of robot {robot.robot_id!r}"
                    + (" (it has several: say which, twin:ID)" if len(physics) > 1 else ""),
                )
        master = robot.master
        at: KeyPath = (*where, "master")
        try:
            if isinstance(master, SequenceMasterBody):
                for number, sequence in enumerate(master.sequences or ()):
                    at = (*where, "master", "sequences", number)
                    get_sequence(sequence).check_against(models[robot.robot_id])
            elif isinstance(master, PolicyMasterBody):
                at = (*where, "master", "path")
                folder = tenant_folder(Path(policy_dir), robot.tenant or "default")
                policy_folder(master.path, folder, anywhere)
            elif isinstance(master, ScriptMasterBody):
                at = (*where, "master", "path")
                script_file(master.path, tenant_folder(Path(script_dir), robot.tenant or "default"))
            elif isinstance(master, ReplayMasterBody):
                at = (*where, "master", "recording")
                existing_recording(Path(recordings_dir), master.recording)
        except ArenaError as error:
            raise setup.error(at, error.message) from None
    for index, group in enumerate(setup.groups.values()):
        if group.id in setup.robots:
            raise setup.error(("groups", index, "id"), "a group's id may not be a robot's")
        for number, member in enumerate(group.members):
            if member not in setup.robots:
                raise setup.error(
                    ("groups", index, "members", number),
                    f"no robot {member!r} is declared in this file",
                )
        if len(set(group.members)) != len(group.members):
            raise setup.error(("groups", index, "members"), "a member is named twice")
        tenants = {setup.robots[m].tenant or "default" for m in group.members}
        if len(tenants) > 1:
            raise setup.error(("groups", index, "members"), "members of one tenant only")


# -- writing ----------------------------------------------------------------------------------


def to_toml(settings: Mapping[str, Any], setup: Setup, notes: Iterable[str] = ()) -> str:
    """The setup in the file's form (`tomllib` reads it back to the same setup)."""
    out = [f"# {note}" for note in notes]
    for key, value in settings.items():
        out.append(f"{key} = {_value(value)}")
    for robot in setup.robots.values():
        out += ["", "[[robots]]", f"id = {_value(robot.robot_id)}"]
        out.append(f"robot_type = {_value(robot.robot_type)}")
        if robot.name is not None:
            out.append(f"name = {_value(robot.name)}")
        if robot.tenant is not None:
            out.append(f"tenant = {_value(robot.tenant)}")
        if robot.workspace is not None:
            out += ["", "[robots.workspace]", *_pairs(robot.workspace)]
        for slave_id, slave in robot.slaves.items():
            out += ["", "[[robots.slaves]]", f"id = {_value(slave_id)}", *_pairs(slave)]
        if robot.master is not None:
            out += ["", "[robots.master]", *_pairs(robot.master)]
        for camera in robot.cameras.values():
            out += ["", "[[robots.cameras]]", *_pairs(camera)]
    for group in setup.groups.values():
        out += ["", "[[groups]]", *_pairs(group)]
    return "\n".join(out).lstrip("\n") + "\n"


def _pairs(body: msgspec.Struct) -> list[str]:
    data = msgspec.to_builtins(body)
    if "type" in data:  # the tag first, as a person writes it
        data = {"type": data.pop("type"), **data}
    return [f"{key} = {_value(value)}" for key, value in data.items() if value is not None]


def _value(value: Any) -> str:
    """A TOML value (no null: absent values are left out)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)  # a TOML basic string: JSON's escapes are TOML's
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_value(v) for v in value) + "]"
    if isinstance(value, dict):
        inner = ", ".join(f"{_key(k)} = {_value(v)}" for k, v in value.items() if v is not None)
        return "{" + (f" {inner} " if inner else "") + "}"
    raise TypeError(f"no TOML form for {type(value).__name__}")


def _key(key: str) -> str:
    return key if re.fullmatch(_BARE, key) else json.dumps(key)
