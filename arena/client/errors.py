"""What a client call raises: `ArenaClientError` and its kinds."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any


class ArenaClientError(Exception):
    """An Arena server answered with an error: `code` is its machine-readable code."""

    def __init__(self, code: str, message: str, status: int | None = None) -> None:
        super().__init__(f"{code}: {message}")
        self.code = code
        self.message = message
        self.status = status


class Refused(ArenaClientError):
    """The server refused a request: a command acknowledged as `refused`, or an `error` (or
    `detached`) message in answer. `code` and `message` are the server's."""


class Disconnected(ArenaClientError):
    """The session's WebSocket is down (it is reconnecting)."""

    def __init__(self, message: str = "not connected") -> None:
        super().__init__("DISCONNECTED", message)


class ClientTimeout(ArenaClientError, TimeoutError):
    """No answer came within the call's `timeout` (code `TIMEOUT`)."""

    def __init__(self, message: str) -> None:
        super().__init__("TIMEOUT", message)


def refusal(message: Mapping[str, Any]) -> Refused:
    """The `Refused` of an error, a detach or a refused ack (a group's names each member's)."""
    data = message.get("data") or {}
    members = data.get("members")
    if not data.get("code") and isinstance(members, dict) and members:
        codes = {str(answer.get("code")) for answer in members.values()}
        text = "; ".join(f"{robot}: {answer.get('message')}" for robot, answer in members.items())
        return Refused(codes.pop() if len(codes) == 1 else "REFUSED", text)
    return Refused(str(data.get("code") or "REFUSED"), str(data.get("message") or ""))
