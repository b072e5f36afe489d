"""The pure Feetech pieces: register encodings, the packet codec, calibration units, health."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from arena.feetech import registers as reg
from arena.feetech.bus import FEETECH
from arena.feetech.packets import Corrupt, Packet, PacketParser, checksum, encode
from arena.protocol.errors import ArenaError, ErrorCode, Severity
from arena.servo.calibration import (
    Calibration,
    JointCalibration,
    RangeCapture,
    calibrate_rest,
    homing_offset_register,
    offset_for,
)
from arena.servo.health import HealthLimits, HealthMonitor
from arena.servo.interface import SyncReadResult

# -- registers ---------------------------------------------------------------------------------


@given(st.integers(-32767, 32767))
def test_sign_magnitude_round_trips(value: int) -> None:
    assert reg.GOAL_POSITION.decode(reg.GOAL_POSITION.encode(value)) == value


def test_sign_magnitude_known_values() -> None:
    assert reg.GOAL_POSITION.encode(-5) == bytes([5, 0x80])  # bit 15 is the sign
    assert reg.PRESENT_LOAD.decode(bytes([0x10, 0x04])) == -16  # bit 10 for the load
    assert reg.HOMING_OFFSET.encode(-2047) == bytes([0xFF, 0x0F])  # bit 11 for homing
    with pytest.raises(ValueError, match="sign bit"):
        reg.HOMING_OFFSET.encode(-2048)
    with pytest.raises(ValueError, match="unsigned"):
        reg.TORQUE_ENABLE.encode(-1)


# -- packets -----------------------------------------------------------------------------------


def test_packet_bytes_match_the_protocol() -> None:
    # Read 2 bytes at 56 from servo 1: FF FF 01 04 02 38 02 chk, chk = ~(1+4+2+0x38+2).
    assert encode(1, 0x02, bytes([0x38, 0x02])) == bytes(
        [0xFF, 0xFF, 0x01, 0x04, 0x02, 0x38, 0x02, ~(1 + 4 + 2 + 0x38 + 2) & 0xFF]
    )
    assert checksum(bytes([0xFE, 0x02, 0x01])) == ~(0xFE + 2 + 1) & 0xFF


packets = st.builds(
    Packet,
    st.integers(0, 0xFE),
    st.integers(0, 0xFF),
    st.binary(max_size=40),
)


@given(st.lists(packets, max_size=8), st.data())
def test_parser_finds_every_packet_however_the_bytes_are_split(
    sent: list[Packet], data: st.DataObject
) -> None:
    stream = b"".join(encode(p.servo_id, p.code, p.params) for p in sent)
    cuts = sorted(data.draw(st.lists(st.integers(0, len(stream)), max_size=6)))
    parser = PacketParser()
    got: list[Packet | Corrupt] = []
    start = 0
    for cut in [*cuts, len(stream)]:
        got += parser.feed(stream[start:cut])
        start = cut
    assert got == sent


def test_parser_skips_noise_and_reports_bad_checksums() -> None:
    good = encode(3, 0, b"\x01\x02")
    bad = bytearray(encode(4, 0, b"\x01\x02"))
    bad[-1] ^= 0xFF
    parser = PacketParser()
    got = parser.feed(b"\x00\x12\xff" + bytes(bad) + b"\xff\xff\xff" + good)
    assert isinstance(got[0], Corrupt) and got[0].servo_id == 4
    assert got[-1] == Packet(3, 0, b"\x01\x02")


# -- calibration -------------------------------------------------------------------------------


def test_identity_maps_center_to_zero_and_a_turn_to_360() -> None:
    joint = JointCalibration(servo_id=1)
    assert joint.to_degrees(2048) == 0.0
    assert joint.to_degrees(2048 + 1024) == 90.0
    assert joint.to_steps(-90.0) == 1024


@given(
    st.integers(0, 4095),
    st.integers(-2048, 2047),
    st.sampled_from([1, -1]),
)
def test_steps_degrees_steps_round_trips_everywhere(raw: int, offset: int, direction: int) -> None:
    joint = JointCalibration(servo_id=1, offset=offset, direction=direction)
    degrees = joint.to_degrees(raw)
    assert -180.0 <= degrees <= 180.0
    assert joint.to_steps(degrees) == raw


def test_wrap_at_zero_and_4095() -> None:
    # The short way round: raw 4095 and raw 0 are one step apart, not a whole turn.
    joint = JointCalibration(servo_id=1, offset=2048)  # raw 0 reads as 0 degrees
    assert joint.to_degrees(0) == 0.0
    assert joint.to_degrees(4095) == pytest.approx(-360 / 4096)
    assert joint.to_degrees(1) == pytest.approx(360 / 4096)
    assert joint.to_steps(-360 / 4096) == 4095
    assert joint.to_steps(0.0) == 0


def test_goals_are_clamped_to_the_captured_range() -> None:
    joint = JointCalibration(servo_id=1, min_degrees=-10.0, max_degrees=20.0)
    assert joint.to_steps(90.0) == joint.to_steps(20.0)
    assert joint.to_steps(-90.0) == joint.to_steps(-10.0)


@given(st.integers(0, 4095), st.floats(-179, 179), st.sampled_from([1, -1]))
def test_rest_calibration_makes_the_pose_read_as_the_twin(
    raw: int, rest: float, direction: int
) -> None:
    offset = offset_for(raw, rest, direction)
    assert -2048 <= offset <= 2047
    joint = JointCalibration(servo_id=1, offset=offset, direction=direction)
    assert joint.to_degrees(raw) == pytest.approx(rest, abs=360 / 4096)


def test_calibrate_rest_and_range_capture() -> None:
    calibration = Calibration.identity({"Rotation": 1, "Pitch": 2})
    calibrated = calibrate_rest(calibration, {1: 3000, 2: 1000}, {"Rotation": 0.0, "Pitch": 10.0})
    assert calibrated.to_degrees({1: 3000, 2: 1000}) == pytest.approx(
        {"Rotation": 0.0, "Pitch": 10.0}, abs=0.05
    )
    capture = RangeCapture()
    for value in (-30.0, 12.0, 45.5, 0.0):
        capture.observe({"Rotation": value, "Pitch": 10.0})
    ranged = capture.apply(calibrated)
    assert (ranged.joints["Rotation"].min_degrees, ranged.joints["Rotation"].max_degrees) == (
        -30.0,
        45.5,
    )
    assert ranged.joints["Pitch"].min_degrees is None  # it did not move: no range captured


def test_homing_register_range_is_checked() -> None:
    assert homing_offset_register(100, 0, FEETECH) == -100
    assert homing_offset_register(100, 50, FEETECH) == -50
    with pytest.raises(ArenaError) as caught:
        homing_offset_register(-2000, 100, FEETECH)
    assert caught.value.code is ErrorCode.INVALID_CONFIG


def test_calibration_file_round_trip_and_errors(tmp_path: object) -> None:
    from pathlib import Path

    folder = Path(str(tmp_path))
    calibration = calibrate_rest(Calibration.identity({"Rotation": 1}), {1: 100}, {"Rotation": 5.0})
    calibration.save(folder / "arm.json")
    assert Calibration.load(folder / "arm.json") == calibration
    (folder / "broken.json").write_text("{not json")
    for name in ("missing.json", "broken.json"):
        with pytest.raises(ArenaError) as caught:
            Calibration.load(folder / name)
        assert caught.value.code is ErrorCode.INVALID_CONFIG


# -- health ------------------------------------------------------------------------------------


def test_health_reports_each_fault_once_its_end_once_and_again_after_it_cleared() -> None:
    monitor = HealthMonitor((1, 2), HealthLimits(hot=50, overheat=60, lost_after=3))
    ok = SyncReadResult(data={1: b"", 2: b""}, errors={1: 0, 2: 0})
    hot = SyncReadResult(data={1: b"", 2: b""}, errors={1: 0, 2: int(reg.ErrorBit.OVERLOAD)})
    first = monitor.on_read(hot)
    assert [(f.code, f.servo_id, f.severity, f.cleared) for f in first] == [
        (ErrorCode.SERVO_OVERLOAD, 2, Severity.CRITICAL, False)
    ]
    assert monitor.on_read(hot) == []
    over = monitor.on_read(ok)  # its end, once (as news: info)
    assert [(f.code, f.servo_id, f.severity, f.cleared) for f in over] == [
        (ErrorCode.SERVO_OVERLOAD, 2, Severity.INFO, True)
    ]
    assert monitor.on_read(ok) == []
    assert len(monitor.on_read(hot)) == 1
    assert [f.code for f in monitor.on_temperatures({1: 55})] == [ErrorCode.SERVO_HOT]
    # warm becomes too hot: the critical fault, and the warm one's end (the levels exclude)
    assert [(f.code, f.cleared) for f in monitor.on_temperatures({1: 61})] == [
        (ErrorCode.SERVO_OVERHEAT, False),
        (ErrorCode.SERVO_HOT, True),
    ]


def test_health_counts_a_silent_servo_as_lost() -> None:
    monitor = HealthMonitor((1, 2), HealthLimits(lost_after=3))
    silent = SyncReadResult(data={1: b""}, errors={1: 0}, missing=[2])
    faults = monitor.on_read(silent)
    assert [(f.code, f.servo_id) for f in faults] == [(ErrorCode.SERVO_TIMEOUT, 2)]
    monitor.on_read(silent)
    assert monitor.lost is None
    monitor.on_read(silent)
    assert monitor.lost == 2
    monitor.reset()
    assert monitor.lost is None
