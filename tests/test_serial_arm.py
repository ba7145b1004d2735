"""The MELFA serial driver against the simulated controller, through a real pty pair.

Every test runs :class:`drivers.serial_arm.MelfaSerialArm` over pyserial on the slave
side of a pseudo-terminal whose master side is :class:`SimulatedSerialArm`, so framing,
line settings, timeouts and retries are exercised as on an RS-232 line.
"""

from __future__ import annotations

import math
import threading
import time

import pytest

from drivers.arm import SoftLimits
from drivers.errors import (
    AlarmError,
    CommunicationError,
    DeviceError,
    DeviceTimeoutError,
    LimitsError,
    MoveInterruptedError,
)
from drivers.pose import Pose
from drivers.serial_arm import MelfaSerialArm, key_value_fields, parse_error, parse_pposf
from sim_devices.serial_peer import ERR_UNKNOWN_COMMAND, SimulatedSerialArm
from sim_devices.stage import ALARM_INJECTED, ALARM_TEXT, SimulatedStage, StageConfig

pytestmark = pytest.mark.timeout(30)

# Fast enough that a 10 cm move takes a fraction of a second.
FAST = dict(speed_m_s=0.5, accel_m_s2=5.0, angular_speed_rad_s=5.0, angular_accel_rad_s2=50.0)
# Noise bounds: five standard deviations of the stage's read-back noise, plus the
# 0.1 µm / 0.0001° rounding of the wire format.
NOISE_M = 5 * StageConfig().readback_noise_m + 1e-7
NOISE_RAD = 5 * StageConfig().readback_noise_rad + math.radians(1e-4)

TARGET = Pose(0.05, 0.12, 0.25, math.pi - 0.2, 0.1, 0.3)


def _assert_close(measured: Pose, expected: Pose, tol_m: float, tol_rad: float) -> None:
    for axis, tol in (("x", tol_m), ("y", tol_m), ("z", tol_m)):
        assert abs(getattr(measured, axis) - getattr(expected, axis)) <= tol, axis
    for axis in ("rx", "ry", "rz"):
        assert abs(getattr(measured, axis) - getattr(expected, axis)) <= tol_rad, axis


@pytest.fixture
def stage() -> SimulatedStage:
    return SimulatedStage(StageConfig(**FAST))


@pytest.fixture
def peer(stage):
    with SimulatedSerialArm(stage) as running:
        yield running


def _arm(peer: SimulatedSerialArm, **kwargs) -> MelfaSerialArm:
    options = dict(name="test arm", timeout_s=0.5, retries=1, poll_interval_s=0.005)
    options.update(kwargs)
    return MelfaSerialArm(peer.device_path, **options)


@pytest.fixture
def arm(peer):
    driver = _arm(peer)
    driver.connect()
    yield driver
    driver.close()


# -- session -------------------------------------------------------------------------
def test_connect_sends_open_cntlon_srvon_and_close_releases(peer):
    driver = _arm(peer)
    driver.connect()
    assert peer.frames_received == ["1;1;OPEN=mirrorgonio", "1;1;CNTLON", "1;1;SRVON"]
    assert driver.connected
    assert "mirrorgonio simulated stage" in driver.identity
    assert "9600 8E2" in driver.identity

    driver.close()
    assert peer.frames_received[-3:] == ["1;1;SRVOFF", "1;1;CNTLOFF", "1;1;CLOSE"]
    assert not driver.connected
    driver.close()  # closing twice is harmless


def test_nonexistent_port_gives_one_line_error_naming_it():
    port = "/dev/mirrorgonio-no-such-port"
    driver = MelfaSerialArm(port, timeout_s=0.1)
    with pytest.raises(CommunicationError) as caught:
        driver.connect()
    message = str(caught.value)
    assert "\n" not in message
    assert port in message
    assert message.startswith(f"MELFA arm on {port}: connect: ")
    assert not driver.connected


def test_request_before_connect_is_a_communication_error(peer):
    with pytest.raises(CommunicationError, match="not connected"):
        _arm(peer).position()


# -- position and motion -------------------------------------------------------------
def test_position_converts_mm_and_degrees_to_metres_and_radians(arm, stage):
    home = stage.config.home_pose  # (0, 0.10, 0.20) m, rx = pi
    _assert_close(arm.position(), home, NOISE_M, NOISE_RAD)

    # The same reading on the wire is in millimetres and degrees.
    wire = key_value_fields(arm.send_command("PPOSF", slot=9))
    assert float(wire["Y"]) == pytest.approx(100.0, abs=NOISE_M * 1000)
    assert float(wire["Z"]) == pytest.approx(200.0, abs=NOISE_M * 1000)
    assert abs(float(wire["A"])) == pytest.approx(180.0, abs=math.degrees(NOISE_RAD))


def test_move_to_reaches_target_and_reads_back_within_noise(arm, stage):
    readback = arm.move_to(TARGET, timeout=10.0)
    _assert_close(readback, TARGET, NOISE_M, NOISE_RAD)
    # The stage went exactly where it was told, up to the wire format's rounding.
    _assert_close(stage.true_pose(), TARGET, 1e-7, math.radians(1e-4))
    status = arm.status()
    assert status.in_position and not status.moving and not status.alarm
    assert status.servo_on and status.homed


def test_move_sends_target_in_mm_and_degrees(arm, peer):
    arm.move_to(Pose(0.01, -0.02, 0.03, 0.0, math.radians(30.0), math.radians(-45.0)))
    assert "1;1;EXECP1=(10.0000,-20.0000,30.0000,0.0000,30.0000,-45.0000)(7,0)" in (peer.frames_received)
    assert "1;1;EXECMOV P1" in peer.frames_received


def test_home_moves_to_the_taught_home_pose(arm, stage, peer):
    arm.move_to(TARGET)
    readback = arm.home(timeout=10.0)
    _assert_close(readback, stage.config.home_pose, NOISE_M, NOISE_RAD)
    assert "1;1;EXECMOV PHOME" in peer.frames_received


def test_soft_limit_violation_raises_before_any_byte_is_written(peer):
    driver = _arm(peer, limits=SoftLimits({"x": (-0.1, 0.1)}))
    driver.connect()
    try:
        before = peer.bytes_received
        time.sleep(0.05)  # let the peer's reader count anything still in flight
        with pytest.raises(LimitsError, match="x=0.200000 m outside the soft limits"):
            driver.move_to(Pose(0.2, 0.1, 0.2))
        time.sleep(0.05)
        assert peer.bytes_received == before
        assert peer.stage.move_count == 0
    finally:
        driver.close()


def test_stop_during_a_long_move_stops_short_of_the_target():
    slow = SimulatedStage(StageConfig(speed_m_s=0.02, accel_m_s2=0.2))
    with SimulatedSerialArm(slow) as slow_peer:
        driver = _arm(slow_peer)
        driver.connect()
        try:
            far = Pose(0.2, 0.1, 0.2, math.pi, 0.0, 0.0)  # 20 cm: about 10 s at this speed
            outcome: dict[str, object] = {}

            def move() -> None:
                try:
                    outcome["pose"] = driver.move_to(far, timeout=10.0)
                except DeviceError as exc:
                    outcome["error"] = exc

            mover = threading.Thread(target=move)
            mover.start()
            time.sleep(0.5)
            assert slow.moving
            driver.stop()  # from another thread, while move_to polls the status
            mover.join(timeout=5.0)
            assert not mover.is_alive()
            # move_to must not pretend the target was reached.
            assert isinstance(outcome.get("error"), MoveInterruptedError), outcome
            assert "stopped before reaching the target" in str(outcome["error"])
            stopped_at = slow.true_pose()
            assert far.x - stopped_at.x > 0.1
            assert not slow.moving
            _assert_close(driver.position(), stopped_at, NOISE_M, NOISE_RAD)
            assert "1;1;STOP" in slow_peer.frames_received
        finally:
            driver.close()


# -- alarms and refusals -------------------------------------------------------------
def test_injected_alarm_raises_alarm_error_and_reset_clears_it(arm, peer):
    peer.inject_alarm_on_move(2)
    arm.move_to(Pose(0.02, 0.1, 0.2, math.pi, 0.0, 0.0))

    with pytest.raises(AlarmError) as caught:
        arm.move_to(TARGET)
    assert caught.value.code == ALARM_INJECTED
    assert ALARM_TEXT[ALARM_INJECTED] in str(caught.value)
    assert str(caught.value).startswith("test arm: move_to: alarm 0x0410")
    assert arm.status().alarm

    arm.reset_alarm()
    assert "1;1;RSTALRM" in peer.frames_received
    assert not arm.status().alarm
    _assert_close(arm.move_to(TARGET), TARGET, NOISE_M, NOISE_RAD)


def test_controller_refusal_names_command_and_error_number(arm):
    with pytest.raises(DeviceError) as caught:
        arm.send_command("NOSUCHCOMMAND")
    message = str(caught.value)
    assert type(caught.value) is DeviceError
    assert "1;1;NOSUCHCOMMAND" in message
    assert f"error {ERR_UNKNOWN_COMMAND}" in message
    assert "\n" not in message


# -- a bad line ----------------------------------------------------------------------
def test_silent_controller_gives_device_timeout_quickly(peer):
    driver = _arm(peer, timeout_s=0.1, retries=1)
    driver.connect()
    try:
        peer.stop_answering(True)
        started = time.monotonic()
        with pytest.raises(DeviceTimeoutError) as caught:
            driver.status()
        elapsed = time.monotonic() - started
        assert elapsed < 1.0
        message = str(caught.value)
        assert message.startswith("test arm: status [1;1;STATE]: no reply within 0.1 s")
        assert "\n" not in message

        # The line recovers once the controller answers again.
        peer.stop_answering(False)
        assert not driver.status().alarm
    finally:
        peer.stop_answering(True)
        started = time.monotonic()
        driver.close()
        assert time.monotonic() - started < 1.0  # a dead link does not stall close()
        assert not driver.connected


def test_one_garbled_reply_is_retried_transparently(arm, peer, stage):
    peer.garble_next_reply()
    _assert_close(arm.position(), stage.config.home_pose, NOISE_M, NOISE_RAD)
    assert peer.garbled_replies == 1
    assert peer.frames_received.count("1;9;PPOSF") == 2


def test_persistently_garbled_replies_give_communication_error(arm, peer):
    peer.garble_next_reply(count=2)  # the fixture allows one retry: both attempts fail
    with pytest.raises(CommunicationError) as caught:
        arm.position()
    message = str(caught.value)
    assert message.startswith("test arm: position [1;9;PPOSF]: garbled reply")
    assert "\n" not in message
    assert peer.garbled_replies == 2
    arm.position()  # the next exchange is clean again


# -- reply parsing (no line needed) --------------------------------------------------
def test_pposf_parser_tolerates_extra_fields_and_rejects_missing_axes():
    pose = parse_pposf("X;100.0;Y;-50.5;Z;300.0;A;180.0;B;-90.0;C;45.0;L1;12.0;;6,0;100;0.00;0")
    assert pose.as_tuple() == pytest.approx((0.1, -0.0505, 0.3, math.pi, -math.pi / 2, math.pi / 4))
    with pytest.raises(ValueError, match="no C field"):
        parse_pposf("X;1;Y;2;Z;3;A;4;B;5")


def test_error_parser_reads_level_letter_and_digits():
    assert parse_error("0000") == (0, "")
    assert parse_error("H3810;Overrun") == (0x3810, "controller error H3810: Overrun")
    assert parse_error("0410") == (0x0410, "controller error 0410")
    with pytest.raises(ValueError):
        parse_error("not a number")
