"""The OpenAPI document, built from the same structs that validate requests, and `/docs`."""

from __future__ import annotations

import typing
from typing import Any

import msgspec

import arena
from arena.protocol import messages as wire
from arena.protocol.rest import (
    CalibrationBody,
    CameraBody,
    ComplianceBody,
    CreateRobotBody,
    EpisodeBody,
    GroupBody,
    HandBackBody,
    InterventionBody,
    JointsBody,
    LeaderJointsBody,
    MasterBody,
    MockSlaveBody,
    MoveBody,
    PhysicsSlaveBody,
    PolicyMasterBody,
    ReasonBody,
    RemoteServerBody,
    ReplayBody,
    ReplayMasterBody,
    ScriptMasterBody,
    SequenceMasterBody,
    SlaveBody,
    TeleopBody,
    UsbMasterBody,
    UsbSlaveBody,
    WebSocketSlaveBody,
    WorkspaceBody,
)
from arena.server.access import ROLE_FOR
from arena.server.base import ArenaApp

#: (method, path, summary, request body type or None). A test checks it covers every route.
ROUTES: list[tuple[str, str, str, Any]] = [
    ("GET", "/", "Server status and metrics", None),
    ("GET", "/api/robots", "List all robots", None),
    ("POST", "/api/robots", "Create a robot", CreateRobotBody),
    ("GET", "/api/robots/{robot_id}", "Get a robot's details", None),
    ("GET", "/api/robots/{robot_id}/status", "Get a robot's connection status", None),
    ("DELETE", "/api/robots/{robot_id}", "Delete a robot (its drivers stop)", None),
    ("GET", "/api/sequences", "List the demo sequences", None),
    (
        "POST",
        "/api/robots/{robot_id}/play-sequence/{sequence_id}",
        "Play a demo sequence (takes the robot over)",
        None,
    ),
    ("POST", "/api/robots/{robot_id}/stop-sequence", "Stop the playing sequence", None),
    ("POST", "/api/robots/{robot_id}/estop", "Emergency-stop a robot", ReasonBody),
    ("POST", "/api/robots/{robot_id}/reset", "Leave the e-stop (moves nothing)", None),
    ("POST", "/api/estop", "Emergency-stop every robot", ReasonBody),
    ("GET", "/api/robots/{robot_id}/joints", "Joint values, virtual and real", None),
    ("PUT", "/api/robots/{robot_id}/joints", "Manual control (refused while mastered)", JointsBody),
    ("GET", "/api/robots/{robot_id}/pose", "The hand's pose, measured and commanded", None),
    ("PUT", "/api/robots/{robot_id}/pose", "Move the hand to a pose (solved)", wire.PoseData),
    (
        "POST",
        "/api/robots/{robot_id}/move",
        "Move to a joint or pose goal, straight or along a planned path",
        MoveBody,
    ),
    ("GET", "/api/robots/{robot_id}/teleop", "Teleoperation's box and dead-man time", None),
    ("PUT", "/api/robots/{robot_id}/teleop", "Change teleoperation's box, dead-man", TeleopBody),
    ("GET", "/api/robots/{robot_id}/workspace", "The collision guard's workspace", None),
    (
        "PUT",
        "/api/robots/{robot_id}/workspace",
        "Change the workspace (floor, margin, keep-out boxes, policy)",
        WorkspaceBody,
    ),
    ("POST", "/api/robots/{robot_id}/slaves", "Attach a slave driver", SlaveBody),
    ("DELETE", "/api/robots/{robot_id}/slaves/{slave_id}", "Detach a slave", None),
    ("POST", "/api/robots/{robot_id}/master", "Attach a master driver", MasterBody),
    ("DELETE", "/api/robots/{robot_id}/master", "Detach the master", None),
    ("POST", "/api/robots/{robot_id}/master/pause", "Pause the master (the robot holds)", None),
    ("POST", "/api/robots/{robot_id}/master/resume", "Resume the paused master", None),
    (
        "POST",
        "/api/robots/{robot_id}/intervention",
        "Intervene: pause the master, another drives",
        InterventionBody,
    ),
    (
        "DELETE",
        "/api/robots/{robot_id}/intervention",
        "End the intervention (the master resumes)",
        HandBackBody,
    ),
    ("GET", "/api/robots/{robot_id}/leader", "The robot's leader arm; the simulated ones", None),
    (
        "PUT",
        "/api/robots/{robot_id}/leader/joints",
        "Move the robot's simulated leader arm (its usb-master then drives)",
        LeaderJointsBody,
    ),
    (
        "POST",
        "/api/robots/{robot_id}/compliance",
        "Hand guiding: lower joints' torque, record their motion",
        ComplianceBody,
    ),
    ("DELETE", "/api/robots/{robot_id}/compliance", "End hand guiding: hold where it is", None),
    ("GET", "/api/recordings", "List recordings and the recorder's state", None),
    ("POST", "/api/recordings", "Start recording", None),
    ("POST", "/api/recordings/{name}/stop", "Stop recording (name or 'current')", None),
    ("GET", "/api/recordings/{name}", "Summary of a recording", None),
    ("GET", "/api/recordings/{name}/file", "Download a recording (MCAP)", None),
    ("GET", "/api/recordings/{name}/joints", "A robot's joints over a recording, for plots", None),
    ("POST", "/api/robots/{robot_id}/replay", "Replay a recording onto a robot", ReplayBody),
    ("GET", "/api/robots/{robot_id}/policies", "The policies the robot's tenant may run", None),
    ("GET", "/api/robots/{robot_id}/calibration", "Calibration of a hardware slave", None),
    (
        "POST",
        "/api/robots/{robot_id}/calibration/start",
        "Start calibrating: torque off, pose the arm like the twin",
        CalibrationBody,
    ),
    (
        "POST",
        "/api/robots/{robot_id}/calibration/capture",
        "Capture the rest pose (offsets); range capture starts",
        CalibrationBody,
    ),
    (
        "POST",
        "/api/robots/{robot_id}/calibration/finish",
        "Store the calibration; torque back on where the arm is",
        CalibrationBody,
    ),
    (
        "POST",
        "/api/robots/{robot_id}/calibration/cancel",
        "Abandon the calibration in progress",
        CalibrationBody,
    ),
    ("GET", "/api/robots/{robot_id}/cameras", "A robot's cameras and their counters", None),
    ("POST", "/api/robots/{robot_id}/cameras", "Attach a camera", CameraBody),
    ("GET", "/api/robots/{robot_id}/cameras/{name}", "One camera", None),
    ("DELETE", "/api/robots/{robot_id}/cameras/{name}", "Detach a camera", None),
    ("GET", "/api/robots/{robot_id}/cameras/{name}/frame", "The newest frame (JPEG)", None),
    (
        "GET",
        "/api/robots/{robot_id}/cameras/{name}/stream",
        "Live MJPEG stream (multipart/x-mixed-replace)",
        None,
    ),
    ("GET", "/api/robots/{robot_id}/episodes", "The running and last episode, counts", None),
    (
        "POST",
        "/api/robots/{robot_id}/episodes/start",
        "Start a data-collection episode with its task",
        EpisodeBody,
    ),
    ("POST", "/api/robots/{robot_id}/episodes/stop", "End the episode and keep it", None),
    (
        "POST",
        "/api/robots/{robot_id}/episodes/discard",
        "End the episode without keeping it (or take back the last)",
        None,
    ),
    (
        "POST",
        "/api/robots/{robot_id}/highlight",
        "Save the last seconds a policy's highlight strategy keeps as an episode",
        None,
    ),
    ("GET", "/api/fleet/nodes", "The nodes of this server's fleet (--node)", None),
    ("GET", "/api/fleet/robots", "Every robot of every node, with its node and state", None),
    ("POST", "/api/fleet/estop", "E-stop every robot of every node; each node's ack", ReasonBody),
    ("GET", "/api/config", "The running setup as a configuration file (TOML)", None),
    ("POST", "/api/config/reload", "Apply the configuration file's changes", None),
    ("GET", "/api/groups", "List robot groups and their members' states", None),
    ("POST", "/api/groups", "Create a group one master can drive", GroupBody),
    ("GET", "/api/groups/{group_id}", "Get a group", None),
    ("DELETE", "/api/groups/{group_id}", "Delete a group (its robots stay)", None),
    ("POST", "/api/groups/{group_id}/estop", "Emergency-stop every member", ReasonBody),
    ("POST", "/api/groups/{group_id}/reset", "Clear every member's e-stop", None),
    ("GET", "/api/robot-types", "List robot types with their joints", None),
    ("GET", "/api/robot-types/{robot_type}", "Get a robot type", None),
    ("GET", "/api/robot-types/{robot_type}/urdf", "The robot type's URDF", None),
    ("GET", "/api/robot-types/{robot_type}/files/{name}", "A mesh the URDF names", None),
    ("GET", "/ui", "The web dashboard (redirects to /ui/)", None),
    ("GET", "/ui/", "The web dashboard", None),
    ("GET", "/ui/{name}", "A file of the web dashboard", None),
    ("GET", "/metrics", "Prometheus metrics", None),
    ("GET", "/healthz", "Liveness: the process answers", None),
    ("GET", "/readyz", "Readiness: listening, recording, every slave connected", None),
    ("GET", "/openapi.json", "This document", None),
    ("GET", "/docs", "Interactive API documentation", None),
]

#: Answers other than 200 OK on success (a test holds them to what each route returns).
SUCCESS: dict[tuple[str, str], int] = {
    ("POST", "/api/robots"): 201,
    ("POST", "/api/robots/{robot_id}/slaves"): 201,
    ("POST", "/api/robots/{robot_id}/master"): 201,
    ("POST", "/api/robots/{robot_id}/intervention"): 201,
    ("POST", "/api/robots/{robot_id}/compliance"): 201,
    ("POST", "/api/recordings"): 201,
    ("POST", "/api/robots/{robot_id}/replay"): 201,
    ("POST", "/api/robots/{robot_id}/cameras"): 201,
    ("POST", "/api/robots/{robot_id}/episodes/start"): 201,
    ("POST", "/api/robots/{robot_id}/highlight"): 201,
    ("POST", "/api/groups"): 201,
    ("GET", "/ui"): 302,
    # Asked on a reused connection; as a connection's first request the listener serves it
    # itself, 200 with the stream.
    ("GET", "/api/robots/{robot_id}/cameras/{name}/stream"): 307,
}

#: What `/docs` fills in for each request body (of a union: for each of its types). A test
#: sends each to its route and checks that the route's validation accepts it.
EXAMPLES: dict[type, dict[str, Any]] = {
    CreateRobotBody: {"robot_type": "so-arm100", "name": "My Robot", "id": "my-robot"},
    ReasonBody: {"reason": "operator pressed stop"},
    InterventionBody: {"master": {"type": "mock-sequence", "sequences": ["gentle-wave"]}},
    HandBackBody: {"resume": False},
    JointsBody: {
        "joints": [
            {"name": "Rotation", "value": 45},
            {"name": "Pitch", "value": -30, "speed": 100},
        ],
        "duration": 1000,
    },
    LeaderJointsBody: {"joints": [{"name": "Rotation", "value": 30}], "duration": 500},
    WorkspaceBody: {
        "floor": 0.0,
        "margin": 0.005,
        "policy": "refuse",
        "keep_out": [{"name": "camera", "min": [0.3, 0.3, 0.0], "max": [0.4, 0.4, 0.2]}],
    },
    MockSlaveBody: {"type": "mock-slave", "simulateLatency": 50, "responseDelay": 20},
    UsbSlaveBody: {"type": "usb-slave", "port": "/dev/ttyUSB0", "estop": "hold", "rate": 250},
    PhysicsSlaveBody: {"type": "physics-slave", "estop": "hold"},
    WebSocketSlaveBody: {
        "type": "websocket-slave",
        "url": "ws://robot-proxy:8080",
        "robotId": "remote-arm-1",
    },
    SequenceMasterBody: {"type": "mock-sequence", "sequences": ["gentle-wave"], "loop": True},
    ReplayMasterBody: {"type": "replay", "recording": "session.mcap", "speed": 2.0},
    UsbMasterBody: {"type": "usb-master", "port": "/dev/ttyUSB1", "deadband": 0.5},
    ComplianceBody: {"joints": ["shoulder_pan", "shoulder_lift"], "torque": 20},
    PolicyMasterBody: {
        "type": "policy",
        "path": "act_cube",
        "task": "pick up the cube",
        "fps": 30,
    },
    ScriptMasterBody: {"type": "script", "path": "pick_and_place.py"},
    RemoteServerBody: {
        "type": "remote-server",
        "url": "ws://localhost:8080",
        "robotId": "my-robot",
    },
    ReplayBody: {"recording": "session.mcap", "source_robot": "demo-arm", "speed": 1.0},
    CalibrationBody: {"slave": "slave-1"},
    CameraBody: {"name": "wrist", "source": "test-pattern", "fps": 15, "width": 320, "height": 240},
    EpisodeBody: {"task": "pick up the red cube"},
    GroupBody: {"id": "pair", "members": ["demo-arm"], "stopTogether": True},
    TeleopBody: {"box": {"min": [-0.3, -0.4, 0.02], "max": [0.3, 0.0, 0.4]}, "deadman": 200},
    wire.PoseData: {"position": [0.0, -0.25, 0.2], "gripper": 50, "duration": 1000},
    MoveBody: {"pose": {"position": [0.1, -0.2, 0.15]}, "plan": True, "budget": 1000},
}


def examples(body: Any) -> dict[str, dict[str, Any]]:
    """The examples of a request body type, by name (a union's: by each member's `type`)."""
    members = typing.get_args(body) or (body,)
    return {
        str(member.__struct_config__.tag or "example"): {"value": EXAMPLES[member]}
        for member in members
    }


#: WebSocket message types, documented as schemas (OpenAPI has no WebSocket operations).
WEBSOCKET_TYPES: list[Any] = [
    wire.MasterMessage,
    wire.SlaveMessage,
    wire.AckMessage,
    wire.JointStatesOut,
    wire.StateMessage,
    wire.ExecuteCommandMessage,
    wire.DetachedMessage,
    wire.MissedMessage,
    wire.MemberLeftMessage,
]

_STATUS_TEXT = {
    200: "OK",
    201: "Created",
    302: "Found: go to /ui/",
    307: "Ask again on a new connection",
}

_ERROR_SCHEMA = {
    "type": "object",
    "properties": {
        "error": {
            "type": "object",
            "properties": {"code": {"type": "string"}, "message": {"type": "string"}},
        }
    },
}


def document(app: ArenaApp | None = None) -> dict[str, Any]:
    """The OpenAPI 3.1 document."""
    bodies = [body for *_, body in ROUTES if body is not None]
    schemas, components = msgspec.json.schema_components(
        [*bodies, *WEBSOCKET_TYPES], ref_template="#/components/schemas/{name}"
    )
    body_schema = dict(zip(map(id, bodies), schemas, strict=False))
    paths: dict[str, dict[str, Any]] = {}
    for method, path, summary, body in ROUTES:
        operation: dict[str, Any] = {
            "summary": summary,
            "responses": {
                str(SUCCESS.get((method, path), 200)): {
                    "description": _STATUS_TEXT[SUCCESS.get((method, path), 200)]
                },
                "default": {
                    "description": "Error",
                    "content": {
                        "application/json": {"schema": {"$ref": "#/components/schemas/Error"}}
                    },
                },
            },
        }
        if (method, path) in ROLE_FOR:  # the least role that may call it (api.md, "Users")
            operation["x-arena-role"] = str(ROLE_FOR[(method, path)])
        parameters = [
            {"name": part[1:-1], "in": "path", "required": True, "schema": {"type": "string"}}
            for part in path.split("/")
            if part.startswith("{")
        ]
        if parameters:
            operation["parameters"] = parameters
        if body is not None:
            operation["requestBody"] = {
                "required": body is not ReasonBody,
                "content": {
                    "application/json": {
                        "schema": body_schema[id(body)],
                        "examples": examples(body),
                    }
                },
            }
        paths.setdefault(path, {})[method.lower()] = operation
    components["Error"] = _ERROR_SCHEMA
    return {
        "openapi": "3.1.0",
        "info": {
            "title": "Arena",
            "version": arena.__version__,
            "description": "Robot control: one master per robot, many slaves, e-stop. "
            "WebSockets: /ws/master/{robot_id}, /ws/slave/{robot_id}, "
            "/ws/robots/{robot_id}/state (message schemas below).",
        },
        "paths": paths,
        "components": {
            "schemas": components,
            "securitySchemes": {
                "apiKey": {
                    "type": "http",
                    "scheme": "bearer",
                    "description": "An API key, or a JSON Web Token (its role in x-arena-role).",
                }
            },
        },
        "security": [{"apiKey": []}],
    }


#: A self-contained page (no CDN): lists the operations from /openapi.json and lets you try them.
DOCS_PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>Arena API</title>
<meta name="viewport" content="width=device-width, initial-scale=1">
<style>
body{font-family:system-ui,sans-serif;margin:1rem auto;max-width:60rem;padding:0 1rem}
.op{border:1px solid #ccc;border-radius:6px;margin:.5rem 0;padding:.5rem}
.m{display:inline-block;min-width:4.5rem;font-weight:bold}
textarea{width:100%;height:5rem;font-family:monospace}
pre{background:#f5f5f5;padding:.5rem;overflow:auto;max-height:20rem}
</style></head><body>
<h1>Arena API</h1>
<p>API key (if the server needs one): <input id="key" size="30"></p>
<div id="ops">Loading /openapi.json ...</div>
<script>
async function main() {
  const doc = await (await fetch('/openapi.json')).json();
  const ops = document.getElementById('ops'); ops.textContent = '';
  for (const [path, methods] of Object.entries(doc.paths)) {
    for (const [method, op] of Object.entries(methods)) {
      const box = document.createElement('div'); box.className = 'op';
      const head = document.createElement('div');
      head.innerHTML = '<span class="m"></span> <code></code> <span></span>';
      head.children[0].textContent = method.toUpperCase();
      head.children[1].textContent = path; head.children[2].textContent = op.summary;
      box.appendChild(head);
      const params = (op.parameters || []).map(p => {
        const input = document.createElement('input'); input.placeholder = p.name;
        box.appendChild(input); return [p.name, input];
      });
      let body = null;
      if (op.requestBody) { body = document.createElement('textarea');
        const shown = Object.values(op.requestBody.content['application/json'].examples || {});
        body.value = shown.length ? JSON.stringify(shown[0].value, null, 1) : '{}';
        box.appendChild(body); }
      const button = document.createElement('button'); button.textContent = 'Try it';
      const out = document.createElement('pre'); out.hidden = true;
      button.onclick = async () => {
        let url = path; for (const [name, input] of params)
          url = url.replace('{' + name + '}', encodeURIComponent(input.value));
        const headers = {'Content-Type': 'application/json'};
        const key = document.getElementById('key').value;
        if (key) headers['Authorization'] = 'Bearer ' + key;
        const response = await fetch(url, {method: method.toUpperCase(), headers,
          body: body ? body.value : undefined});
        out.hidden = false;
        out.textContent = response.status + ' ' + await response.text();
      };
      box.appendChild(button); box.appendChild(out); ops.appendChild(box);
    }
  }
}
main();
</script></body></html>
"""
