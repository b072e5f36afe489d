"""The physics twin as a camera: the MuJoCo scene of a robot's physics slave, drawn with the arm
at the pose the twin has reached.

It renders in a capture process of its own (`arena.sensors.capture`), never in the server: a
frame costs ~130 ms of CPU at 96x96 (OSMesa rasterises the meshes), and OpenGL runs native code
that can hang holding its interpreter's lock. The server sends the compiled model once (MuJoCo's
binary MJB) and, before each frame, the pose the slave published under its lock after its last
batch of steps (`PhysicsSlave.pose`); the child draws it with its own model and `MjData`, on an
OpenGL backend the server found to work there (EGL or OSMesa, with no display).
"""

from __future__ import annotations

import tempfile
import time
from dataclasses import asdict
from typing import Any

import numpy as np

from arena.drivers.physics import PhysicsSlave, View
from arena.sensors.capture import GLUnavailable, Recipe
from arena.sensors.sources import JpegEncoder


def twin_recipe(
    slave: PhysicsSlave, width: int, height: int, fps: int, view: View | None = None
) -> Recipe:
    """How a capture process draws `slave`'s scene as `view` sees it; `OSError` when the twin
    is not running."""
    simulation = slave.simulation
    if simulation is None or not slave.running:
        raise OSError("the physics twin is not running")
    import mujoco

    model = simulation.model
    blob = np.empty(mujoco.mj_sizeModel(model), np.uint8)
    mujoco.mj_saveModel(model, None, blob)

    def pose() -> bytes:
        found = slave.pose()
        if found is None or not slave.running:
            raise OSError("the physics twin stopped")
        values = np.concatenate([found.qpos, np.ravel(found.mocap_pos)]).astype("<f8")
        return bytes(values.tobytes())

    params = {"width": width, "height": height, "fps": fps, "view": asdict(view or View())}
    return Recipe(
        "arena.drivers.twin_camera:TwinRenderer", params, blob.tobytes(), feed=pose, gl=True
    )


class TwinRenderer:
    """In the capture process: the scene of the model in `blob` at the pose last fed, as
    `width` x `height` JPEG. Raises `GLUnavailable` when OpenGL cannot start here."""

    paced = True  # renders on demand: the server keeps the rate

    def __init__(
        self, blob: bytes, width: int, height: int, fps: int, view: dict[str, Any]
    ) -> None:
        try:  # MUJOCO_GL names a backend MuJoCo loads at import
            import mujoco
        except ModuleNotFoundError:
            raise
        except Exception as exc:  # a backend's libraries missing or broken
            raise GLUnavailable(str(exc) or type(exc).__name__) from None
        self._mj = mujoco
        with tempfile.NamedTemporaryFile(suffix=".mjb") as file:
            file.write(blob)
            file.flush()
            self._model = mujoco.MjModel.from_binary_path(file.name)
        # MuJoCo renders off-screen into a buffer the model sizes: make room for this camera.
        size = self._model.vis.global_
        size.offwidth, size.offheight = max(size.offwidth, width), max(size.offheight, height)
        self._data = mujoco.MjData(self._model)
        try:
            self._renderer = mujoco.Renderer(self._model, height=height, width=width)
        except Exception as exc:  # mujoco's GL backends raise what they like
            raise GLUnavailable(str(exc) or type(exc).__name__) from None
        self._camera = mujoco.MjvCamera()
        self._camera.lookat[:] = view["lookat"]
        self._camera.distance = view["distance"]
        self._camera.azimuth, self._camera.elevation = view["azimuth"], view["elevation"]
        self._encoder = JpegEncoder(width, height, fps)
        #: When the pose last fed arrived (`perf_counter`): the frame shows the arm then.
        self.exposed: float | None = None

    def feed(self, pose: bytes) -> None:
        """Where the arm is (`qpos`, then the markers' `mocap_pos`), as little-endian doubles."""
        values = np.frombuffer(pose, "<f8")
        count = self._model.nq
        if values.size != count + 3 * self._model.nmocap:
            raise OSError(f"a pose of {values.size} numbers for a model of {count} positions")
        self._data.qpos[:] = values[:count]
        self._data.mocap_pos[:] = values[count:].reshape(-1, 3)
        self.exposed = time.perf_counter()

    def read(self) -> bytes:
        """The scene at the pose last fed, as JPEG."""
        # Only what drawing needs: where the bodies, geoms and lights are for this qpos.
        self._mj.mj_kinematics(self._model, self._data)
        self._mj.mj_camlight(self._model, self._data)
        self._renderer.update_scene(self._data, camera=self._camera)
        return self._encoder.encode_rgb(self._renderer.render())

    def close(self) -> None:
        """Free the renderer's GL context."""
        self._renderer.close()
