"""JSON Schemas of every wire message and recorded record, written to specs/schemas/ (a test
keeps them in sync). It sits above `protocol` and `recording`, whose types it describes."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import msgspec

from arena.protocol import messages as wire
from arena.protocol import rest
from arena.protocol.stopped import StoppedNotice
from arena.recording.records import RECORD_TYPES

#: File name (without .json) -> the type it describes.
SCHEMA_TYPES: dict[str, Any] = {
    "master-message": wire.MasterMessage,
    "slave-message": wire.SlaveMessage,
    "ack": wire.AckMessage,
    "group-ack": wire.GroupAckMessage,
    "error": wire.ErrorMessage,
    "joint-states": wire.JointStatesOut,
    "state": wire.StateMessage,
    "fault": wire.FaultMessage,
    "execute-command": wire.ExecuteCommandMessage,
    "slave-notice": wire.EStopNotice | wire.ResetNotice | wire.HoldNotice | wire.StopNotice,
    "detached": wire.DetachedMessage,
    "released": wire.ReleasedMessage,
    "stopped": StoppedNotice,
    "missed": wire.MissedMessage,
    "member-left": wire.MemberLeftMessage,
    "heartbeat": wire.HeartbeatMessage,
    "rest-create-robot": rest.CreateRobotBody,
    "rest-joints": rest.JointsBody,
    "rest-leader-joints": rest.LeaderJointsBody,
    "rest-slave": rest.SlaveBody,
    "rest-master": rest.MasterBody,
    "rest-reason": rest.ReasonBody,
    "rest-replay": rest.ReplayBody,
    "rest-workspace": rest.WorkspaceBody,
    "rest-calibration": rest.CalibrationBody,
    "rest-camera": rest.CameraBody,
    "rest-episode": rest.EpisodeBody,
    "rest-group": rest.GroupBody,
}


def _recording_types() -> dict[str, Any]:
    return {
        f"record-{kind.replace('_', '-')}": kind_type for kind, kind_type in RECORD_TYPES.items()
    }


def schemas() -> dict[str, str]:
    """File name -> JSON text of its schema."""
    return {
        f"{name}.json": json.dumps(msgspec.json.schema(kind), indent=2, sort_keys=True) + "\n"
        for name, kind in {**SCHEMA_TYPES, **_recording_types()}.items()
    }


def write_schemas(folder: Path) -> list[Path]:
    """Write every schema into `folder`; returns the paths written."""
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for name, text in schemas().items():
        path = folder / name
        path.write_text(text, encoding="utf-8")
        written.append(path)
    return written
