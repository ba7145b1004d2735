"""The real Modbus driver against the real Modbus server of the simulated stage.

Everything goes over TCP on loopback (and RTU over a pseudo-terminal null modem): the
bytes on the wire are those a real controller would see.
"""

from __future__ import annotations

import math
import os
import select
import socket
import threading
import time
import tty

import pytest
from pymodbus.client import ModbusTcpClient

from drivers.arm import SoftLimits
from drivers.errors import (
    AlarmError,
    CommunicationError,
    DeviceError,
    DeviceTimeoutError,
    LimitsError,
    MoveInterruptedError,
)
from drivers.modbus_arm import ModbusArm, contiguous_runs
from drivers.modbus_profile import SIM_STAGE_PROFILE, ProfileError, WatchdogSection, load_profile
from drivers.pose import Pose
from sim_devices.modbus_server import SimulatedModbusArm, decode_int32, encode_int32
from sim_devices.stage import (
    ALARM_COMM_TIMEOUT,
    ALARM_INJECTED,
    ALARM_TEXT,
    ALARM_TRAVEL,
    SimulatedStage,
    StageConfig,
)

pytestmark = pytest.mark.timeout(30)

# Read-back noise is 5 um and 1e-5 rad; the wire resolution 1 um and 1 millidegree.
POSITION_TOLERANCE_M = 30e-6
ANGLE_TOLERANCE_RAD = 1e-4

NEAR = Pose(0.05, 0.08, 0.22, math.pi, 0.0, 0.0)
FAR = Pose(-0.25, -0.25, 0.45, math.pi, 0.0, 0.0)  # about 0.5 m from home: ~1.2 s


def fast_stage() -> SimulatedStage:
    return SimulatedStage(StageConfig(speed_m_s=0.5, accel_m_s2=2.0))


def assert_close(measured: Pose, expected: Pose) -> None:
    distance, angle = measured.distance_to(expected)
    assert distance < POSITION_TOLERANCE_M, (measured, expected)
    assert angle < ANGLE_TOLERANCE_RAD, (measured, expected)


@pytest.fixture
def stage() -> SimulatedStage:
    return fast_stage()


@pytest.fixture
def server(stage):
    with SimulatedModbusArm(stage, port=0) as running:
        yield running


@pytest.fixture
def open_arm(server):
    """Factory of connected arms on ``server``; every arm is closed after the test."""
    arms: list[ModbusArm] = []

    def factory(profile=None, **options) -> ModbusArm:
        options.setdefault("timeout_s", 0.5)
        options.setdefault("retries", 2)
        arm = ModbusArm(profile or server.profile, port=server.port, **options)
        arm.connect()
        arms.append(arm)
        return arm

    yield factory
    for arm in arms:
        arm.close()


@pytest.fixture
def arm(open_arm) -> ModbusArm:
    return open_arm()


# -- motion ---------------------------------------------------------------------------------
def test_move_reads_back_the_target_within_the_noise(arm, stage):
    target = Pose(0.1, -0.05, 0.3, math.radians(170), math.radians(5), math.radians(-10))
    reached = arm.move_to(target, timeout=10)
    assert_close(reached, target)
    assert_close(stage.true_pose(), target)
    assert arm.status().in_position


def test_a_long_move_takes_time_and_reports_moving(arm):
    seen = []
    read_status = arm.status

    def recording_status():
        status = read_status()
        seen.append(status)
        return status

    arm.status = recording_status
    start = time.monotonic()
    reached = arm.move_to(FAR, timeout=10)
    elapsed = time.monotonic() - start
    assert elapsed > 0.8  # 0.5 m at 0.5 m/s with 2 m/s^2 ramps: 1.24 s
    assert any(status.moving for status in seen)
    assert seen[-1].in_position and not seen[-1].moving
    assert_close(reached, FAR)


def test_home_returns_to_the_home_pose(arm, stage):
    arm.move_to(NEAR, timeout=10)
    reached = arm.home(timeout=10)
    assert_close(reached, stage.config.home_pose)


def test_stop_during_a_long_move_leaves_the_stage_short_of_the_target(arm, stage):
    start = stage.true_pose()
    outcome = {}

    def move():
        try:
            outcome["pose"] = arm.move_to(FAR, timeout=10)
        except DeviceError as exc:
            outcome["error"] = exc

    mover = threading.Thread(target=move)
    mover.start()
    time.sleep(0.3)
    arm.stop()
    mover.join(timeout=5)
    assert not mover.is_alive()
    # move_to must not pretend the target was reached.
    assert isinstance(outcome.get("error"), MoveInterruptedError), outcome
    here = stage.true_pose()
    assert not stage.moving
    assert here.distance_to(start)[0] > 0.01  # it did move...
    assert here.distance_to(FAR)[0] > 0.1  # ...and stopped well short
    time.sleep(0.1)
    assert stage.true_pose() == here


# -- refusals and alarms --------------------------------------------------------------------
def test_soft_limit_violation_names_the_axis_and_sends_nothing(open_arm, server):
    arm = open_arm(limits=SoftLimits({"x": (-0.2, 0.2), "z": (0.0, 0.4)}))
    writes_before = server.writes_received
    with pytest.raises(LimitsError) as caught:
        arm.move_to(Pose(0.0, 0.0, 0.45, math.pi, 0.0, 0.0))
    message = str(caught.value)
    assert "z=" in message and "soft limits" in message and arm.name in message
    assert server.writes_received == writes_before


def test_injected_alarm_raises_with_code_and_text_and_reset_clears_it(arm, server, stage):
    server.inject_alarm_on_move(stage.move_count + 2, ALARM_INJECTED)
    arm.move_to(NEAR, timeout=10)  # the first move is fine
    with pytest.raises(AlarmError) as caught:
        arm.move_to(FAR, timeout=10)
    assert caught.value.code == ALARM_INJECTED
    assert "0x0410" in str(caught.value)
    assert ALARM_TEXT[ALARM_INJECTED] in str(caught.value)
    assert "\n" not in str(caught.value)
    arm.reset_alarm()
    assert not arm.status().alarm
    assert_close(arm.move_to(FAR, timeout=10), FAR)


def test_alarm_injected_over_modbus_registers(arm, server, stage):
    # What a test in another process does: write [move number, code] to the
    # simulation registers of the profile.
    injection = server.profile.simulation.inject_alarm_on_move
    with ModbusTcpClient("127.0.0.1", port=server.port, timeout=1) as raw:
        reply = raw.write_registers(injection, [stage.move_count + 1, ALARM_TRAVEL], device_id=1)
        assert not reply.isError()
    with pytest.raises(AlarmError) as caught:
        arm.move_to(NEAR, timeout=10)
    assert caught.value.code == ALARM_TRAVEL
    assert ALARM_TEXT[ALARM_TRAVEL] in str(caught.value)


def test_a_target_outside_the_stage_travel_raises_the_travel_alarm(arm):
    # No soft limits: the controller's own travel check answers.
    with pytest.raises(AlarmError) as caught:
        arm.move_to(Pose(0.35, 0.0, 0.2, math.pi, 0.0, 0.0), timeout=10)
    assert caught.value.code == ALARM_TRAVEL


def test_a_modbus_exception_reply_is_a_device_error_with_its_code(open_arm, server):
    # A driver profile that reads the alarm code where this device has no register.
    wrong_map = server.profile.model_copy(update={"alarm": server.profile.alarm.model_copy(update={"address": 40})})
    arm = open_arm(wrong_map)
    with pytest.raises(DeviceError) as caught:
        arm.status()
    assert type(caught.value) is DeviceError
    assert "Modbus exception 2 (illegal data address)" in str(caught.value)


# -- link failures --------------------------------------------------------------------------
def test_a_server_that_stops_answering_times_out_quickly(open_arm, server):
    arm = open_arm(timeout_s=0.2, retries=1)
    server.stop_answering(True)
    start = time.monotonic()
    with pytest.raises(DeviceTimeoutError) as caught:
        arm.status()
    assert time.monotonic() - start < 3.0
    message = str(caught.value)
    assert arm.name in message and "status" in message and f"127.0.0.1:{server.port}" in message
    server.stop_answering(False)
    assert not arm.status().alarm  # the link recovers by itself


def test_a_dropped_connection_is_retried_transparently(arm, server):
    arm.status()
    server.drop_connections()
    assert server.connection_count == 0
    assert_close(arm.move_to(NEAR, timeout=10), NEAR)
    assert server.connection_count == 1


def test_connection_refused_names_the_endpoint(stage):
    with socket.socket() as probe:  # a port that nobody listens on
        probe.bind(("127.0.0.1", 0))
        free_port = probe.getsockname()[1]
    arm = ModbusArm(SIM_STAGE_PROFILE, port=free_port, timeout_s=0.2, retries=1)
    with pytest.raises(CommunicationError) as caught:
        arm.connect()
    message = str(caught.value)
    assert f"127.0.0.1:{free_port}" in message and "connect" in message and arm.name in message
    with pytest.raises(CommunicationError):
        arm.status()  # not connected: refused cleanly, no client left behind


# -- watchdog -------------------------------------------------------------------------------
def test_the_heartbeat_keeps_the_watchdog_fed_and_its_loss_stops_the_stage(open_arm, server, stage):
    quick = server.profile.model_copy(
        update={"watchdog": WatchdogSection(address=server.profile.watchdog.address, timeout_ms=500)}
    )
    arm = open_arm(quick)
    assert stage.watchdog_timeout_s == pytest.approx(0.5)
    time.sleep(1.0)  # idle for twice the timeout: only the heartbeat talks
    assert stage.alarm_code == 0

    arm._start_move(FAR)
    arm._stop_heartbeat()  # the host goes silent in the middle of a move
    deadline = time.monotonic() + 3.0
    while stage.alarm_code == 0 and time.monotonic() < deadline:
        time.sleep(0.02)
    assert stage.alarm_code == ALARM_COMM_TIMEOUT
    assert not stage.moving
    assert stage.true_pose().distance_to(FAR)[0] > 0.1
    status = arm.status()
    assert status.alarm_code == ALARM_COMM_TIMEOUT
    assert status.alarm_text == ALARM_TEXT[ALARM_COMM_TIMEOUT]


def test_a_clean_close_disarms_the_watchdog(server, stage):
    with ModbusArm(server.profile, port=server.port) as arm:
        assert stage.watchdog_timeout_s == pytest.approx(server.profile.watchdog.timeout_ms / 1000)
        arm.status()
    assert stage.watchdog_timeout_s == 0.0


# -- profiles -------------------------------------------------------------------------------
def test_little_endian_word_order_round_trips(tmp_path):
    text = SIM_STAGE_PROFILE.read_text(encoding="utf-8")
    assert 'word_order = "big"' in text
    little = tmp_path / "little_stage.toml"
    little.write_text(text.replace('word_order = "big"', 'word_order = "little"'), encoding="utf-8")
    profile = load_profile(little)
    assert profile.device.word_order == "little"
    target = Pose(-0.123456, 0.05, 0.25, math.pi, 0.0, 0.0)
    with SimulatedModbusArm(fast_stage(), little) as server, ModbusArm(little, port=server.port) as arm:
        assert_close(arm.move_to(target, timeout=10), target)
        # On the wire the low word comes first.
        with ModbusTcpClient("127.0.0.1", port=server.port, timeout=1) as raw:
            registers = raw.read_holding_registers(profile.axes["x"].target, count=2, device_id=1).registers
        assert registers == encode_int32(-123456, "little")
        assert registers != encode_int32(-123456, "big")
        assert decode_int32(registers, "little") == -123456


def test_a_bad_profile_is_refused_in_one_line_naming_the_field(tmp_path):
    text = SIM_STAGE_PROFILE.read_text(encoding="utf-8")
    broken = tmp_path / "broken.toml"
    broken.write_text(text.replace("counts_per_unit = 1_000_000", "counts_per_unit = 0", 1), encoding="utf-8")
    with pytest.raises(ProfileError) as caught:
        ModbusArm(broken)
    message = str(caught.value)
    assert message == f"{broken}: axes.x.counts_per_unit: must be > 0 (got 0)"
    assert "\n" not in message

    broken.write_text(text.replace("[status]", "[status", 1), encoding="utf-8")
    with pytest.raises(ProfileError, match=r"broken\.toml: not valid TOML: .*line \d+") as caught:
        load_profile(broken)
    assert "\n" not in str(caught.value)

    broken.write_text(text.replace("address = 21", "address = 20", 1), encoding="utf-8")
    with pytest.raises(ProfileError, match=r"watchdog\.address: register 20 is also used by command\.address"):
        load_profile(broken)


def test_contiguous_targets_are_written_in_one_request():
    profile = load_profile()
    runs = contiguous_runs((axis.target, 2) for axis in profile.axes.values())
    assert runs == [(0, 12)]


def test_identity_names_the_device_and_the_endpoint(arm, server):
    assert arm.identity == f"ModbusArm(mirrorgonio simulated stage @ tcp://127.0.0.1:{server.port})"


# -- Modbus RTU -----------------------------------------------------------------------------
@pytest.fixture
def null_modem():
    """Two pseudo-terminals joined like a null-modem cable: (server end, client end)."""
    master_a, slave_a = os.openpty()
    master_b, slave_b = os.openpty()
    for slave in (slave_a, slave_b):
        tty.setraw(slave)  # no echo, no line editing before pyserial configures it
    stop = threading.Event()

    def relay() -> None:
        other = {master_a: master_b, master_b: master_a}
        while not stop.is_set():
            readable, _, _ = select.select(list(other), [], [], 0.02)
            for fd in readable:
                try:
                    os.write(other[fd], os.read(fd, 4096))
                except OSError:
                    pass

    relay_thread = threading.Thread(target=relay, daemon=True)
    relay_thread.start()
    yield os.ttyname(slave_a), os.ttyname(slave_b)
    stop.set()
    relay_thread.join(timeout=2)
    for fd in (master_a, master_b, slave_a, slave_b):
        os.close(fd)


def test_modbus_rtu_over_a_serial_line(null_modem, stage):
    server_end, client_end = null_modem
    # Linux pseudo-terminals refuse parity bits, so this line runs 8N1 (RS-485 is often 8E1).
    line = {"baudrate": 115200, "parity": "N", "stopbits": 1}
    with SimulatedModbusArm(stage, serial_port=server_end, **line):
        arm = ModbusArm(SIM_STAGE_PROFILE, transport="rtu", serial_port=client_end, timeout_s=0.5, **line)
        with arm:
            assert arm.identity.startswith("ModbusArm(mirrorgonio simulated stage @ rtu://")
            assert_close(arm.move_to(NEAR, timeout=10), NEAR)
            assert_close(stage.true_pose(), NEAR)
