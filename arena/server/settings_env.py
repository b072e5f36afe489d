"""Server settings from the environment, as containers and unit files pass them.

Each setting of `ServerConfig` is `ARENA_` and its name in capitals (`ARENA_PORT=9000`,
`ARENA_RECORD=false`, `ARENA_ALLOWED_ORIGINS=https://a,https://b`); `ARENA_CONFIG` names the
TOML file and `ARENA_API_KEY_FILE` a file of keys. A value that does not parse is refused naming
its variable; an `ARENA_` variable that is no setting is a warning naming it (a typo must not
pass silently, but it must not stop a service from starting either).
"""

from __future__ import annotations

import logging
import types
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from arena.protocol.errors import ArenaError, ErrorCode

log = logging.getLogger(__name__)

PREFIX = "ARENA_"
CONFIG_ENV = "ARENA_CONFIG"
API_KEY_FILE_ENV = "ARENA_API_KEY_FILE"
#: `ARENA_` variables that are read elsewhere and are no server setting.
OTHER_VARIABLES = frozenset(
    {
        CONFIG_ENV,
        API_KEY_FILE_ENV,
        "ARENA_ROBOT_TYPES",  # arena/robot/model.py: more robot types
        "ARENA_SHARED",  # the tests' reference data
        "ARENA_FLOOR_PYTHON",  # `arena bench versus`
        "ARENA_FLOOR_SCRIPT",
    }
)
_TRUE = frozenset({"1", "true", "yes", "on"})
_FALSE = frozenset({"0", "false", "no", "off"})


def settings_from_env(fields: Mapping[str, Any], environ: Mapping[str, str]) -> dict[str, Any]:
    """The settings `environ` gives, parsed by the types in `fields` (setting name -> type, as
    `typing.get_type_hints` gives them). Warns about each unknown `ARENA_` variable."""
    found: dict[str, Any] = {}
    for variable in sorted(environ):
        if not variable.startswith(PREFIX) or variable in OTHER_VARIABLES:
            continue
        name = variable[len(PREFIX) :].lower()
        if name not in fields:
            log.warning("%s is no Arena setting: ignored (is it misspelt?)", variable)
            continue
        found[name] = parse_value(variable, environ[variable], fields[name])
    return found


def parse_value(variable: str, text: str, kind: Any) -> Any:
    """`text` as a value of type `kind`; `ArenaError(INVALID_CONFIG)` naming `variable`."""
    optional = typing.get_origin(kind) in (typing.Union, types.UnionType)
    if optional:
        if text.strip() == "":
            return None
        kind = next(arg for arg in typing.get_args(kind) if arg is not type(None))
    text = text.strip()
    if typing.get_origin(kind) is tuple:
        return tuple(item.strip() for item in text.split(",") if item.strip())
    if kind is bool:
        if text.lower() in _TRUE:
            return True
        if text.lower() in _FALSE:
            return False
        raise _bad(variable, text, "true or false")
    if kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            raise _bad(variable, text, "an integer" if kind is int else "a number") from None
    return text


def _bad(variable: str, text: str, wanted: str) -> ArenaError:
    return ArenaError(ErrorCode.INVALID_CONFIG, f"{variable}={text!r}: expected {wanted}.")


def read_key_file(path: str) -> tuple[str, ...]:
    """API keys from a file, one a line (blank lines and `#` comments skipped), so that keys
    never show in a process listing; an unreadable or empty file is refused."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ArenaError(
            ErrorCode.INVALID_CONFIG, f"Cannot read the API key file {path}: {exc}"
        ) from exc
    keys = tuple(
        line.strip() for line in text.splitlines() if line.strip() and not line.startswith("#")
    )
    if not keys:
        raise ArenaError(ErrorCode.INVALID_CONFIG, f"The API key file {path} holds no key.")
    return keys
