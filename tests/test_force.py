"""Force limits, stall and heat protection: through a real server on the simulated buses."""

from __future__ import annotations

import math
from collections.abc import Awaitable, Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import trio

from arena.drivers.usb_slave import torque_limits
from arena.feetech import registers as reg
from arena.protocol.errors import ArenaError, ErrorCode
from arena.recording.mcap_file import read_recording
from arena.robot.model import load_robot_model
from arena.servo.force import ForceGuard, ForceSettings
from arena.servo.sim_pty import AMBIENT_C, PtySimBus
from tests.conftest import RunningServer, eventually
from tests.hardware import open_test_bus, running_sim
from tests.lerobot_arms import joined

StartServer = Callable[..., Awaitable[RunningServer]]
GRIPPER = 6


@pytest.fixture
def sim(tmp_path: Path) -> Iterator[PtySimBus]:
    yield from running_sim(tmp_path)


def peek(sim: PtySimBus, sid: int, register: reg.Register) -> int:
    """A register of one simulated servo."""
    with sim.paused() as bus:
        return int(bus.servo(sid).peek(register))


async def attach_so101(http: Any, sim: PtySimBus, **more: Any) -> Any:
    """Robot `arm` of type so-101, its usb-slave on the simulated bus; the attach's reply."""
    made = await http.post("/api/robots", json={"id": "arm", "robot_type": "so-101"})
    assert made.status_code == 201, made.text
    body = {"type": "usb-slave", "port": str(sim.link), **more}
    return await http.post("/api/robots/arm/slaves", json=body)


async def grip_an_object(http: Any, sim: PtySimBus) -> None:
    """An object between the jaws: a stop 60 steps on from where the gripper is, and a command
    that drives the gripper far past it (uncalibrated, 2048 reads 0 %, 100 % is 1250 steps on)."""
    here = peek(sim, GRIPPER, reg.PRESENT_POSITION)
    with sim.paused() as bus:
        bus.servo(GRIPPER).place_obstacle(here + 60)
    move = {"joints": [{"name": "gripper", "value": 100}]}
    answer = await http.put("/api/robots/arm/joints", json=move)
    assert answer.status_code == 200, answer.text
    await eventually(
        lambda: peek(sim, GRIPPER, reg.GOAL_POSITION) > here + 200, what="the gripper's goal"
    )


async def test_a_torque_limit_is_written_to_the_servo_and_obeyed(
    start_server: StartServer, sim: PtySimBus
) -> None:
    server = await start_server()
    async with server.client() as http:
        attached = await attach_so101(
            http, sim, torqueLimit={"gripper": 30, "shoulder_pan": 80}, stallTime=60
        )
        assert attached.status_code == 201, attached.text
        await eventually(lambda: joined(http), what="the arm joined")
        limits = {sid: peek(sim, sid, reg.TORQUE_LIMIT) for sid in range(1, 7)}
        assert limits == {1: 800, 2: 1000, 3: 1000, 4: 1000, 5: 1000, 6: 300}
        await grip_an_object(http, sim)
        # Held by the object, it pushes with what its limit allows and no more.
        await eventually(
            lambda: peek(sim, GRIPPER, reg.PRESENT_LOAD) == 300, what="the gripper pushing at 30 %"
        )
        assert peek(sim, GRIPPER, reg.TORQUE_ENABLE) == 1


async def test_the_so101_gripper_is_capped_as_lerobot_caps_it(
    start_server: StartServer, sim: PtySimBus
) -> None:
    with sim.paused() as bus:
        bus.servo(GRIPPER).poke(reg.TORQUE_LIMIT, 1000)
    server = await start_server()
    async with server.client() as http:
        attached = await attach_so101(http, sim)
        assert attached.status_code == 201, attached.text
        await eventually(lambda: joined(http), what="the arm joined")
        # LeRobot's Max_Torque_Limit 500 for the SO follower's gripper (so_follower.py).
        assert peek(sim, GRIPPER, reg.TORQUE_LIMIT) == 500
        assert peek(sim, 1, reg.TORQUE_LIMIT) == 1000


@pytest.mark.parametrize(
    ("limits", "status", "code"),
    [
        ({"thumb": 50}, 422, "UNKNOWN_JOINT"),
        ({"gripper": 150}, 422, "INVALID_BODY"),
        ({"gripper": 0}, 422, "INVALID_BODY"),
        ({f"j{k}": 10 for k in range(40)}, 422, "INVALID_BODY"),
    ],
)
async def test_a_bad_torque_limit_is_refused_with_a_reason(
    start_server: StartServer, sim: PtySimBus, limits: dict[str, int], status: int, code: str
) -> None:
    server = await start_server()
    async with server.client() as http:
        refused = await attach_so101(http, sim, torqueLimit=limits)
        assert refused.status_code == status, refused.text
        assert refused.json()["error"]["code"] == code
        assert refused.json()["error"]["message"]
        assert peek(sim, 1, reg.TORQUE_ENABLE) == 0  # nothing was started


def test_the_koch_gripper_is_current_based_as_lerobot_runs_it(tmp_path: Path) -> None:
    pytest.importorskip("dynamixel_sdk")
    from arena.dynamixel import registers as dr
    from arena.dynamixel.sim import SimBus as DynamixelSim

    model = load_robot_model("koch")
    assert torque_limits(model, {}) == {GRIPPER: 100.0}
    assert torque_limits(model, {"gripper": 40}) == {GRIPPER: 40.0}
    for sim in running_sim(tmp_path, bus=DynamixelSim()):
        bus = open_test_bus(str(sim.link))
        bus.open()
        try:
            bus.prepare(range(1, 7), limited=[GRIPPER])
            bus.set_torque_limits({sid: 100.0 for sid in range(1, 6)} | {GRIPPER: 40.0})
            bus.read_positions(range(1, 7))  # (answered after the write: it was handled)
            with sim.paused() as servos:
                modes = {sid: s.peek(dr.OPERATING_MODE) for sid, s in servos.servos.items()}
                goal_current = servos.servo(GRIPPER).peek(dr.GOAL_CURRENT)
            assert modes == {1: 3, 2: 3, 3: 3, 4: 3, 5: 3, 6: dr.OperatingMode.CURRENT_POSITION}
            assert goal_current == 700  # 40 % of the XL330-M288's 1750 mA
            # A servo not in current-based mode cannot be lowered: the others are written.
            with pytest.raises(ArenaError) as unlimited:
                bus.set_torque_limits({2: 50.0, GRIPPER: 20.0})
            assert unlimited.value.code is ErrorCode.INVALID_CONFIG
            assert "[2]" in unlimited.value.message
            bus.read_positions(range(1, 7))
            with sim.paused() as servos:
                assert servos.servo(GRIPPER).peek(dr.GOAL_CURRENT) == 350
            # A limit on an XL430, which reads no current, is refused, naming it.
            with pytest.raises(ArenaError) as refused:
                bus.prepare(range(1, 7), limited=[2, GRIPPER])
            assert refused.value.code is ErrorCode.INVALID_CONFIG
            assert "XL430-W250" in refused.value.message and "servo 2" in refused.value.message
        finally:
            bus.close()


async def slave_faults(http: Any) -> set[tuple[str, str | None]]:
    """The (code, joint) of each fault robot `arm`'s slave shows now."""
    robot = (await http.get("/api/robots/arm")).json()
    return {(f["code"], f["joint"]) for f in robot["slaves"][0]["faults"]}


async def test_a_blocked_gripper_stalls_eases_to_a_holding_torque_and_stays_cool(
    start_server: StartServer, sim: PtySimBus
) -> None:
    with sim.paused() as bus:  # heats and cools twice as fast as the defaults: same limits
        bus.servo(GRIPPER).heating *= 2
        bus.servo(GRIPPER).cooling *= 2
        # The servo's own overload protection races the stall in real time here (a loaded
        # machine can lose it): that the stall comes first is proven in the bus's own time
        # (test_a_joint_held_while_its_goal_runs_on_stalls_before_the_servo_trips).
        bus.servo(GRIPPER).overload_after = 60.0
    server = await start_server()
    async with server.client() as http:
        # Uncapped, as a gripper pushing with all it has would burn (110 C when it settles).
        attached = await attach_so101(http, sim, torqueLimit={"gripper": 100}, stallTime=0.5)
        assert attached.status_code == 201, attached.text
        await eventually(lambda: joined(http), what="the arm joined")
        await grip_an_object(http, sim)

        async def stalled() -> bool:
            return ("STALL", "gripper") in await slave_faults(http)

        await eventually(stalled, what="a STALL fault naming the gripper")
        robot = (await http.get("/api/robots/arm")).json()
        assert robot["state"] != "estopped"  # a warning: the robot goes on
        # Eased to a holding torque: it keeps its grip, gently, and cools down.
        await eventually(
            lambda: peek(sim, GRIPPER, reg.TORQUE_LIMIT) == 250, what="the holding torque"
        )
        await eventually(
            lambda: peek(sim, GRIPPER, reg.PRESENT_LOAD) == 250, what="the gentle grip"
        )
        with sim.paused() as bus:
            servo = bus.servo(GRIPPER)
            load, celsius = servo.load, servo.temperature
            settles_at = AMBIENT_C + servo.heating * load**2 / servo.cooling
        assert load == pytest.approx(0.25)
        assert celsius < 55  # the warm threshold was never reached
        assert settles_at < 40  # and never will be: 35 C at 25 % (110 C pushing uncapped)
        assert peek(sim, GRIPPER, reg.TORQUE_ENABLE) == 1
        # The next command moves it again, with its limit back: the fault clears.
        with sim.paused() as bus:
            bus.servo(GRIPPER).remove_obstacle()
        move = {"joints": [{"name": "gripper", "value": 10}]}
        assert (await http.put("/api/robots/arm/joints", json=move)).status_code == 200

        async def released() -> bool:
            return ("STALL", "gripper") not in await slave_faults(http)

        await eventually(released, what="the STALL fault cleared")
        await eventually(
            lambda: peek(sim, GRIPPER, reg.TORQUE_LIMIT) == 1000, what="the gripper's own limit"
        )
        await eventually(
            lambda: abs(peek(sim, GRIPPER, reg.PRESENT_POSITION) - 2173) <= 3,
            what="the gripper at 10 %",
        )


async def test_a_blocked_joint_stops_pushing_where_it_is(
    start_server: StartServer, sim: PtySimBus
) -> None:
    server = await start_server()
    async with server.client() as http:
        attached = await attach_so101(http, sim, stallTime=0.5)
        assert attached.status_code == 201, attached.text
        await eventually(lambda: joined(http), what="the arm joined")
        with sim.paused() as bus:
            bus.servo(1).place_obstacle(2048 + 100)  # a wall 8.8 degrees on
            bus.servo(1).overload_after = 60.0  # (no race in real time: as for the gripper)
        # A slow move (8 s): the wall is met at about 3 s, the stall found while it runs on.
        move = {"joints": [{"name": "shoulder_pan", "value": 30}], "duration": 8000}
        assert (await http.put("/api/robots/arm/joints", json=move)).status_code == 200

        async def stalled() -> bool:
            return ("STALL", "shoulder_pan") in await slave_faults(http)

        async def moved_on() -> bool:
            """The robot's target for it at the move's end; held at the wall until then."""
            joints = (await http.get("/api/robots/arm/joints")).json()
            pan = next(j for j in joints if j["name"] == "shoulder_pan")
            assert peek(sim, 1, reg.GOAL_POSITION) == 2148, pan
            return bool(pan["virtual_value"] == 30.0)

        await eventually(stalled, what="a STALL fault naming shoulder_pan")
        # It stops pushing: its goal is where it stopped, its load gone, no overload.
        await eventually(
            lambda: peek(sim, 1, reg.GOAL_POSITION) == 2148, what="the goal where it stopped"
        )
        await eventually(lambda: peek(sim, 1, reg.PRESENT_LOAD) == 0, what="no load")
        # The rest of the move (targets further on into the wall) does not push it again.
        await eventually(moved_on, what="the move's end")  # (never released meanwhile)
        assert peek(sim, 1, reg.GOAL_POSITION) == 2148
        assert peek(sim, 1, reg.TORQUE_ENABLE) == 1
        assert await stalled()
        # The next command (away from the wall) moves it.
        move = {"joints": [{"name": "shoulder_pan", "value": -10}]}
        assert (await http.put("/api/robots/arm/joints", json=move)).status_code == 200
        await eventually(
            lambda: abs(peek(sim, 1, reg.PRESENT_POSITION) - (2048 - 114)) <= 3,
            what="shoulder_pan at -10",
        )

        async def released() -> bool:
            return ("STALL", "shoulder_pan") not in await slave_faults(http)

        await eventually(released, what="the STALL fault cleared")


async def test_a_warm_servo_gets_its_torque_limit_lowered(
    start_server: StartServer, sim: PtySimBus
) -> None:
    server = await start_server()
    async with server.client() as http:
        attached = await attach_so101(http, sim)
        assert attached.status_code == 201, attached.text
        await eventually(lambda: joined(http), what="the arm joined")
        with sim.paused() as bus:
            bus.servo(GRIPPER).temperature = 60.0
            bus.servo(GRIPPER).cooling = 0.001  # it stays warm while the test looks
        await eventually(
            lambda: peek(sim, GRIPPER, reg.TORQUE_LIMIT) == 250, what="half its 50 % limit"
        )
        assert peek(sim, 1, reg.TORQUE_LIMIT) == 1000
        text = (await http.get("/metrics")).text
        assert 'arena_servo_temperature_celsius{robot="arm",joint="gripper"} 60' in text
        assert 'arena_servo_load_percent{robot="arm",joint="shoulder_pan"} 0' in text
        with sim.paused() as bus:
            bus.servo(GRIPPER).temperature = 45.0  # cooled: its own limit comes back
        await eventually(
            lambda: peek(sim, GRIPPER, reg.TORQUE_LIMIT) == 500, what="its own limit back"
        )


def test_the_guard_counts_a_stall_from_the_push_on_its_own_clock() -> None:
    guard = ForceGuard({GRIPPER: 50.0}, grippers=[GRIPPER], settings=ForceSettings(stall_time=1.0))
    guard.goal(1, 3000)
    guard.goal(GRIPPER, 3000)
    cool = {1: 30.0, GRIPPER: 30.0}
    # Short of the goal but with little load (still moving): no stall, however long.
    assert guard.observe(0.0, {1: 2500, GRIPPER: 2500}, {1: 10.0, GRIPPER: 10.0}, cool) == []
    assert guard.observe(5.0, {1: 2600, GRIPPER: 2600}, {1: 10.0, GRIPPER: 10.0}, cool) == []
    # Pushing: half its limit is high for the capped gripper (25 of 50), not for the other.
    assert guard.observe(6.0, {1: 2600, GRIPPER: 2600}, {1: 30.0, GRIPPER: 30.0}, cool) == []
    # A goal that runs on does not restart the wait: the joint has not moved.
    guard.goal(GRIPPER, 3100)
    assert guard.observe(6.9, {1: 2600, GRIPPER: 2600}, {1: 30.0, GRIPPER: 30.0}, cool) == []
    (stall,) = guard.observe(7.0, {1: 2600, GRIPPER: 2600}, {1: 30.0, GRIPPER: 30.0}, cool)
    assert (stall.servo_id, stall.present, stall.goal, stall.limit) == (GRIPPER, 2600, 3100, 50.0)
    assert guard.stalled(GRIPPER) and guard.limit(GRIPPER) == 25.0  # the holding torque
    assert guard.observe(9.0, {GRIPPER: 2600}, {GRIPPER: 25.0}, cool) == []  # told once
    # Goals on into the object are the same push; one backing off is a new command.
    assert guard.pushes_on(GRIPPER, 3100) and guard.pushes_on(GRIPPER, 3400)
    assert guard.pushes_on(GRIPPER, 3080) and not guard.pushes_on(GRIPPER, 3079)
    guard.release(GRIPPER)
    assert not guard.stalled(GRIPPER) and guard.limit(GRIPPER) == 50.0
    # Warm: the limit halves; it comes back only once cooled past the margin.
    assert guard.observe(10.0, {}, {}, {1: 56.0}) == [] and guard.limit(1) == 50.0
    guard.observe(11.0, {}, {}, {1: 52.0})
    assert guard.limit(1) == 50.0
    guard.observe(12.0, {}, {}, {1: 49.0})
    assert guard.limit(1) == 100.0


async def test_hand_guiding_records_the_motion_as_commands_that_replay(
    start_server: StartServer, sim: PtySimBus, tmp_path: Path
) -> None:
    server = await start_server()
    async with server.client() as http:
        attached = await attach_so101(http, sim)
        assert attached.status_code == 201, attached.text
        await eventually(lambda: joined(http), what="the arm joined")
        refused = await http.post(
            "/api/robots/arm/compliance", json={"joints": ["thumb"], "torque": 20}
        )
        assert refused.status_code == 422 and refused.json()["error"]["code"] == "UNKNOWN_JOINT"
        holder = await server.app.manager.get("arm").connect_master("holder")
        busy = await http.post(
            "/api/robots/arm/compliance", json={"joints": ["shoulder_pan"], "torque": 20}
        )
        assert busy.status_code == 409 and busy.json()["error"]["code"] == "MASTER_ACTIVE"
        assert peek(sim, 1, reg.TORQUE_LIMIT) == 1000  # nothing changed
        await holder.release()
        assert (await http.delete("/api/robots/arm/compliance")).json() == {"detached": None}
        entered = await http.post(
            "/api/robots/arm/compliance", json={"joints": ["shoulder_pan"], "torque": 20}
        )
        assert entered.status_code == 201, entered.text
        assert entered.json()["joints"] == ["shoulder_pan"]
        robot = (await http.get("/api/robots/arm")).json()
        assert robot["master"]["kind"] == "hand-guide"
        await eventually(lambda: peek(sim, 1, reg.TORQUE_LIMIT) == 200, what="20 % torque")
        assert peek(sim, 2, reg.TORQUE_LIMIT) == 1000  # the other joints stay stiff
        # A hand takes shoulder_pan round, step by step: the robot's target follows it.
        for step in range(2098, 2310, 50):
            with sim.paused() as bus:
                bus.servo(1).hold_by_hand(step)
            await eventually(
                lambda s=step: abs(peek(sim, 1, reg.GOAL_POSITION) - s) <= 12,  # type: ignore[misc]
                what=f"the goal following the hand to {step}",
            )
        with sim.paused() as bus:
            bus.servo(1).let_go()
        left = await http.delete("/api/robots/arm/compliance")
        assert left.json() == {"detached": entered.json()["id"]}
        await eventually(lambda: peek(sim, 1, reg.TORQUE_LIMIT) == 1000, what="full torque back")
        # It holds where the hand left it (22 degrees on), no spring back.
        await trio.sleep(0.3)
        assert abs(peek(sim, 1, reg.PRESENT_POSITION) - 2298) <= 12
        back = {"joints": [{"name": "shoulder_pan", "value": 0}]}
        assert (await http.put("/api/robots/arm/joints", json=back)).status_code == 200
        await eventually(
            lambda: abs(peek(sim, 1, reg.PRESENT_POSITION) - 2048) <= 3, what="back at 0"
        )

        async def file_open() -> bool:
            return bool((await http.get("/api/recordings")).json()["recorder"]["file"])

        await eventually(file_open, what="the recording's file")
        name = (await http.post("/api/recordings/current/stop")).json()["stopped"]
        guided = [
            m
            for m in read_recording(tmp_path / "recordings" / name).messages
            if m.kind == "command" and m.data["label"] == "hand-guide"  # (its own source)
        ]
        assert len(guided) >= 4 and all(m.data["accepted"] for m in guided)
        values = [m.data["joints"][0]["value"] for m in guided]
        assert values == sorted(values) and values[-1] > 20  # the way the hand went
        # Replayed: the arm goes the way the hand took it.
        replay = await http.post("/api/robots/arm/replay", json={"recording": name, "speed": 2})
        assert replay.status_code == 201, replay.text
        await eventually(
            lambda: peek(sim, 1, reg.GOAL_POSITION) > 2270, what="the replay going the hand's way"
        )


def run_into_a_wall(guard: ForceGuard, wall: float | None, load_of_moving: float = 0.0) -> float:
    """Servo 1 of a simulated Feetech bus, its goal streamed on 25 steps every 10 ms (about
    220 deg/s) from 1000 to 4000 while the guard watches 10 reads a second, in the bus's own
    time: when the guard found the stall (inf: never). Each read lands as a goal is written,
    so it finds the horn where the last goal took it. A `wall` stops the horn there; else it
    follows, loaded (lifting, say) with `load_of_moving` percent while it moves."""
    from arena.feetech.sim import SimBus as FeetechSim

    servo = FeetechSim().servo(1)
    servo.move_by_hand(1000)
    if wall is not None:
        servo.place_obstacle(wall)
    servo.poke(reg.TORQUE_ENABLE, 1)
    for k in range(400):
        now = k / 100
        goal = min(1000 + 25 * k, 4000)
        servo.poke(reg.GOAL_POSITION, goal)
        guard.goal(1, goal)
        if k % 10 == 0:
            present = round(servo.present_position)
            load = 100.0 * servo.load if wall is not None else load_of_moving * (goal < 4000)
            if guard.observe(now, {1: present}, {1: load}, {1: servo.temperature}):
                return now
        servo.advance(now)
        assert servo.peek(reg.TORQUE_ENABLE) == 1, f"the servo's own protection tripped at {now}"
    return math.inf


def test_a_joint_held_while_its_goal_runs_on_stalls_before_the_servo_trips() -> None:
    # A wall 100 steps on, met at once; the goal runs on for 1.2 s. Counted from the push, the
    # stall comes a second later, before the STS3215's own 2 s protection drops the horn (the
    # goal's last change would be 2.2 s, after it: the CI run that e-stopped).
    settings = ForceSettings(stall_time=1.0)
    found = run_into_a_wall(ForceGuard({}, settings=settings), wall=1100)
    assert 1.0 <= found <= 1.2
    # Loaded as much but following its goal (25 steps behind it): never a stall.
    assert run_into_a_wall(ForceGuard({}, settings=settings), None, load_of_moving=90) == math.inf
    # Pushed back while it pushes (a load it cannot hold, a hand): moving, but a stall.
    guard = ForceGuard({}, settings=settings)
    guard.goal(1, 3000)
    sagging = [guard.observe(k / 10, {1: 2600 - 3 * k}, {1: 90.0}, {1: 30.0}) for k in range(11)]
    assert [k for k, found in enumerate(sagging) if found] == [10]
