"""Why a REST body or a WebSocket message was refused, in a sentence that names the field.

msgspec says where (`$.data.joints[0]`) and what (an unknown field, an unknown `type`, a
value out of a list). This turns that into words a client can act on: the field at fault, the
names that are allowed there and the nearest one to what was sent. REST bodies and WebSocket
messages share it, so that both refuse an unknown field the same way: every struct they decode
is declared with `forbid_unknown_fields`, because a misspelled field that is silently dropped
(`robot_id` for `id`) does the wrong thing without a word. No I/O here.
"""

from __future__ import annotations

import difflib
import functools
import re
from typing import Any

import msgspec
from msgspec import inspect

from arena.protocol.errors import ArenaError, ErrorCode

#: msgspec's sentence: what is wrong, and where (absent: the whole).
_PLACED = re.compile(r"^(?P<detail>.*?)(?: - at `(?P<at>\$[^`]*)`)?$", re.DOTALL)
_UNKNOWN_FIELD = re.compile(r"^Object contains unknown field `(?P<name>[^`]*)`$")
_MISSING_FIELD = re.compile(r"^Object missing required field `(?P<name>[^`]*)`$")
_BAD_VALUE = re.compile(r"^Invalid (?:enum )?value (?P<value>.*)$", re.DOTALL)
_SEGMENT = re.compile(r"\.([^.\[]+)|\[(\d+|\.\.\.)\]")


def nearest(name: str, choices: list[str]) -> str | None:
    """The allowed name `name` was most likely meant to be, if one is near enough.

    The same name in another case or spelling (`baud_rate` for `baudRate`) first, then a name
    that is its last word (`robot_id` for `id`), then the one name it is a word of (`mock` for
    `mock-slave`), then the closest spelling.
    """

    def folded(text: str) -> str:
        return text.replace("_", "").replace("-", "").lower()

    for choice in choices:
        if folded(choice) == folded(name):
            return choice
    words = _words(name)
    for choice in choices:
        if len(words) > 1 and choice.lower() == words[-1]:
            return choice
    containing = [choice for choice in choices if name.lower() in _words(choice)]
    if len(containing) == 1:
        return containing[0]
    close = difflib.get_close_matches(name, choices, n=1, cutoff=0.6)
    return close[0] if close else None


def _words(name: str) -> list[str]:
    """`robot_id`, `mock-slave`, `baudRate` -> their words, in lower case."""
    return [w.lower() for w in re.split(r"[_\-]|(?<=[a-z])(?=[A-Z])", name) if w]


def refusal(
    kind: Any, raw: bytes | str, error: msgspec.ValidationError, *, what: str, code: ErrorCode
) -> ArenaError:
    """The error for `raw`, which failed to decode as `kind` with `error`.

    `what` names the whole ("body", "message"). An unknown field is UNKNOWN_FIELD; an unknown
    or missing `type` at the top of a message is UNKNOWN_MESSAGE_TYPE (when `code` is
    INVALID_MESSAGE); anything else is `code`.
    """
    placed = _PLACED.match(str(error))
    assert placed is not None  # (the pattern matches any text)
    detail, at = placed["detail"], placed["at"] or "$"
    try:
        value: Any = msgspec.json.decode(raw)
    except (msgspec.DecodeError, RecursionError):
        value = None
    if match := _UNKNOWN_FIELD.match(detail):
        sentence = _unknown_field(kind, value, at, _short(match["name"]), what)
        return ArenaError(ErrorCode.UNKNOWN_FIELD, sentence)
    missing = _MISSING_FIELD.match(detail)
    bad = _BAD_VALUE.match(detail)
    # A union's tag: `type` missing from an object, or a `type` that names no member.
    if missing:
        union_at, field, given = at, missing["name"], None
    else:
        union_at, _, field = at.rpartition(".")
        given = _short(bad["value"]) if bad else None
    tags = _tags_at(kind, value, union_at) if (missing or bad) and union_at else None
    if tags is not None and tags[0] == field:
        sentence = _tag_sentence(field, tags[1], given, _place(union_at, what))
        if union_at == "$" and code is ErrorCode.INVALID_MESSAGE:
            return ArenaError(ErrorCode.UNKNOWN_MESSAGE_TYPE, sentence)
        return ArenaError(code, sentence)
    if missing:
        return ArenaError(code, f"Missing field {field!r}{_place(at, what)}: it is required.")
    choices = _choices(_info_at(kind, value, at)) if bad else []
    if bad and choices:
        return ArenaError(
            code, f"Invalid {_name(at)}: {_short(bad['value'])} is not one of {', '.join(choices)}."
        )
    if at == "$":
        return ArenaError(code, f"Invalid {what}: {detail}.")
    return ArenaError(code, f"Invalid {_name(at)}: {detail}.")


def _unknown_field(kind: Any, value: Any, at: str, name: str, what: str) -> str:
    place = _place(at, what)
    struct = _struct_at(kind, value, at)
    if struct is None:
        return f"Unknown field {name!r}{place}."
    allowed = _field_names(struct)
    hint = nearest(name, allowed)
    guess = f": did you mean {hint!r}?" if hint else "."
    return f"Unknown field {name!r}{place}{guess} The fields are {', '.join(allowed)}."


def _tag_sentence(field: str, tags: list[str], given: str | None, place: str) -> str:
    if given is None:
        return f"Missing {field!r}{place}: it is one of {', '.join(tags)}."
    hint = nearest(given.strip("'\""), tags)
    guess = f" (did you mean {hint!r}?)" if hint else ""
    return f"Unknown {field} {given}{place}{guess}: it is one of {', '.join(tags)}."


def _short(text: str) -> str:
    """What a client sent, as an answer repeats it: a hostile one's 60 kB name is cut."""
    return text if len(text) <= 64 else f"{text[:60]}..."


def _name(at: str) -> str:
    """The field at `at` as a client writes it: `$.data.joints[0]` -> `data.joints[0]`."""
    return f"`{at[2:]}`"


def _place(at: str, what: str) -> str:
    """` in the body` for the whole, else ` in `keep_out[0]``."""
    return f" in the {what}" if at == "$" else f" in {_name(at)}"


@functools.lru_cache(maxsize=64)
def _info(kind: Any) -> inspect.Type:
    return inspect.type_info(kind)


def _unwrap(info: inspect.Type) -> inspect.Type:
    while isinstance(info, inspect.Metadata):
        info = info.type
    return info


def _options(info: inspect.Type) -> list[inspect.Type]:
    info = _unwrap(info)
    if isinstance(info, inspect.UnionType):
        return [_unwrap(t) for t in info.types if not isinstance(_unwrap(t), inspect.NoneType)]
    return [info]


def _resolve(info: inspect.Type, value: Any) -> inspect.Type:
    """The member of a union that `value` is (by its tag, or by being an object or a list)."""
    options = _options(info)
    if len(options) == 1:
        return options[0]
    structs = [t for t in options if isinstance(t, inspect.StructType)]
    if isinstance(value, dict):
        for struct in structs:
            if struct.tag_field is not None and value.get(struct.tag_field) == struct.tag:
                return struct
        objects = [t for t in options if isinstance(t, inspect.StructType | inspect.DictType)]
        if len(objects) == 1:
            return objects[0]
    if isinstance(value, list):
        lists = [t for t in options if isinstance(t, inspect.ListType | inspect.VarTupleType)]
        if len(lists) == 1:
            return lists[0]
    return _unwrap(info)


def _info_at(kind: Any, value: Any, at: str) -> inspect.Type | None:
    """The type at the path `at` of a value of `kind` (`value`: the JSON, to pick unions)."""
    info: inspect.Type = _info(kind)
    for name, index in _SEGMENT.findall(at[1:]):
        info = _resolve(info, value)
        if name:
            if not isinstance(info, inspect.StructType):
                return None
            fields = {f.encode_name: f for f in info.fields}
            if name not in fields:
                return None
            info = fields[name].type
            value = value.get(name) if isinstance(value, dict) else None
        elif isinstance(info, inspect.ListType | inspect.VarTupleType):
            info = info.item_type
            position = int(index) if index.isdigit() else -1
            ok = isinstance(value, list) and 0 <= position < len(value)
            value = value[position] if ok else None
        elif isinstance(info, inspect.DictType):
            info = info.value_type
            value = None  # msgspec does not say which key
        else:
            return None
    return info


def _struct_at(kind: Any, value: Any, at: str) -> inspect.StructType | None:
    info = _info_at(kind, value, at)
    if info is None:
        return None
    resolved = _resolve(info, _value_at(value, at))
    return resolved if isinstance(resolved, inspect.StructType) else None


def _value_at(value: Any, at: str) -> Any:
    for name, index in _SEGMENT.findall(at[1:]):
        if name and isinstance(value, dict):
            value = value.get(name)
        elif index.isdigit() and isinstance(value, list) and int(index) < len(value):
            value = value[int(index)]
        else:
            return None
    return value


def _tags_at(kind: Any, value: Any, at: str) -> tuple[str, list[str]] | None:
    """The tag field and the tags of the tagged union at `at`, if there is one."""
    info = _info_at(kind, value, at)
    if info is None:
        return None
    structs = [t for t in _options(info) if isinstance(t, inspect.StructType)]
    tagged = [t for t in structs if t.tag_field is not None and isinstance(t.tag, str)]
    if not tagged:
        return None
    return tagged[0].tag_field or "type", [str(t.tag) for t in tagged]


def _field_names(struct: inspect.StructType) -> list[str]:
    names = [f.encode_name for f in struct.fields]
    return [struct.tag_field, *names] if struct.tag_field else names


def _choices(info: inspect.Type | None) -> list[str]:
    """The values a literal or an enum allows."""
    if info is None:
        return []
    choices: list[str] = []
    for option in _options(info):
        if isinstance(option, inspect.LiteralType):
            choices += [str(v) for v in option.values]
        elif isinstance(option, inspect.EnumType):
            choices += [str(member.value) for member in option.cls]
    return choices
