"""What the tests of LeRobot's arms share (the SO-101 on Feetech servos, the Koch on Dynamixel):
their joints, LeRobot's arithmetic for one step, LeRobot observing the arm through its own bus,
and a server's view of the arm (its real values, whether it joined)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from arena.servo.sim_pty import PtySimBus

NAMES = ("shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll", "gripper")
STEP = 360 / 4095  # LeRobot's degrees per step


def place_arm(sim: PtySimBus, present: Mapping[int, int]) -> None:
    """Move every servo by hand so that it reads `present` (by id)."""
    with sim.paused() as bus:
        for sid, step in present.items():
            bus.servo(sid).move_by_hand(step)


def one_step(calibration: Mapping[str, Any], name: str) -> float:
    """One servo step in the joint's units, under LeRobot's `calibration` (its
    `MotorCalibration`s by joint): a 0-100 gripper's share of its range, else degrees."""
    if name == "gripper":
        cal = calibration[name]
        return float(100 / (cal.range_max - cal.range_min))
    return STEP


def lerobot_observes(robot: Any, calibration: Mapping[str, Any], *, configure: bool) -> dict:
    """What LeRobot's own follower `robot` reads: it saves `calibration` as its file, connects,
    writes it to the servos (as its `connect()` does when the user keeps the file), configures
    them if asked (the Koch's operating modes), then observes the arm."""
    robot.calibration = dict(calibration)
    robot._save_calibration()
    robot.bus.connect()
    try:
        robot.bus.disable_torque()
        robot.bus.write_calibration(robot.calibration)
        assert robot.bus.is_calibrated  # read back from the servos' registers
        if configure:
            robot.configure()
        observed = robot.get_observation()
    finally:
        robot.bus.disconnect()
    return {name: float(observed[f"{name}.pos"]) for name in NAMES}


def assert_reads_as(
    read: Mapping[str, float | None], expected: Mapping[str, float], calibration: Mapping[str, Any]
) -> None:
    """Arena's real values within one step of what LeRobot read, the gripper in 0..100."""
    for name in NAMES:
        value = read[name]
        assert value is not None
        assert abs(value - expected[name]) <= one_step(calibration, name), (name, value)
    gripper = read["gripper"]
    assert gripper is not None and 0 <= gripper <= 100  # LeRobot's 0-100, not degrees


async def attach_arm(
    http: Any, sim: PtySimBus, robot_type: str, calibration: str, **more: Any
) -> Any:
    """Robot `arm` of `robot_type`, its usb-slave on the simulated bus with `calibration`; the
    attach's reply."""
    made = await http.post("/api/robots", json={"id": "arm", "robot_type": robot_type})
    assert made.status_code == 201, made.text
    body = {"type": "usb-slave", "port": str(sim.link), "calibration": calibration, **more}
    return await http.post("/api/robots/arm/slaves", json=body)


async def real_values(http: Any, robot: str = "arm") -> dict[str, float | None]:
    """Each joint's real value, as the server reports it."""
    joints = (await http.get(f"/api/robots/{robot}/joints")).json()
    return {j["name"]: j["real_value"] for j in joints}


async def all_read(http: Any) -> bool:
    """Whether every joint of robot `arm` has a real value."""
    return all(v is not None for v in (await real_values(http)).values())


async def joined(http: Any) -> bool:
    """Whether robot `arm` has slaves and all of them have joined."""
    robot = (await http.get("/api/robots/arm")).json()
    return bool(robot["slaves"]) and not any(s.get("joining") for s in robot["slaves"])
