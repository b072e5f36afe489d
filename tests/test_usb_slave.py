"""The USB slave: the real driver and the real scservo_sdk against a simulated bus on a pty."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import trio

from arena.feetech import registers as reg
from arena.protocol.errors import ArenaError, ErrorCode, Severity
from arena.robot.events import FaultReported, JointStatesReceived, PeerChanged
from arena.robot.manager import RobotManager
from arena.robot.model import load_robot_model
from arena.robot.motion import Command
from arena.robot.safety import Mode
from arena.servo.calibration import Calibration
from arena.servo.sim_pty import PtySimBus
from tests.conftest import eventually
from tests.hardware import (
    running_sim,
    servo_goals,
    servo_torque,
    usb_slave,
    wait_joined,
)

MODEL = load_robot_model("so-arm100")


@pytest.fixture
def sim(tmp_path: Path) -> Iterator[PtySimBus]:
    yield from running_sim(tmp_path)


def steps(degrees: float) -> int:
    """Raw steps of an uncalibrated servo for `degrees` from neutral."""
    return round(degrees * 4096 / 360) + 2048


async def test_connect_holds_the_arm_where_it_is_before_torque(
    manager: RobotManager, sim: PtySimBus
) -> None:
    with sim.paused() as bus:
        for sid, servo in bus.servos.items():
            servo.move_by_hand(1500 + 100 * sid)  # somewhere else than the goal register says
            servo.poke(reg.GOAL_POSITION, 3000)
    robot = await manager.create_robot("so-arm100", robot_id="arm")
    driver = usb_slave(sim, MODEL)
    await robot.attach_slave(driver)
    await eventually(lambda: all(servo_torque(sim).values()), what="torque on")
    assert servo_goals(sim) == {sid: 1500 + 100 * sid for sid in range(1, 7)}
    await eventually(lambda: robot.snapshot().joint("Rotation").real_value is not None)
    real = robot.snapshot().joint("Rotation").real_value
    assert real == pytest.approx((1600 - 2048) * 360 / 4096)
    await robot.detach_slave(robot.snapshot().slaves[0].peer_id)
    await eventually(lambda: not any(servo_torque(sim).values()), what="torque off on detach")


async def test_a_ping_lost_at_connect_is_asked_again_but_a_missing_servo_refuses(
    manager: RobotManager, sim: PtySimBus
) -> None:
    from arena.servo.worker import PING_ATTEMPTS

    robot = await manager.create_robot("so-arm100", robot_id="arm")
    with sim.paused() as bus:
        bus.servo(3).faults.drop = PING_ATTEMPTS - 1  # lost replies, then it answers
    await robot.attach_slave(usb_slave(sim, MODEL))
    await eventually(lambda: all(servo_torque(sim).values()), what="torque on")
    with sim.paused() as bus:
        assert bus.servo(3).faults.drop == 0  # every lost reply was a ping asked again
    await robot.detach_slave(robot.snapshot().slaves[0].peer_id)
    await eventually(lambda: not any(servo_torque(sim).values()), what="torque off on detach")
    with sim.paused() as bus:
        bus.servo(3).faults.drop = PING_ATTEMPTS  # as many as the attempts: missing
    refused_driver = usb_slave(sim, MODEL)
    with pytest.raises(ArenaError) as refused:
        await refused_driver.prepare()  # what attaching over REST waits for
    assert refused.value.code is ErrorCode.SERVO_TIMEOUT and "Servo 3" in refused.value.message


async def test_follows_targets_and_reports_real_values(
    manager: RobotManager, sim: PtySimBus
) -> None:
    robot = await manager.create_robot("so-arm100", robot_id="arm")
    await robot.attach_slave(usb_slave(sim, MODEL))
    await eventually(lambda: all(servo_torque(sim).values()))
    await wait_joined(robot)
    with robot.subscribe() as events:
        result = await robot.command(Command.of({"Rotation": 20.0, "Elbow": -30.0}, duration=0.3))
        assert result.accepted
        await eventually(
            lambda: abs((robot.snapshot().joint("Elbow").real_value or 0) + 30.0) < 0.2,
            what="the real elbow to reach -30",
        )
        final = {1: steps(20.0), 3: steps(-30.0)}
        await eventually(lambda: {k: servo_goals(sim)[k] for k in final} == final)
        got = events.drain()
    readings = [e for e in got if isinstance(e, JointStatesReceived)]
    assert len(readings) > 10  # the move was reported as it happened, not just at the end
    rotation = [e.joints["Rotation"] for e in readings]
    assert rotation == sorted(rotation)  # and it moved monotonically (min-jerk, no overshoot)


@pytest.mark.parametrize("policy", ["hold", "torque-off"])
async def test_estop_freezes_the_arm(manager: RobotManager, sim: PtySimBus, policy: str) -> None:
    robot = await manager.create_robot("so-arm100", robot_id="arm")
    await robot.attach_slave(usb_slave(sim, MODEL, estop=policy))
    await eventually(lambda: all(servo_torque(sim).values()))
    await wait_joined(robot)
    await robot.command(Command.of({"Rotation": 60.0}, duration=2.0))
    await eventually(lambda: (robot.snapshot().joint("Rotation").real_value or 0) > 10)
    await robot.estop("test")

    torque_now = {1} if policy == "hold" else {0}

    def stopped() -> bool:
        with sim.paused() as bus:
            rotation = bus.servo(1)
            held = abs(rotation.present - rotation.peek(reg.GOAL_POSITION)) <= 2
        return held and set(servo_torque(sim).values()) == torque_now

    await eventually(stopped, what="goal = present (stopped where it was), torque per policy")
    with sim.paused() as bus:
        goal = bus.servo(1).peek(reg.GOAL_POSITION)
    assert goal < steps(59.0)
    # Targets that still arrive are ignored; a manual command is refused anyway.
    assert not (await robot.command(Command.of({"Rotation": 0.0}))).accepted
    await robot.reset()
    await eventually(lambda: all(servo_torque(sim).values()), what="torque back after reset")
    assert abs(servo_goals(sim)[1] - goal) <= 2  # the reset moved nothing


async def test_silent_servo_times_out_then_the_bus_is_lost_and_recovers(
    manager: RobotManager, sim: PtySimBus
) -> None:
    robot = await manager.create_robot("so-arm100", robot_id="arm")
    with robot.subscribe() as events:
        await robot.attach_slave(usb_slave(sim, MODEL, lost_after=5))
        await eventually(lambda: all(servo_torque(sim).values()))
        with sim.paused() as bus:
            bus.servo(3).faults.silent = True
        await eventually(lambda: robot.snapshot().mode is Mode.ESTOPPED, what="e-stop")
        slave = robot.snapshot().slaves[0]
        assert not slave.connected
        with sim.paused() as bus:
            bus.servo(3).faults.silent = False
        got: list[object] = []

        def measured_again() -> bool:
            # "adopted" follows "reconnected" once a reading came back: wait for it, not for time
            got.extend(events.drain())
            changes = [e.change for e in got if isinstance(e, PeerChanged)]
            return "reconnected" in changes and changes[-1] == "adopted"

        await eventually(measured_again, what="reconnection, the pose measured again")
    faults = [e for e in got if isinstance(e, FaultReported)]
    timeout = next(f for f in faults if f.code == ErrorCode.SERVO_TIMEOUT)
    assert timeout.joint == "Elbow"
    changes = [e.change for e in got if isinstance(e, PeerChanged)]
    links = [change for change in changes if change in ("disconnected", "reconnected")]
    assert links[-2:] == ["disconnected", "reconnected"]
    assert changes[-1] == "adopted"  # back, the arm's pose is measured again (it may have moved)
    assert robot.snapshot().mode is Mode.ESTOPPED  # the loss policy: stays stopped until reset


async def test_unplugged_bus_comes_back_without_stale_goals(
    manager: RobotManager, sim: PtySimBus
) -> None:
    robot = await manager.create_robot("so-arm100", robot_id="arm")
    await robot.attach_slave(usb_slave(sim, MODEL))
    await eventually(lambda: all(servo_torque(sim).values()))
    sim.unplug()
    await eventually(lambda: not robot.snapshot().slaves[0].connected, what="loss")
    assert robot.snapshot().mode is Mode.ESTOPPED
    # The robot says why: the worker's own account of the loss, passed on whole.
    why = robot.snapshot().slaves[0].last_error or ""
    assert why.startswith(f"SLAVE_LOST: servo bus on {sim.link}: The servo bus on {sim.link}")
    assert why.endswith("check the USB cable and the servo power supply.")
    await robot.reset()
    await robot.command(Command.of({"Rotation": 45.0}))  # sent while the bus is away
    await trio.sleep(0.6)  # the whole move happens (virtually) during the outage
    sim.plug()
    await eventually(lambda: robot.snapshot().slaves[0].connected, what="reconnection")
    await trio.sleep(0.2)
    with sim.paused() as bus:
        assert bus.servo(1).peek(reg.GOAL_POSITION) == bus.servo(1).present  # nothing stale
        assert bus.servo(1).present == steps(0.0)


@pytest.mark.parametrize(
    ("fault", "code", "severity"),
    [
        ("overheat", ErrorCode.SERVO_OVERHEAT, Severity.CRITICAL),
        ("voltage", ErrorCode.SERVO_VOLTAGE, Severity.ERROR),
        ("corrupt", ErrorCode.SERVO_CORRUPT, Severity.WARNING),
        ("stall", ErrorCode.SERVO_OVERLOAD, Severity.CRITICAL),
    ],
)
async def test_servo_faults_become_errors_naming_the_joint(
    manager: RobotManager, sim: PtySimBus, fault: str, code: ErrorCode, severity: Severity
) -> None:
    robot = await manager.create_robot("so-arm100", robot_id="arm")
    with robot.subscribe() as events:
        # (a stall long enough for the servo's own overload protection: Arena's stall guard,
        # which stops pushing after a second, is tested in tests/test_force.py)
        await robot.attach_slave(usb_slave(sim, MODEL, stallTime=60.0))
        await eventually(lambda: all(servo_torque(sim).values()))
        await wait_joined(robot)
        with sim.paused() as bus:
            servo = bus.servo(2)
            if fault == "overheat":
                servo.temperature = 72.0
            elif fault == "voltage":
                servo.voltage = 3.0
            elif fault == "corrupt":
                servo.faults.corrupt = True
            else:
                servo.faults.stalled = True
        if fault == "stall":
            await robot.command(Command.of({"Pitch": 20.0}))
        found: list[FaultReported] = []

        def seen() -> bool:
            found.extend(e for e in events.drain() if isinstance(e, FaultReported))
            return any(f.code == code for f in found)

        await eventually(seen, timeout=8.0, what=str(code))
    fault_event = next(f for f in found if f.code == code)
    assert fault_event.joint == "Pitch"
    assert fault_event.severity == severity
    critical = severity is Severity.CRITICAL
    assert (robot.snapshot().mode is Mode.ESTOPPED) == critical


async def test_uses_the_calibration_file(
    manager: RobotManager, sim: PtySimBus, tmp_path: Path
) -> None:
    calibration = Calibration.identity({j.name: j.servo_id for j in MODEL.joints})
    joints = dict(calibration.joints)
    joints["Rotation"] = joints["Rotation"].__class__(servo_id=1, offset=100, direction=-1)
    path = tmp_path / "arm.json"
    Calibration(joints=joints).save(path)
    robot = await manager.create_robot("so-arm100", robot_id="arm")
    await robot.attach_slave(usb_slave(sim, MODEL, path))
    await eventually(lambda: all(servo_torque(sim).values()))
    await wait_joined(robot)
    await robot.command(Command.of({"Rotation": 10.0}))
    # degrees = -(raw + 100 - 2048) * 360/4096  ->  raw = 2048 - 100 - 10 * 4096/360
    await eventually(lambda: servo_goals(sim)[1] == round(2048 - 100 - 10 * 4096 / 360))


async def test_follows_a_sequence_closely(manager: RobotManager, sim: PtySimBus) -> None:
    from arena.drivers.sequence_master import SequenceMaster
    from arena.drivers.sequences import parse_sequence

    # Each pose is held a second after its 0.4 s move: the servos (simulated behind a pty, on
    # real time) must get there before the next move begins. A busy machine only delays the
    # simulator's replies (its bus waits for it, see `open_test_bus`): no servo turns silent.
    sequence = parse_sequence(
        {
            "id": "short",
            "name": "short",
            "commands": [
                {"timestamp": 0, "duration": 400, "joints": [{"name": "Elbow", "value": -20}]},
                {"timestamp": 1400, "duration": 400, "joints": [{"name": "Elbow", "value": 15}]},
                {"timestamp": 2800, "duration": 400, "joints": [{"name": "Elbow", "value": 0}]},
            ],
            "total_duration": 3200,
        }
    )
    robot = await manager.create_robot("so-arm100", robot_id="arm")
    await robot.attach_slave(usb_slave(sim, MODEL))
    await eventually(lambda: all(servo_torque(sim).values()))
    await wait_joined(robot)
    extremes: list[float] = []
    with robot.subscribe() as events:

        def seen() -> list[float]:
            # Taken as they come: the queue is bounded and drops its oldest events.
            for event in events.drain():
                if isinstance(event, JointStatesReceived) and "Elbow" in event.joints:
                    extremes.append(event.joints["Elbow"])
            return extremes

        await robot.attach_master(SequenceMaster([sequence]))
        await eventually(
            lambda: bool(seen()) and robot.snapshot().owner is None, what="the sequence to end"
        )
        await eventually(lambda: abs(seen()[-1]) <= 0.2, what="the arm at rest")
    assert events.dropped == 0
    assert min(extremes) == pytest.approx(-20, abs=0.5)
    assert max(extremes) == pytest.approx(15, abs=0.5)
    assert extremes[-1] == pytest.approx(0, abs=0.2)  # and it came to rest where it should


async def test_late_replies_time_out_and_readings_stay_right(
    manager: RobotManager, sim: PtySimBus
) -> None:
    robot = await manager.create_robot("so-arm100", robot_id="arm")
    with sim.paused() as bus:
        for sid, servo in bus.servos.items():
            servo.move_by_hand(2048 + 100 * sid)  # every servo reads differently
    with robot.subscribe() as events:
        await robot.attach_slave(usb_slave(sim, MODEL, lost_after=1000))
        await eventually(lambda: all(servo_torque(sim).values()))
        got: list[object] = []

        def seen(condition: Callable[[list[object]], bool]) -> Callable[[], bool]:
            def check() -> bool:
                got.extend(events.drain())
                return condition(got)

            return check

        def timed_out(events_so_far: list[object]) -> bool:
            return any(
                isinstance(e, FaultReported) and e.code == ErrorCode.SERVO_TIMEOUT
                for e in events_so_far
            )

        with sim.paused() as bus:
            bus.servo(2).faults.late = 0.08  # past the reply timeout: it lands in the next read
        await eventually(seen(timed_out), what="a timeout")
        with sim.paused() as bus:
            bus.servo(2).faults.late = 0.0
        cleared = len(got)
        await eventually(
            seen(lambda g: sum(isinstance(e, JointStatesReceived) for e in g[cleared:]) > 10),
            what="readings after the fault",
        )
    faults = [e for e in got if isinstance(e, FaultReported)]
    assert any(f.code == ErrorCode.SERVO_TIMEOUT and f.joint == "Pitch" for f in faults)
    expected = {j.name: 100 * j.servo_id * 360 / 4096 for j in MODEL.joints}
    readings = [e.joints for e in got if isinstance(e, JointStatesReceived)]
    assert len(readings) > 10
    for joints in readings:
        for name, value in joints.items():
            assert value == pytest.approx(expected[name], abs=0.1), name


async def test_a_stop_while_the_bus_is_away_is_kept_when_it_returns(
    manager: RobotManager, sim: PtySimBus
) -> None:
    robot = await manager.create_robot("so-arm100", robot_id="arm")
    driver = usb_slave(sim, MODEL, estop="torque-off")
    await robot.attach_slave(driver)
    await eventually(lambda: all(servo_torque(sim).values()), what="torque on")
    sim.unplug()  # the loss e-stops the robot while the slave cannot reach its servos
    await eventually(lambda: not robot.snapshot().slaves[0].connected, what="loss")
    assert robot.snapshot().mode is Mode.ESTOPPED
    await eventually(lambda: driver.frozen, what="the slave told to stop, with its bus away")
    sim.plug()
    await eventually(lambda: robot.snapshot().slaves[0].connected, what="reconnection")
    assert set(servo_torque(sim).values()) == {0}  # torque-off: it comes back released
    await robot.reset()
    await eventually(lambda: all(servo_torque(sim).values()), what="torque back after reset")


async def test_a_simulator_kept_off_the_cpu_is_not_a_silent_servo(
    manager: RobotManager, sim: PtySimBus
) -> None:
    robot = await manager.create_robot("so-arm100", robot_id="arm")
    await robot.attach_slave(usb_slave(sim, MODEL, lost_after=5))
    await eventually(lambda: all(servo_torque(sim).values()), what="torque on")
    with robot.subscribe() as events:
        with sim.paused():  # the bus thread cannot answer, as on a machine too busy to run it
            await trio.sleep(1.0)  # many times lost_after x the reply timeout
        got: list[object] = []

        def answered_again() -> bool:
            got.extend(events.drain())
            return sum(isinstance(e, JointStatesReceived) for e in got) > 10

        await eventually(answered_again, what="readings after the pause")
    assert not [
        e for e in got if isinstance(e, FaultReported) and e.code is ErrorCode.SERVO_TIMEOUT
    ]
    lost = [e for e in got if isinstance(e, PeerChanged) and e.change == "disconnected"]
    assert not lost and robot.snapshot().slaves[0].connected  # never lost
    assert robot.snapshot().mode is not Mode.ESTOPPED
