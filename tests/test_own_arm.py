"""Your own arm from files alone: a robot type written into a folder outside the package (URDF,
a mesh, robot.toml with its servo map, limits and rates), found through `ARENA_ROBOT_TYPES`,
driven through a real server on its simulated bus, as specs/robot-model.md tells."""

from __future__ import annotations

from collections.abc import Awaitable, Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from arena.servo.sim_pty import PtySimBus
from tests.conftest import RunningServer, write_stl
from tests.hardware import eventually, running_sim

pytest.importorskip("dynamixel_sdk")
from arena.dynamixel import registers as reg
from arena.dynamixel.sim import SimBus

StartServer = Callable[..., Awaitable[RunningServer]]
XL330 = reg.MODELS["xl330-m288"]

URDF = """<?xml version="1.0"?>
<robot name="pointer">
  <link name="base"><visual><geometry><mesh filename="meshes/block.stl"/></geometry></visual>
  </link>
  <link name="turret"/>
  <link name="boom"><visual><geometry><mesh filename="meshes/block.stl"/></geometry></visual>
  </link>
  <link name="claw"/>
  <joint name="yaw" type="revolute">
    <parent link="base"/><child link="turret"/><origin xyz="0 0 0.05"/><axis xyz="0 0 1"/>
    <limit lower="-1.5" upper="1.5" effort="1" velocity="4"/>
  </joint>
  <joint name="boom_joint" type="revolute">
    <parent link="turret"/><child link="boom"/><origin xyz="0 0 0.03"/><axis xyz="0 1 0"/>
    <limit lower="-1.0" upper="1.0" effort="1" velocity="4"/>
  </joint>
  <joint name="claw_joint" type="revolute">
    <parent link="boom"/><child link="claw"/><origin xyz="0.1 0 0"/><axis xyz="0 0 1"/>
    <limit lower="0" upper="0.8" effort="1" velocity="4"/>
  </joint>
</robot>
"""

ROBOT_TOML = """
description = "A three-joint pointer on Dynamixel servos 21-23"
urdf = "pointer.urdf"

[bus]
family = "dynamixel"
baud_rate = 1000000

[safety]
command_rate = 50.0
command_burst = 5
control_rate = 100.0

[[joints]]
name = "yaw"
servo_id = 21
servo_model = "xl330-m288"
lower = -60.0
upper = 60.0
max_velocity = 90.0

[[joints]]
name = "lift"
urdf_joint = "boom_joint"
servo_id = 22
servo_model = "xl330-m288"
aliases = ["boom"]

[[joints]]
name = "claw"
urdf_joint = "claw_joint"
servo_id = 23
servo_model = "xl330-m288"
unit = "percent"
"""


def write_block_stl(path: Path, size: float = 0.04) -> None:
    """A cube of side `size` as a binary STL (12 triangles)."""
    h = size / 2
    corners = [(x, y, z) for x in (-h, h) for y in (-h, h) for z in (-h, h)]
    faces = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    triangles = [(a, b, c, a, c, d) for a, b, c, d in faces]
    write_stl(path, [corners[index] for corner_indices in triangles for index in corner_indices])


@pytest.fixture
def types_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    folder = tmp_path / "my-types" / "pointer"
    (folder / "meshes").mkdir(parents=True)
    (folder / "pointer.urdf").write_text(URDF)
    (folder / "robot.toml").write_text(ROBOT_TOML)
    write_block_stl(folder / "meshes" / "block.stl")
    monkeypatch.setenv("ARENA_ROBOT_TYPES", str(tmp_path / "my-types"))
    return folder


@pytest.fixture
def sim(tmp_path: Path) -> Iterator[PtySimBus]:
    yield from running_sim(tmp_path, bus=SimBus({21: XL330, 22: XL330, 23: XL330}))


def goals(sim: PtySimBus) -> dict[int, int]:
    with sim.paused() as bus:
        return {sid: servo.peek(reg.GOAL_POSITION) for sid, servo in bus.servos.items()}


async def test_an_arm_added_from_files_is_driven_on_its_bus(
    start_server: StartServer, sim: PtySimBus, types_dir: Path, tmp_path: Path
) -> None:
    server = await start_server(calibration_dir=str(tmp_path / "cal"))
    async with server.client() as http:
        types = (await http.get("/api/robot-types")).json()
        assert "pointer" in str(types)
        made = await http.post("/api/robots", json={"id": "p", "robot_type": "pointer"})
        assert made.status_code == 201, made.text
        joints = {j["name"]: j for j in (await http.get("/api/robots/p/joints")).json()}
        assert list(joints) == ["yaw", "lift", "claw"]
        attached = await http.post(
            "/api/robots/p/slaves", json={"type": "usb-slave", "port": str(sim.link)}
        )
        assert attached.status_code == 201, attached.text

        async def joined() -> bool:
            robot = (await http.get("/api/robots/p")).json()
            return bool(robot["slaves"]) and not any(s.get("joining") for s in robot["slaves"])

        await eventually(joined, what="the pointer joined")
        # `boom` is an alias; yaw asks beyond its soft limit (60) and is clamped to it.
        move = {"joints": [{"name": "boom", "value": 30.0}, {"name": "yaw", "value": 80.0}]}
        answer = await http.put("/api/robots/p/joints", json=move)
        assert answer.status_code == 200, answer.text
        # Uncalibrated: step 2048 is 0 degrees; 4096 steps a turn.
        wanted = {21: 2048 + round(60 * 4096 / 360), 22: 2048 + round(30 * 4096 / 360)}

        def there() -> bool:
            now = goals(sim)
            return all(now[sid] == step for sid, step in wanted.items())

        await eventually(there, what="the goals of yaw 60 and lift 30 on servos 21 and 22")
        stopped = await http.post("/api/robots/p/estop", json={"reason": "test"})
        assert stopped.status_code == 200
        assert (await http.get("/api/robots/p/status")).json()["state"] == "estopped"

        def held() -> bool:
            with sim.paused() as bus:
                return all(
                    s.peek(reg.GOAL_POSITION) == s.peek(reg.PRESENT_POSITION)
                    for s in bus.servos.values()
                )

        await eventually(held, what="every servo held where it is")


def test_a_type_whose_servo_model_its_family_lacks_is_refused(types_dir: Path) -> None:
    from arena.drivers.servo_arm import family_of, servo_models
    from arena.protocol.errors import ArenaError
    from arena.robot.model import load_robot_model

    toml = types_dir / "robot.toml"
    text = toml.read_text().replace('"xl330-m288"\nlower', '"sts3215"\nlower')
    toml.write_text(text)
    model = load_robot_model("pointer")
    with pytest.raises(ArenaError, match="sts3215"):
        servo_models(model, family_of(model))


async def test_the_bus_opens_at_the_type_s_baud_rate_unless_the_body_names_one(
    start_server: StartServer,
    sim: PtySimBus,
    types_dir: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from arena.drivers import servo_arm

    toml = types_dir / "robot.toml"
    toml.write_text(toml.read_text().replace("baud_rate = 1000000", "baud_rate = 57600"))
    opened: list[tuple[str, int]] = []
    simulated = servo_arm.open_family_bus  # (the simulator's paced bus, see tests/hardware.py)

    def recording(family: Any, port: str, baud: int) -> Any:
        opened.append((family.name, baud))
        return simulated(family, port, baud)

    monkeypatch.setattr(servo_arm, "open_family_bus", recording)
    server = await start_server(calibration_dir=str(tmp_path / "cal"))
    async with server.client() as http:
        await http.post("/api/robots", json={"id": "p", "robot_type": "pointer"})
        for body, baud in (({}, 57600), ({"baudRate": 115200}, 115200)):
            slave = {"type": "usb-slave", "port": str(sim.link), **body}
            attached = await http.post("/api/robots/p/slaves", json=slave)
            assert attached.status_code == 201, attached.text
            assert opened[-1] == ("dynamixel", baud)
            detached = await http.delete(f"/api/robots/p/slaves/{attached.json()['id']}")
            assert detached.status_code in (200, 204), detached.text
