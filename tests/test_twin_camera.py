"""The physics twin as a camera: a real server renders its physics slave's scene, the frames are
recorded, exported as a LeRobot dataset and read back by LeRobot; a robot with no physics slave
is refused one.

The twin and the capture thread run on real time; the test waits for events (frames counted,
the arm at its target), never for a fixed time.
"""

from __future__ import annotations

import json
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from trio_websocket import open_websocket_url

from arena import cli
from arena.recording import images
from arena.recording.mcap_file import read_recording
from arena.sensors import capture
from tests.conftest import RunningServer, eventually, missing, need
from tests.test_cameras import jpeg_rgb

lerobot_dataset = need("lerobot.datasets.lerobot_dataset", "lerobot")
need("mujoco", "physics")

BASE = "/api/robots/twin-arm"
FPS = 10  # the dataset's; the camera renders at its default 5


@pytest.fixture(autouse=True)
def _renders() -> None:
    """Skip where MuJoCo cannot render at all (no OSMesa, a system package)."""
    from arena.drivers.physics import ArmSimulation, View
    from arena.robot.model import load_robot_model

    probe = ArmSimulation(load_robot_model("so-arm100"))
    try:
        probe.render(View(), 8, 8)
    except Exception as exc:  # no GL to render with
        missing(f"MuJoCo cannot render headless ({exc}): apt-get install libosmesa6")
    finally:
        probe.close()


def pose(rotation: float) -> str:
    """A command turning the base to `rotation` degrees, the rest at the wire zero."""
    joints = [{"name": "Rotation", "value": rotation}, {"name": "Pitch", "value": 0.0}]
    return json.dumps({"type": "command", "data": {"joints": joints}})


async def test_a_twin_camera_is_recorded_and_exported_with_the_arm_moving_in_it(
    start_server: Callable[..., Awaitable[RunningServer]],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    server = await start_server()
    async with server.client() as http:
        await http.post("/api/robots", json={"id": "twin-arm", "robot_type": "so-arm100"})
        slave = await http.post(f"{BASE}/slaves", json={"type": "physics-slave"})
        assert slave.status_code == 201, slave.text
        made = await http.post(f"{BASE}/cameras", json={"name": "front", "source": "twin"})
        assert made.status_code == 201, made.text
        camera: dict[str, Any] = made.json()
        assert (camera["source"], camera["fps"], camera["width"], camera["height"]) == (
            "twin",
            5,
            96,
            96,
        )
        live = server.app.cameras.get("twin-arm", "front")
        robot = server.app.manager.get("twin-arm")

        def at(rotation: float) -> bool:
            real = robot.snapshot().joint("Rotation").real_value
            return real is not None and abs(real - rotation) < 1.0

        async def frames_after(count: int) -> None:
            seen = live.frames
            await eventually(lambda: live.frames >= seen + count, what="twin frames")

        url = server.ws_url + "/ws/master/twin-arm?acks=false&joint_states=false"
        async with open_websocket_url(url) as master:
            await master.send_message(pose(-30.0))
            await eventually(lambda: at(-30.0), what="the arm at -30")
            await frames_after(2)  # (a frame may have been rendered while it turned)
            started = await http.post(f"{BASE}/episodes/start", json={"task": "turn"})
            assert started.status_code == 201
            await frames_after(3)
            await master.send_message(pose(30.0))
            await eventually(lambda: at(30.0), what="the arm at +30")
            await frames_after(3)
            assert (await http.post(f"{BASE}/episodes/stop")).status_code == 200
        name = (await http.post("/api/recordings/current/stop")).json()["stopped"]
        assert live.dropped == 0 and live.failures == 0
        # the twin detached: the camera says so (and retries), as an unplugged one does
        assert (await http.delete(f"{BASE}/slaves/{slave.json()['id']}")).status_code == 200
        await eventually(lambda: live.error is not None, what="the camera's failure")
        assert live.error in ("the physics twin stopped", "the physics twin is not running")
    path = Path(server.app.recorder.folder) / name

    # the recording holds the camera's frames: the same picture while the arm stands, another
    # once it turned
    recording = read_recording(path)
    marks = [m for m in recording.messages if m.kind == "episode"]
    start, stop = marks[0].log_time, marks[1].log_time
    frames = [
        v
        for v in recording.views
        if v.topic == "/robots/twin-arm/cameras/front" and start <= v.log_time <= stop
    ]
    # The turn's command: the frames before it show the arm standing (the last two, the twin
    # settled by then: the first in the episode may still catch it settling on a slow machine).
    turn = min(m.log_time for m in recording.messages if m.kind == "command" and m.log_time > start)
    standing = [f for f in frames if f.log_time < turn]
    assert len(standing) >= 2
    first, second, last = (
        jpeg_rgb(images.decode(f.data).data).astype(int)
        for f in (standing[-2], standing[-1], frames[-1])
    )
    assert first.shape == last.shape == (96, 96, 3)
    turned = np.abs(first - last).mean()
    assert turned > 4.0  # the base turned by 60 degrees between them
    assert np.abs(first - second).mean() < turned / 3  # where it stood

    out = tmp_path / "dataset"
    args = ["export", str(path), "--format", "lerobot", "--robot", "twin-arm", "-o", str(out)]
    assert cli.main([*args, "--fps", str(FPS), "--repo-id", "lab/twin"]) == 0, (
        capsys.readouterr().err
    )
    dataset = lerobot_dataset.LeRobotDataset("lab/twin", root=out, video_backend="pyav")
    assert dataset.meta.video_keys == ["observation.images.front"]
    assert dataset.num_episodes == 1
    every = [v for v in recording.views if v.topic == "/robots/twin-arm/cameras/front"]
    ends = (0, len(dataset) - 1)
    pictures, recorded = [], []
    for index in ends:
        item = dataset[index]
        pictures.append(
            (item["observation.images.front"].permute(1, 2, 0).numpy() * 255).astype(int)
        )
        # the frame the export sampled there: the newest at or before the row's time
        when = start + round(int(item["frame_index"]) * 1e9 / FPS)
        jpeg = [v.data for v in every if v.log_time <= when][-1]
        recorded.append(jpeg_rgb(images.decode(jpeg).data).astype(int))
    assert pictures[0].shape == (96, 96, 3)
    # the dataset's first and last images are the recorded ones (through AV1): each is much
    # nearer its own recorded frame than the other end's
    assert np.abs(recorded[0] - recorded[1]).mean() > 4.0
    for picture, own, other in ((pictures[0], *recorded), (pictures[1], *recorded[::-1])):
        assert np.abs(picture - own).mean() < np.abs(picture - other).mean() / 2


async def test_a_twin_camera_needs_a_physics_slave(
    start_server: Callable[..., Awaitable[RunningServer]],
) -> None:
    server = await start_server(demo=True)  # the demo arm's slave is a mock
    async with server.client() as http:
        for source in ("twin", "twin:demo-mock-slave"):
            refused = await http.post(
                "/api/robots/demo-arm/cameras", json={"name": "front", "source": source}
            )
            error = refused.json()["error"]
            assert (refused.status_code, error["code"]) == (409, "NO_TWIN")
            assert "attach a physics-slave first" in error["message"]
        assert (await http.get("/api/robots/demo-arm/cameras")).json() == {"cameras": []}
        # a malformed twin source is the body's fault, before any slave is looked for
        bad = await http.post("/api/robots/demo-arm/cameras", json={"name": "f", "source": "twin:"})
        assert (bad.status_code, bad.json()["error"]["code"]) == (422, "INVALID_BODY")


async def test_a_twin_camera_where_mujoco_cannot_render_is_refused(
    start_server: Callable[..., Awaitable[RunningServer]], monkeypatch: pytest.MonkeyPatch
) -> None:
    # Every backend fails to start in the capture process: MUJOCO_GL's and the headless ones.
    monkeypatch.setattr(capture, "_working_gl", None)
    monkeypatch.setattr(capture, "GL_BACKENDS", ("nogl",))
    monkeypatch.setenv("MUJOCO_GL", "nosuchgl")
    server = await start_server()
    async with server.client() as http:
        await http.post("/api/robots", json={"id": "twin-arm", "robot_type": "so-arm100"})
        assert (await http.post(f"{BASE}/slaves", json={"type": "physics-slave"})).is_success
        refused = await http.post(f"{BASE}/cameras", json={"name": "front", "source": "twin"})
        error = refused.json()["error"]
        assert (refused.status_code, error["code"]) == (422, "CAMERA_FAILED")
        message = error["message"]
        assert "nosuchgl: invalid value" in message and "nogl: invalid value" in message
        assert "libosmesa6" in message
        assert (await http.get(f"{BASE}/cameras")).json() == {"cameras": []}

        # MUJOCO_GL naming a backend this machine lacks: the next that works is found and kept
        monkeypatch.setattr(capture, "GL_BACKENDS", ("nogl", "egl", "osmesa"))
        made = await http.post(f"{BASE}/cameras", json={"name": "front", "source": "twin"})
        assert made.status_code == 201, made.text
        assert capture.gl_candidates() in (["egl"], ["osmesa"])
        camera = server.app.cameras.get("twin-arm", "front")
        await eventually(lambda: camera.frames > 0, what="a frame rendered")
