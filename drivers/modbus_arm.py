"""An arm or stage driven over Modbus TCP or Modbus RTU, described by a register profile.

The register map (targets, read-backs, command, status bits, alarm code, watchdog) comes
from a :class:`~drivers.modbus_profile.ModbusProfile`, so one driver serves every
controller that speaks Modbus; ``drivers/profiles/sim_stage.toml`` documents the
simulated stage.

Behaviour on the wire
---------------------
- A move writes the six int32 targets in one request (function code 16) where the
  profile keeps them consecutive, then writes the move code to the command register.
- Transient failures (no reply in ``timeout_s``, connection dropped or refused, garbled
  frame) are retried ``retries`` times after a short back-off, reconnecting first; the
  last failure is raised as :class:`DeviceTimeoutError` or :class:`CommunicationError`.
- A Modbus exception reply is the device refusing: it is raised at once as
  :class:`DeviceError` with the exception code.
- Where the profile has a watchdog, :meth:`ModbusArm.connect` arms it and a daemon
  thread reads the status register whenever the link has been idle for a third of the
  timeout. If the host process dies or hangs, the controller's watchdog stops the arm.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Literal, cast

from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.client.base import ModbusBaseSyncClient
from pymodbus.exceptions import ConnectionException, ModbusIOException
from pymodbus.pdu import ModbusPDU

from drivers.arm import Arm, ArmStatus, SoftLimits
from drivers.errors import CommunicationError, DeviceError, DeviceTimeoutError, LimitsError
from drivers.modbus_profile import ModbusProfile, load_profile
from drivers.pose import AXES, Pose

_log = logging.getLogger(__name__)

_INT32 = ModbusTcpClient.DATATYPE.INT32
#: One Modbus request on a connected client, returning the controller's reply.
_Request = Callable[[ModbusBaseSyncClient], ModbusPDU]

#: Meaning of the Modbus exception codes (Modbus application protocol v1.1b3, 7).
MODBUS_EXCEPTION_TEXT = {
    1: "illegal function",
    2: "illegal data address",
    3: "illegal data value",
    4: "server device failure",
    5: "acknowledge",
    6: "server device busy",
    8: "memory parity error",
    10: "gateway path unavailable",
    11: "gateway target device failed to respond",
}

#: Alarm code reported when the alarm bit is set but the alarm register reads 0.
UNKNOWN_ALARM = 0xFFFF


def contiguous_runs(blocks: Iterable[tuple[int, int]]) -> list[tuple[int, int]]:
    """Merge ``(start, count)`` register blocks that touch into ``(start, count)`` runs.

    Examples
    --------
    >>> contiguous_runs([(2, 2), (0, 2), (10, 1)])
    [(0, 4), (10, 1)]
    """
    runs: list[tuple[int, int]] = []
    for start, count in sorted(blocks):
        if runs and start <= runs[-1][0] + runs[-1][1]:
            run_start, run_count = runs[-1]
            runs[-1] = (run_start, max(run_count, start + count - run_start))
        else:
            runs.append((start, count))
    return runs


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


class ModbusArm(Arm):
    """An arm whose controller speaks Modbus TCP or Modbus RTU.

    Parameters
    ----------
    profile : ModbusProfile or path
        The controller's register map, or the TOML file holding it.
    transport : {"tcp", "rtu"}
        Modbus TCP to ``host:port``, or Modbus RTU on ``serial_port``.
    host, port : str, int
        TCP endpoint.
    serial_port : str
        Serial device (or a pyserial URL) for RTU.
    baudrate, parity, stopbits : int, str, int
        Serial line settings for RTU (8 data bits).
    timeout_s : float
        How long one request waits for its reply.
    retries : int
        How many times a request that failed transiently is sent again.
    retry_backoff_s : float
        Pause before the first retry; the n-th retry waits n times as long.
    limits : SoftLimits
        Checked before anything of a move is sent.
    name : str
        Device name in error messages; the profile's device name by default.
    poll_interval_s, sleep, clock
        As for :class:`~drivers.arm.Arm`. The heartbeat and the retry back-off use real
        time whatever ``sleep`` and ``clock`` are: the controller's watchdog does.
    """

    def __init__(
        self,
        profile: ModbusProfile | str | Path,
        *,
        transport: Literal["tcp", "rtu"] = "tcp",
        host: str = "127.0.0.1",
        port: int = 502,
        serial_port: str | None = None,
        baudrate: int = 19200,
        parity: str = "E",
        stopbits: int = 1,
        timeout_s: float = 1.0,
        retries: int = 3,
        retry_backoff_s: float = 0.05,
        limits: SoftLimits | None = None,
        name: str | None = None,
        poll_interval_s: float = 0.01,
        sleep: Callable[[float], None] = time.sleep,
        clock: Callable[[], float] = time.monotonic,
    ):
        self.profile = profile if isinstance(profile, ModbusProfile) else load_profile(profile)
        super().__init__(
            name or self.profile.device.name,
            limits=limits,
            poll_interval_s=poll_interval_s,
            sleep=sleep,
            clock=clock,
        )
        if transport not in ("tcp", "rtu"):
            raise ValueError(f"{self.name}: transport must be 'tcp' or 'rtu', not {transport!r}")
        if transport == "rtu" and not serial_port:
            raise ValueError(f"{self.name}: transport 'rtu' needs serial_port")
        if retries < 0 or timeout_s <= 0:
            raise ValueError(f"{self.name}: retries must be >= 0 and timeout_s > 0")
        self.transport = transport
        self.host = host
        self.port = port
        self.serial_port = serial_port
        self.baudrate = baudrate
        self.parity = parity
        self.stopbits = stopbits
        self.timeout_s = timeout_s
        self.retries = retries
        self.retry_backoff_s = retry_backoff_s
        self._unit = self.profile.device.unit_id
        self._word_order = self.profile.device.word_order
        self._client: ModbusTcpClient | ModbusSerialClient | None = None
        # One request at a time on the link: the caller and the heartbeat thread share it.
        self._lock = threading.RLock()
        self._last_traffic = time.monotonic()
        self._heartbeat: threading.Thread | None = None
        self._heartbeat_stop = threading.Event()

    # -- description -------------------------------------------------------------------
    @property
    def endpoint(self) -> str:
        """Where the controller is, e.g. ``tcp://127.0.0.1:502``."""
        if self.transport == "tcp":
            return f"tcp://{self.host}:{self.port}"
        return f"rtu://{self.serial_port}@{self.baudrate},8{self.parity}{self.stopbits}"

    @property
    def identity(self) -> str:
        return f"ModbusArm({self.name} @ {self.endpoint})"

    # -- life cycle --------------------------------------------------------------------
    def connect(self) -> None:
        """Open the link, check that the controller answers and arm its watchdog.

        Raises
        ------
        CommunicationError
            If the endpoint cannot be reached (the message names it).
        DeviceTimeoutError
            If it is reached but does not answer.
        """
        if self._client is not None:
            return
        self._client = self._make_client()
        try:
            watchdog = self.profile.watchdog
            if watchdog is not None:
                self._write_registers("connect", {watchdog.address: watchdog.timeout_ms})
            else:
                # A TCP connection alone does not prove that a controller answers.
                self._read_inputs("connect", [(self.profile.status.address, 1)])
        except DeviceError:
            with self._lock:
                self._client.close()
                self._client = None
            raise
        self._start_heartbeat()

    def close(self) -> None:
        """Stop the heartbeat, disarm the watchdog and close the link.

        A clean close disarms the watchdog: the host leaves on purpose, and the next
        session should not find a communication alarm latched.
        """
        self._stop_heartbeat()
        if self._client is None:
            return
        watchdog = self.profile.watchdog
        if watchdog is not None:
            try:
                self._write_registers("close", {watchdog.address: 0}, retries=0)
            except DeviceError as exc:
                _log.warning("%s (the watchdog stays armed)", exc)
        with self._lock:
            self._client.close()
            self._client = None

    # -- motion primitives -------------------------------------------------------------
    def _start_move(self, pose: Pose) -> None:
        registers: dict[int, int] = {}
        # Encode every axis before sending anything, so a bad value sends nothing.
        for axis in AXES:
            spec = self.profile.axes[axis]
            try:
                counts = spec.to_counts(getattr(pose, axis))
            except ValueError as exc:
                raise LimitsError(self.name, "move_to", f"{axis}: {exc}") from None
            first_word, second_word = self._encode_int32(counts)
            registers[spec.target] = first_word
            registers[spec.target + 1] = second_word
        self._write_registers("move_to", registers)
        self._command("move_to", self.profile.command.move)

    def _start_home(self) -> None:
        self._command("home", self.profile.command.home)

    def stop(self) -> None:
        self._command("stop", self.profile.command.stop)

    def reset_alarm(self) -> None:
        self._command("reset_alarm", self.profile.command.reset_alarm)

    # -- read-back ---------------------------------------------------------------------
    def position(self) -> Pose:
        axes = self.profile.axes
        registers = self._read_inputs("position", [(axes[a].actual, 2) for a in AXES])
        values = []
        for axis in AXES:
            spec = axes[axis]
            counts = self._decode_int32(registers[spec.actual], registers[spec.actual + 1])
            values.append(spec.from_counts(counts))
        return Pose(*values)

    def status(self) -> ArmStatus:
        status_map = self.profile.status
        alarm_address = self.profile.alarm.address
        registers = self._read_inputs("status", [(status_map.address, 1), (alarm_address, 1)])
        word = registers[status_map.address]

        def bit(number: int) -> bool:
            return bool(word >> number & 1)

        # The alarm bit is authoritative: some controllers keep the last code after a reset.
        code = registers[alarm_address] if bit(status_map.alarm) else 0
        text = self.profile.alarm_text(code)
        if bit(status_map.alarm) and code == 0:
            code, text = UNKNOWN_ALARM, "alarm bit set but the alarm code register reads 0"
        return ArmStatus(
            moving=bit(status_map.moving),
            in_position=bit(status_map.in_position),
            alarm_code=code,
            alarm_text=text,
            homed=bit(status_map.homed),
            servo_on=bit(status_map.servo_on),
        )

    # -- registers ---------------------------------------------------------------------
    def _encode_int32(self, counts: int) -> tuple[int, int]:
        first, second = ModbusTcpClient.convert_to_registers(counts, _INT32, word_order=self._word_order)
        return first, second

    def _decode_int32(self, first: int, second: int) -> int:
        value = ModbusTcpClient.convert_from_registers([first, second], _INT32, word_order=self._word_order)
        return int(cast(int, value))  # an INT32 decodes to an int

    def _command(self, command: str, code: int) -> None:
        self._write_registers(command, {self.profile.command.address: code})

    def _write_registers(self, command: str, values: dict[int, int], retries: int | None = None) -> None:
        """Write holding registers, one request per run of consecutive addresses."""
        for start, count in contiguous_runs((address, 1) for address in values):
            block = [values[address] for address in range(start, start + count)]
            if count == 1:
                self._transact(
                    command,
                    cast(
                        _Request, lambda client, a=start, v=block[0]: client.write_register(a, v, device_id=self._unit)
                    ),
                    retries,
                )
            else:
                self._transact(
                    command,
                    cast(_Request, lambda client, a=start, v=block: client.write_registers(a, v, device_id=self._unit)),
                    retries,
                )

    def _read_inputs(
        self, command: str, blocks: Iterable[tuple[int, int]], retries: int | None = None
    ) -> dict[int, int]:
        """Read input registers, one request per run of consecutive addresses."""
        registers: dict[int, int] = {}
        for start, count in contiguous_runs(blocks):
            response = self._transact(
                command,
                cast(
                    _Request,
                    lambda client, a=start, n=count: client.read_input_registers(a, count=n, device_id=self._unit),
                ),
                retries,
            )
            if len(response.registers) != count:
                raise CommunicationError(
                    self.name, command, f"asked {count} registers at {start}, got {len(response.registers)}"
                )
            registers.update(zip(range(start, start + count), response.registers, strict=False))
        return registers

    def _transact(
        self,
        command: str,
        request: _Request,
        retries: int | None = None,
    ) -> ModbusPDU:
        """Send one request and return its reply, retrying transient failures.

        Raises
        ------
        DeviceError
            The controller answered with a Modbus exception.
        DeviceTimeoutError
            No reply on the last attempt.
        CommunicationError
            The link failed on the last attempt.
        """
        attempts = 1 + (self.retries if retries is None else retries)
        failure: DeviceError | None = None
        for attempt in range(attempts):
            if attempt:
                time.sleep(self.retry_backoff_s * attempt)
            with self._lock:
                client = self._client
                if client is None:
                    raise CommunicationError(self.name, command, "not connected (call connect() first)")
                try:
                    if not client.connected and not client.connect():
                        failure = CommunicationError(self.name, command, f"cannot connect to {self.endpoint}")
                        continue
                    response = request(client)
                except ModbusIOException as exc:
                    # Start the next attempt on a fresh link: a late reply must not be
                    # taken for the answer to the next request.
                    client.close()
                    if "no response" in str(exc).lower():
                        failure = DeviceTimeoutError(
                            self.name, command, f"no reply from {self.endpoint} within {self.timeout_s:g} s"
                        )
                    else:
                        failure = CommunicationError(
                            self.name, command, f"bad exchange with {self.endpoint}: {_one_line(exc)}"
                        )
                    continue
                except (ConnectionException, OSError) as exc:
                    client.close()
                    failure = CommunicationError(
                        self.name, command, f"link to {self.endpoint} failed: {_one_line(exc)}"
                    )
                    continue
                self._last_traffic = time.monotonic()
            if response.isError():
                code = response.exception_code
                meaning = MODBUS_EXCEPTION_TEXT.get(code, "unknown exception")
                raise DeviceError(self.name, command, f"Modbus exception {code} ({meaning}) from {self.endpoint}")
            return response
        assert failure is not None
        suffix = f" (after {attempts} attempts)" if attempts > 1 else ""
        raise type(failure)(self.name, command, failure.cause + suffix)

    def _make_client(self) -> ModbusTcpClient | ModbusSerialClient:
        # pymodbus's own retries are off: retries, back-off and reconnection happen in
        # _transact, so that `retries` means the same for every failure.
        if self.transport == "tcp":
            return ModbusTcpClient(self.host, port=self.port, timeout=self.timeout_s, retries=0, name=self.name)
        assert self.serial_port is not None  # __init__ requires it for rtu
        return ModbusSerialClient(
            self.serial_port,
            baudrate=self.baudrate,
            bytesize=8,
            parity=self.parity,
            stopbits=self.stopbits,
            timeout=self.timeout_s,
            retries=0,
            name=self.name,
        )

    # -- heartbeat ---------------------------------------------------------------------
    def _start_heartbeat(self) -> None:
        watchdog = self.profile.watchdog
        if watchdog is None:
            return
        period_s = watchdog.timeout_ms / 3000.0
        self._heartbeat_stop = threading.Event()
        self._heartbeat = threading.Thread(
            target=self._heartbeat_loop,
            args=(period_s, self._heartbeat_stop),
            name=f"{self.name} heartbeat",
            daemon=True,  # a dying host must not be kept alive by it: the watchdog is the point
        )
        self._heartbeat.start()

    def _stop_heartbeat(self) -> None:
        self._heartbeat_stop.set()
        if self._heartbeat is not None and self._heartbeat is not threading.current_thread():
            self._heartbeat.join(timeout=(self.timeout_s + self.retry_backoff_s) * (self.retries + 2))
        self._heartbeat = None

    def _heartbeat_loop(self, period_s: float, stop: threading.Event) -> None:
        due = time.monotonic() + period_s
        while not stop.wait(max(0.0, due - time.monotonic())):
            idle_since = self._last_traffic
            if time.monotonic() - idle_since < period_s:
                # The caller talked recently; that fed the watchdog already.
                due = idle_since + period_s
                continue
            try:
                self._read_inputs("heartbeat", [(self.profile.status.address, 1)], retries=0)
            except DeviceError as exc:
                _log.warning("%s", exc)
            due = time.monotonic() + period_s


__all__ = ["MODBUS_EXCEPTION_TEXT", "UNKNOWN_ALARM", "ModbusArm", "contiguous_runs"]
