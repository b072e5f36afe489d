"""The physics slave: the arm simulated by MuJoCo, with gravity, its table and servo-like joints.

MuJoCo compiles the robot type's own URDF (masses, inertias and meshes included); Arena adds
what a URDF cannot say: the table under the base (the workspace's floor), collisions between
the links' meshes (convex hulls) and with the table, and a position actuator per joint shaped
after the STS3215: a proportional gain that saturates at the servo's stall torque, damping,
the gearbox's reflected inertia (armature) and friction. So the simulated joints lag behind
their targets, sag under load and fall with their torque off, as the real ones do.

`ArmSimulation` is the model and its stepping, with no threads and no trio. `PhysicsSlave`
drives it as a slave, paced by trio's clock, `report_interval` of steps at a go: in real time
(the default) each batch runs in a worker thread, off the event loop; with `realtime` off it
runs inside trio. Either way a test on MockClock runs it faster than real time.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import trio

from arena.protocol.errors import ErrorCode, Severity
from arena.robot.events import NoticeKind, SlaveNotice, SlaveTarget
from arena.robot.links import SlaveLink
from arena.robot.model import RobotModel

#: The STS3215 at 12 V: stall torque (N m) and the gain that reaches it 0.3 rad off target.
STALL_TORQUE = 2.94
POSITION_GAIN = STALL_TORQUE / 0.3
#: Reflected rotor inertia (kg m^2) and dry friction (N m) of the geared servo, and damping.
ARMATURE = 0.01
FRICTION = 0.05
DAMPING = 0.3
#: How far (seconds) the real-time simulation may fall behind the clock before it lets the
#: rest go rather than catch up.
MAX_LAG = 0.25


@dataclass(frozen=True, slots=True)
class View:
    """A camera looking at the scene: at `lookat` (metres, the base's frame) from `distance`
    metres, turned `azimuth` degrees about the vertical and `elevation` degrees up or down."""

    lookat: tuple[float, float, float] = (0.0, -0.2, 0.12)
    distance: float = 0.8
    azimuth: float = 60.0
    elevation: float = -30.0


@dataclass(frozen=True, slots=True)
class Pose:
    """A copy of where the simulated arm is (MuJoCo's `qpos`) and where the target marker is
    (`mocap_pos`): what a camera needs to draw the scene, read off the stepping thread."""

    qpos: Any
    mocap_pos: Any


@dataclass(frozen=True, slots=True)
class PhysicsSettings:
    """How the simulation runs."""

    rate: float = 500.0  # steps a second (the MuJoCo timestep is 1 / rate)
    estop: str = "hold"  # "hold": keep the pose; "torque-off": the servos go limp
    realtime: bool = True
    report_interval: float = 0.01  # seconds between joint-state reports
    #: No clock of its own: whoever owns the slave moves it on (`PhysicsSlave.step_to`), as a
    #: Gymnasium environment steps its world.
    stepped: bool = False
    #: A red sphere (no mass, touching nothing) that marks a task's target in the scene
    #: (`ArmSimulation.set_target`).
    target_marker: bool = False


class ArmSimulation:
    """A robot type's arm in MuJoCo: targets in, joint values and contacts out (wire units)."""

    def __init__(self, model: RobotModel, settings: PhysicsSettings | None = None) -> None:
        if "MUJOCO_GL" not in os.environ and "DISPLAY" not in os.environ:
            os.environ["MUJOCO_GL"] = "osmesa"  # rendering with no screen (`render`)
        import mujoco  # only the physics slave needs it

        self.settings = settings or PhysicsSettings()
        self.robot = model
        self._mj = mujoco
        spec = _spec(model, self.settings)
        self.model = spec.compile()
        self.data = mujoco.MjData(self.model)
        # Meshes that touch in the rest pose touch by design (the shoulder's hull on the
        # table, say): those pairs never collide.
        self._place_at_rest(model)
        for first, second in self._touching():
            spec.add_exclude(bodyname1=_spec_body(first), bodyname2=_spec_body(second))
        self.model = spec.compile()
        self.data = mujoco.MjData(self.model)
        # Each joint's spec (its units: `JointSpec.to_urdf`, `from_urdf`) and qpos address.
        self._joints = [
            (joint, self.model.joint(joint.urdf_name).qposadr[0]) for joint in model.joints
        ]
        self._actuators = [self.model.actuator(joint.name).id for joint in model.joints]
        self._gains = self.model.actuator_gainprm.copy(), self.model.actuator_biasprm.copy()
        self.torque = True
        self.steps = 0
        self._renderers: dict[tuple[int, int], Any] = {}
        self.set_pose(dict.fromkeys(model.joint_names, 0.0))

    def render(self, view: View, width: int, height: int) -> Any:
        """The scene as `view` sees it now: an (height, width, 3) uint8 RGB array. MuJoCo's
        renderer, headless through OSMesa where there is no display (Debian's `libosmesa6`;
        `MUJOCO_GL` chooses another). Call it from the thread that steps the simulation."""
        renderer = self._renderers.get((width, height))
        if renderer is None:
            renderer = self._mj.Renderer(self.model, height=height, width=width)
            self._renderers[(width, height)] = renderer
        camera = self._mj.MjvCamera()
        camera.lookat[:] = view.lookat
        camera.distance, camera.azimuth, camera.elevation = (
            view.distance,
            view.azimuth,
            view.elevation,
        )
        renderer.update_scene(self.data, camera=camera)
        return renderer.render()

    def close(self) -> None:
        """Free the renderers' GL contexts."""
        for renderer in self._renderers.values():
            renderer.close()
        self._renderers.clear()

    def set_target(self, position: tuple[float, float, float]) -> None:
        """Put the target marker at `position` (metres, the base's frame); needs
        `target_marker` in the settings."""
        if not self.settings.target_marker:
            raise ValueError("this simulation has no target marker (PhysicsSettings.target_marker)")
        self.data.mocap_pos[0] = position
        self._mj.mj_forward(self.model, self.data)

    def target(self) -> tuple[float, float, float] | None:
        """Where the target marker is (None without one)."""
        if not self.settings.target_marker:
            return None
        x, y, z = (float(v) for v in self.data.mocap_pos[0])
        return x, y, z

    def _place_at_rest(self, model: RobotModel) -> None:
        for joint in model.joints:
            self.data.qpos[self.model.joint(joint.urdf_name).qposadr[0]] = joint.neutral
        self._mj.mj_forward(self.model, self.data)

    def set_pose(self, degrees: Mapping[str, float]) -> None:
        """Put the arm at rest at `degrees` (targets there too)."""
        for joint, address in self._joints:
            self.data.qpos[address] = joint.to_urdf(degrees.get(joint.name, 0.0))
        self.data.qvel[:] = 0.0
        self._mj.mj_forward(self.model, self.data)
        self.set_targets(degrees)

    def restart(self, degrees: Mapping[str, float]) -> None:
        """Start afresh at rest at `degrees`: MuJoCo's whole state is reset (its solver's warm
        start too), so what follows depends on nothing before. The target marker stays."""
        marker = self.data.mocap_pos.copy()
        self._mj.mj_resetData(self.model, self.data)
        self.data.mocap_pos[:] = marker
        self.set_pose(degrees)

    def set_targets(self, degrees: Mapping[str, float]) -> None:
        """Where each actuator pulls its joint (wire degrees; joints not named keep theirs)."""
        for (joint, _), actuator in zip(self._joints, self._actuators, strict=True):
            if joint.name in degrees:
                self.data.ctrl[actuator] = joint.to_urdf(degrees[joint.name])

    def hold(self) -> None:
        """Targets where the joints are now."""
        for (_, address), actuator in zip(self._joints, self._actuators, strict=True):
            self.data.ctrl[actuator] = self.data.qpos[address]

    def set_torque(self, on: bool) -> None:
        """Servos on (position control) or limp (no actuator force at all)."""
        gains, biases = self._gains
        self.model.actuator_gainprm[:] = gains if on else 0.0
        self.model.actuator_biasprm[:] = biases if on else 0.0
        self.torque = on

    def step(self, count: int = 1) -> None:
        """Advance `count` timesteps."""
        for _ in range(count):
            self._mj.mj_step(self.model, self.data)
        self.steps += count

    def positions(self) -> dict[str, float]:
        """Every joint's value in wire degrees."""
        return {
            joint.name: joint.from_urdf(self.data.qpos[address]) for joint, address in self._joints
        }

    def contacts(self) -> set[tuple[str, str]]:
        """Pairs of bodies touching now ("table" for the floor)."""
        return self._touching()

    def _touching(self) -> set[tuple[str, str]]:
        found = set()
        for contact in self.data.contact[: self.data.ncon]:
            names = sorted((self._body(contact.geom1), self._body(contact.geom2)))
            found.add((names[0], names[1]))
        return found

    def _body(self, geom: int) -> str:
        body = self.model.geom_bodyid[geom]
        return "table" if body == 0 else str(self.model.body(body).name)


def _spec_body(name: str) -> str:
    return "world" if name == "table" else name


def _spec(model: RobotModel, settings: PhysicsSettings) -> Any:
    """The URDF as a MuJoCo spec, with the table, collisions and servo-like actuators."""
    import mujoco

    text = model.urdf_path.read_text(encoding="utf-8")
    # Keep the visual meshes (a URDF's only geometry here) and their folders.
    extension = '<mujoco><compiler discardvisual="false" strippath="false"/></mujoco>'
    head, tag, rest = text.partition("<robot")
    close = rest.index(">") + 1
    spec = mujoco.MjSpec.from_string(head + tag + rest[:close] + extension + rest[close:])
    spec.meshdir = str(model.urdf_path.parent)
    spec.option.timestep = 1.0 / settings.rate
    # Light from above for a camera (`render`); it has no part in the physics.
    spec.worldbody.add_light(pos=[0.0, 0.0, 1.5], dir=[0.0, 0.0, -1.0], diffuse=[0.8, 0.8, 0.8])
    for geom in spec.geoms:
        geom.contype = geom.conaffinity = 1
    if model.workspace.floor is not None:
        spec.worldbody.add_geom(
            name="table",
            type=mujoco.mjtGeom.mjGEOM_PLANE,
            size=[2.0, 2.0, 0.01],
            pos=[0.0, 0.0, model.workspace.floor],
        )
    if settings.target_marker:
        # A mocap body: placed by hand, moved by nothing; it collides with nothing either.
        marker = spec.worldbody.add_body(name="target", mocap=True, pos=[0.0, 0.0, -1.0])
        marker.add_geom(
            type=mujoco.mjtGeom.mjGEOM_SPHERE,
            size=[0.015, 0.0, 0.0],
            rgba=[1.0, 0.0, 0.0, 1.0],
            contype=0,
            conaffinity=0,
        )
    for joint in model.joints:
        found = spec.joint(joint.urdf_name)
        found.armature = ARMATURE
        found.frictionloss = FRICTION
        found.damping = [DAMPING, 0.0, 0.0]  # MuJoCo 4: damping, then its polynomial terms
        actuator = spec.add_actuator(
            name=joint.name, target=joint.urdf_name, trntype=mujoco.mjtTrn.mjTRN_JOINT
        )
        actuator.set_to_position(kp=POSITION_GAIN, kv=0.0)
        actuator.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
        actuator.forcerange = [-STALL_TORQUE, STALL_TORQUE]
    return spec


class PhysicsSlave:
    """A slave that is the simulated arm: it follows targets through the physics, reports the
    joint values it reaches, and a fault for each new contact (with the table or itself)."""

    kind = "physics-slave"
    measures = False  # a twin: it goes where it is told, from where it was told

    def __init__(self, settings: PhysicsSettings | None = None) -> None:
        self.settings = settings or PhysicsSettings()
        self.simulation: ArmSimulation | None = None
        self.contacts_reported: list[tuple[str, str]] = []
        self._pending: list[SlaveTarget | SlaveNotice] = []
        #: Guards `_pending` and `_pose` (taken briefly by the stepping thread and cameras).
        self._lock = threading.Lock()
        self._pose: Pose | None = None  # the newest pose, for cameras (`pose`)
        self.running = False  # between the simulation's build and the slave's end
        self._link: SlaveLink | None = None
        self._started = 0.0  # trio time of the simulation's step 0 (stepped mode)
        #: Set once the simulation is built and has reported its first joint values.
        self.ready = trio.Event()

    async def run(self, link: SlaveLink) -> None:
        """Simulate until detached."""
        model = link.robot.model
        if self.settings.realtime:  # compiling takes ~0.25 s: not on the event loop
            simulation = await trio.to_thread.run_sync(ArmSimulation, model, self.settings)
        else:  # on a virtual clock a thread's time would not count: build it here
            simulation = ArmSimulation(model, self.settings)
        self.simulation = simulation
        self._link, self._started = link, trio.current_time()
        self._publish(simulation)
        self.running = True
        try:
            await link.report_joint_states(simulation.positions())
            self.ready.set()
            async with trio.open_nursery() as nursery:
                if self.settings.stepped:
                    pass  # moved on by its owner (`step_to`)
                elif self.settings.realtime:
                    nursery.start_soon(self._in_real_time, link, simulation)
                else:
                    nursery.start_soon(self._in_trio_time, link, simulation)
                async for message in link.messages():
                    with self._lock:
                        self._pending.append(message)
                nursery.cancel_scope.cancel()
        finally:
            self.running = False

    def _publish(self, simulation: ArmSimulation) -> None:
        """Keep a copy of the pose just reached for the cameras (in the stepping thread)."""
        pose = Pose(simulation.data.qpos.copy(), simulation.data.mocap_pos.copy())
        with self._lock:
            self._pose = pose

    def pose(self) -> Pose | None:
        """The newest pose the simulation reached (None before it is built); any thread."""
        with self._lock:
            return self._pose

    def _apply_pending(self, simulation: ArmSimulation) -> None:
        with self._lock:
            pending, self._pending = self._pending, []
        for message in pending:
            if isinstance(message, SlaveTarget):
                if simulation.torque:
                    simulation.set_targets(message.joints)
            elif message.kind is NoticeKind.ESTOP:
                if self.settings.estop == "torque-off":
                    simulation.set_torque(False)
                else:
                    simulation.hold()
            elif message.kind is NoticeKind.RESET:
                simulation.hold()
                simulation.set_torque(True)
            elif message.kind in (NoticeKind.HOLD, NoticeKind.SHUTDOWN):
                simulation.hold()

    async def _report(
        self, link: SlaveLink, positions: dict[str, float], touching: set[tuple[str, str]]
    ) -> None:
        await link.report_joint_states(positions)
        for pair in sorted(touching - set(self.contacts_reported)):
            self.contacts_reported.append(pair)
            await link.report_fault(
                ErrorCode.CONTACT, f"{pair[0]} touches {pair[1]}", Severity.WARNING, None
            )

    async def step_to(self, when: float) -> None:
        """Stepped mode: apply the targets and notices that came, simulate up to trio time
        `when` (steps counted from the last `place`), then report. Its owner calls it every
        `report_interval` or so, after letting everything due at `when` happen."""
        simulation, link = self.simulation, self._link
        if simulation is None or link is None:
            raise RuntimeError("step_to before the simulation is ready")
        self._apply_pending(simulation)
        count = round((when - self._started) * self.settings.rate) - simulation.steps
        if count > 0:
            simulation.step(count)
        self._publish(simulation)
        await self._report(link, simulation.positions(), simulation.contacts())

    async def place(self, degrees: Mapping[str, float]) -> None:
        """Stepped mode: start the simulation afresh at rest at `degrees` (a twin's reset, where
        a real arm would be brought there by its commands) and report."""
        simulation, link = self.simulation, self._link
        if simulation is None or link is None:
            raise RuntimeError("place before the simulation is ready")
        self._apply_pending(simulation)
        simulation.restart(degrees)
        # Steps count from here: the same step grid for every start, wherever the clock is.
        self._started, simulation.steps = trio.current_time(), 0
        self._publish(simulation)
        await self._report(link, simulation.positions(), simulation.contacts())

    async def _in_trio_time(self, link: SlaveLink, simulation: ArmSimulation) -> None:
        interval = self.settings.report_interval
        steps = max(1, round(interval * self.settings.rate))
        while True:
            await trio.sleep(interval)
            self._apply_pending(simulation)
            simulation.step(steps)
            self._publish(simulation)
            await self._report(link, simulation.positions(), simulation.contacts())

    async def _in_real_time(self, link: SlaveLink, simulation: ArmSimulation) -> None:
        """Paced by trio's clock: every `report_interval`, that interval's steps run in a
        worker thread (off the event loop), then the report. When it falls behind (a slow
        step, a busy loop) it catches up, so the simulated time keeps to the clock's; more
        than `MAX_LAG` behind, it lets the rest go. On MockClock it runs as it does for real."""
        interval = self.settings.report_interval
        steps = max(1, round(interval * self.settings.rate))
        due = trio.current_time()
        while True:
            due = max(due + interval, trio.current_time() - MAX_LAG)
            await trio.sleep_until(due)
            positions, touching = await trio.to_thread.run_sync(self._steps, simulation, steps)
            await self._report(link, positions, touching)

    def _steps(
        self, simulation: ArmSimulation, count: int
    ) -> tuple[dict[str, float], set[tuple[str, str]]]:
        """In the worker thread: `count` steps, the targets and notices that came meanwhile
        applied before each; the joint values and contacts after them."""
        for _ in range(count):
            self._apply_pending(simulation)
            simulation.step()
        self._publish(simulation)
        return simulation.positions(), simulation.contacts()
