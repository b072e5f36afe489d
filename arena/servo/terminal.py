"""Terminal tools: `arena calibrate` (the calibration workflow without a server) and
`arena sim-bus` (a simulated bus anyone can point the USB slave at)."""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path

from arena.protocol.errors import ArenaError, ErrorCode
from arena.robot.model import RobotModel
from arena.servo.calibration import Calibration, RangeCapture, calibrate_rest
from arena.servo.interface import ServoBus
from arena.servo.lerobot_calibration import read_register_homings, save_lerobot
from arena.servo.sim_pty import PtySimBus, SimulatedBus
from arena.servo.worker import read_positions, set_torque, store_offsets_in_servos

#: Reads a calibration makes before it gives up: a person is waiting, not an arm in motion,
#: so one late or garbled reply (a busy computer, a noisy cable) is worth asking again.
READ_ATTEMPTS = 5


def read_patiently(
    bus: ServoBus, ids: tuple[int, ...], attempts: int = READ_ATTEMPTS
) -> dict[int, int]:
    """`read_positions`, asked again up to `attempts` times while servos do not answer."""
    for _ in range(attempts - 1):
        try:
            return read_positions(bus, ids)
        except ArenaError as error:
            if error.code is not ErrorCode.SERVO_TIMEOUT:
                raise
    return read_positions(bus, ids)


#: A joint swept less than this during calibration was most likely not moved at all.
LEAST_SWEEP_DEGREES = 10.0


def calibrate_interactively(
    bus: ServoBus,
    servo_ids: Mapping[str, int],
    out: Path,
    *,
    robot_type: str = "so-arm100",
    write_homing: bool = False,
    lerobot_model: RobotModel | None = None,
    ask: Callable[[str], str] = input,
    say: Callable[[str], None] = print,
    poll_interval: float = 0.05,
) -> Calibration:
    """Walk the user through calibrating the arm on `bus`; store the result in `out`.

    Torque goes off, the user poses the arm at rest (every joint at 0 degrees: the middle of
    its range), then moves each joint through its range while min and max are recorded.
    With `lerobot_model` the file is written in LeRobot's format for that robot type.
    """
    ids = tuple(servo_ids.values())
    set_torque(bus, ids, on=False)
    homings = read_register_homings(bus, ids)  # (LeRobot's file holds the servo's own homing)
    say("Torque is off: the arm can be moved by hand (hold it, it will not hold itself).")
    say(
        "1/2  Put the arm in its rest pose, the pose the digital twin shows at 0 degrees: "
        "every joint in the middle of its range (a gripper read 0 to 100, as the so-101's: "
        "closed)."
    )
    ask("     Press Enter when it is in place. ")
    raw = read_patiently(bus, ids)
    start = (
        Calibration.load(out)
        if out.exists() and lerobot_model is None
        else Calibration.identity(servo_ids, robot_type)
    )
    calibration = calibrate_rest(start, raw, dict.fromkeys(servo_ids, 0.0))
    say("     Rest pose captured.")
    say("2/2  Move every joint slowly through its whole range, one after the other.")
    capture = RangeCapture()
    done = threading.Event()

    def watch() -> None:  # owns the bus while the main thread waits for Enter
        while not done.is_set():
            capture.observe(calibration.to_degrees(read_patiently(bus, ids)))
            done.wait(poll_interval)

    watcher = threading.Thread(target=watch, name="range-capture", daemon=True)
    watcher.start()
    try:
        ask("     Press Enter when every joint has been to both ends. ")
    finally:
        done.set()
        watcher.join()
    calibration = capture.apply(calibration)
    if write_homing:
        calibration = store_offsets_in_servos(bus, calibration, ids)
        homings = read_register_homings(bus, ids)
        say("     Offsets written to the servos' Homing_Offset registers.")
    if lerobot_model is not None:
        save_lerobot(calibration, lerobot_model, homings, bus.family, out, rest_present=raw)
    else:
        calibration.save(out)
    say(f"Saved {out}:")
    for name, joint in calibration.joints.items():
        span = (
            f"{joint.min_degrees:8.1f} .. {joint.max_degrees:6.1f} deg"
            if joint.min_degrees is not None and joint.max_degrees is not None
            else "   (no range captured)"
        )
        say(f"  {name:<12} servo {joint.servo_id}  offset {joint.offset:+5d}  {span}")
    still = [
        name
        for name, joint in calibration.joints.items()
        if joint.min_degrees is None
        or joint.max_degrees is None
        or joint.max_degrees - joint.min_degrees < LEAST_SWEEP_DEGREES
    ]
    if still:
        say(
            f"Warning: not moved through a range ({LEAST_SWEEP_DEGREES:g} degrees or more): "
            f"{', '.join(still)}. Was every joint moved from one end to the other? Run the "
            "calibration again to capture their ranges."
        )
    say("Torque stays off until a server drives the arm.")
    return calibration


def serve_sim_bus(
    link: Path,
    bus: SimulatedBus,
    wire_time: bool,
    baud: int,
    *,
    model: RobotModel | None = None,
    control_port: int | None = None,
    calibration: Calibration | None = None,
    keys: bool = False,
) -> None:
    """Run a simulated bus at `link` until SIGINT or SIGTERM. With `model`, its joints can be
    moved by hand (`arena.servo.sim_control`): over a socket on 127.0.0.1:`control_port` (0:
    any free port), and by `keys` in this terminal."""
    from arena.servo import sim_control

    stop = threading.Event()
    with PtySimBus(link, bus, wire_time=wire_time, baud=baud, share=True) as sim:
        for sig in (signal.SIGINT, signal.SIGTERM):  # once the link is ours (it may be taken)
            signal.signal(sig, lambda *_: stop.set())
        timing = f", wire time at {baud} baud" if wire_time else ""
        print(
            f"simulated {bus.family.name} bus: servos {','.join(map(str, bus.servos))} on "
            f"{sim.link} -> {sim.link.resolve()}{timing}",
            flush=True,
        )
        if model is None or (control_port is None and not keys):
            print("move its joints by hand: --control PORT (JSON lines) or --keys", flush=True)
            stop.wait()
            return
        control = sim_control.SimControl(sim, model, calibration)
        port = None
        if control_port is not None:
            port = control.serve(control_port, stop).port
        else:
            threading.Thread(target=control.run_mover, args=(stop,), daemon=True).start()
        with _keys_from_terminal() if keys else contextlib.nullcontext() as read_key:
            # (told once the keys are read one by one: a key pressed on the word counts)
            print(sim_control.usage(control, port, keys), flush=True)
            if read_key is not None:
                threading.Thread(
                    target=sim_control.key_loop,
                    args=(control, read_key, lambda text: print(text, flush=True)),
                    daemon=True,
                ).start()
            stop.wait()


@contextlib.contextmanager
def _keys_from_terminal() -> Iterator[Callable[[], str]]:
    """Single key presses from this terminal (cbreak: Ctrl-C still stops), restored after."""
    import sys
    import termios
    import tty

    stdin = sys.stdin.fileno()
    saved = termios.tcgetattr(stdin)
    tty.setcbreak(stdin)
    try:
        yield lambda: sys.stdin.read(1)
    finally:
        termios.tcsetattr(stdin, termios.TCSADRAIN, saved)
