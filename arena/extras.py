"""The optional features and the extra that brings each: a missing one says what to install.

`make run` (and `pip install arena`) installs only what serving needs; a feature whose package
is missing answers `NOT_INSTALLED` with the exact line to run, over REST (HTTP 501) as on the
command line (one line, exit 2), instead of an `ImportError` from deep inside.
"""

from __future__ import annotations

import importlib
import shlex
import sys
from dataclasses import dataclass
from types import ModuleType

from arena.protocol.errors import ArenaError, ErrorCode


@dataclass(frozen=True, slots=True)
class Extra:
    """An optional feature: the module it imports, the package and the extra that bring it."""

    module: str
    package: str
    extra: str


#: Every optional import in `arena/`, by the name its callers use.
EXTRAS = {
    "physics": Extra("mujoco", "MuJoCo", "physics"),
    "fleet": Extra("zenoh", "Zenoh (eclipse-zenoh)", "fleet"),
    "ros2": Extra("rosbags", "rosbags (with eclipse-zenoh)", "ros2"),
    "plot": Extra("matplotlib", "matplotlib", "plot"),
    "lerobot": Extra("lerobot", "LeRobot (0.4, which brings torch)", "lerobot"),
    "dynamixel": Extra("dynamixel_sdk", "the Dynamixel SDK (dynamixel-sdk)", "dynamixel"),
    "gym": Extra("gymnasium", "Gymnasium", "gym"),
    "plan": Extra("ompl", "OMPL (ompl)", "plan"),
    "mcp": Extra("mcp", "the MCP Python SDK (mcp)", "mcp"),
}


def install_line(extra: str) -> str:
    """The command that installs `extra`: `PYTHON -m pip install 'arena[NAME]'`, with the
    Python that runs Arena named (PyPI's `arena` is another project: another environment's
    pip would install that one; this one's has Arena and installs only the extra's packages)."""
    return f"{shlex.quote(sys.executable)} -m pip install 'arena[{EXTRAS[extra].extra}]'"


def require(extra: str, feature: str) -> ModuleType:
    """Import the module of `extra` and return it; when it is missing, raise
    `ArenaError(NOT_INSTALLED)` saying that `feature` needs it and how to install it."""
    wanted = EXTRAS[extra]
    try:
        return importlib.import_module(wanted.module)
    except ImportError:
        raise ArenaError(
            ErrorCode.NOT_INSTALLED,
            f"{feature} needs {wanted.package}, which is not installed: {install_line(extra)}",
        ) from None
