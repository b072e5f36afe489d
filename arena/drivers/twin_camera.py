"""The physics twin as a camera: a frame source (`arena.sensors.sources.FrameSource`) that draws
the MuJoCo scene of a robot's physics slave, the arm at the pose the twin has reached.

It runs in the camera's capture thread, never on trio's: a frame costs ~130 ms of CPU at 96x96
(OSMesa rasterises the meshes), so cameras of the twin are small and slow (specs/physics.md).
MuJoCo's renderer is not thread-safe, and the twin steps in threads of its own, so the source
shares nothing mutable with them: it renders its own copy of the model, into its own `MjData`,
from a copy of the pose the slave publishes under its lock after each batch of steps
(`PhysicsSlave.pose`). Its GL context is made and used in the capture thread only.
"""

from __future__ import annotations

import copy
import time
from typing import Any

from arena.drivers.physics import PhysicsSlave, View
from arena.sensors.sources import JpegEncoder


class TwinCamera:
    """Frames of `slave`'s scene as `view` sees it, `width` x `height` JPEG at `fps`."""

    paced = True  # renders on demand: the capture thread keeps the rate

    def __init__(
        self, slave: PhysicsSlave, width: int, height: int, fps: int, view: View | None = None
    ) -> None:
        simulation = slave.simulation
        if simulation is None or not slave.running:
            raise OSError("the physics twin is not running")
        import mujoco

        self._mj = mujoco
        self._slave = slave
        self._model = copy.copy(simulation.model)  # our own: the stepping thread keeps its
        # MuJoCo renders off-screen into a buffer the model sizes: make room for this camera.
        size = self._model.vis.global_
        size.offwidth, size.offheight = max(size.offwidth, width), max(size.offheight, height)
        self._data = mujoco.MjData(self._model)
        self._size = width, height
        #: When the last frame's pose was read (`perf_counter`): the camera dates it so.
        self.exposed: float | None = None
        self._renderer: Any = None  # made in the capture thread, on the first frame
        view = view or View()
        self._camera = mujoco.MjvCamera()
        self._camera.lookat[:] = view.lookat
        self._camera.distance = view.distance
        self._camera.azimuth, self._camera.elevation = view.azimuth, view.elevation
        # Can MuJoCo render here at all (a GL to render with: OSMesa with no display)? Asked
        # now, so that attaching the camera fails, not its first frame. A bare GL context (a
        # few ms), freed in this thread, where it was made: a whole renderer would upload the
        # meshes too, holding Python's GIL for ~80 ms.
        try:
            import mujoco.gl_context

            context = mujoco.gl_context.GLContext(width, height)
            context.make_current()
            context.free()
        except Exception as exc:  # mujoco's GL backends raise what they like
            raise OSError(
                f"MuJoCo cannot render headless ({exc}): install Debian's libosmesa6, or set "
                "MUJOCO_GL to a backend this machine has"
            ) from None
        self._encoder = JpegEncoder(width, height, fps)

    def render(self) -> Any:
        """The scene now, an (height, width, 3) uint8 RGB array; raises `OSError` once the twin
        has stopped (detached), so the camera reports it and retries."""
        self.exposed = time.perf_counter()  # the frame shows the arm as it is now
        pose = self._slave.pose()
        if pose is None or not self._slave.running:
            raise OSError("the physics twin stopped")
        if self._renderer is None:
            width, height = self._size
            self._renderer = self._mj.Renderer(self._model, height=height, width=width)
        self._data.qpos[:] = pose.qpos
        self._data.mocap_pos[:] = pose.mocap_pos
        # Only what drawing needs: where the bodies, geoms and lights are for this qpos.
        self._mj.mj_kinematics(self._model, self._data)
        self._mj.mj_camlight(self._model, self._data)
        self._renderer.update_scene(self._data, camera=self._camera)
        return self._renderer.render()

    def read(self) -> bytes:
        """The next frame as JPEG."""
        return self._encoder.encode_rgb(self.render())

    def close(self) -> None:
        """Free the renderer's GL context (in the capture thread, which made it)."""
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
