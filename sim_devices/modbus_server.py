"""The simulated stage as a real Modbus TCP (or RTU) server.

A pymodbus server on loopback, laid out by the same register profile as the driver
(``drivers/profiles/sim_stage.toml``), translates Modbus requests into calls on one
:class:`~sim_devices.stage.SimulatedStage`:

- reads of input registers report the stage live: status bits, alarm code and the
  read-back pose (with its noise), scaled and word-ordered as the profile says;
- writes to the target registers only store the target; writing the move code to the
  command register starts the move, the other codes stop, home or reset the alarm;
- the watchdog register arms the stage's communication watchdog; every request feeds
  it, and a ticker advances the stage every 10 ms so the watchdog fires while the host
  is silent;
- the profile's ``[simulation]`` registers inject faults over Modbus, for tests in
  another process; in-process tests call :meth:`SimulatedModbusArm.inject_alarm_on_move`,
  :meth:`~SimulatedModbusArm.stop_answering` and
  :meth:`~SimulatedModbusArm.drop_connections` directly.

The server runs its own asyncio loop in a background thread, so a synchronous test can
drive it with the synchronous driver.
"""

from __future__ import annotations

import asyncio
import struct
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

from pymodbus.constants import ExcCodes
from pymodbus.framer import FramerType
from pymodbus.pdu import ModbusPDU
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from drivers.modbus_profile import SIM_STAGE_PROFILE, ModbusProfile, load_profile
from drivers.pose import AXES, Pose
from sim_devices.stage import ALARM_INJECTED, SimulatedStage, StageConfig

#: Function codes that write (coils or registers).
WRITE_FUNCTION_CODES = frozenset({5, 6, 15, 16, 22, 23})
#: Function code of "read input registers".
READ_INPUT_REGISTERS = 4

TICK_INTERVAL_S = 0.01


def encode_int32(counts: int, word_order: str) -> list[int]:
    """Two registers holding ``counts``; written independently of the driver's codec."""
    high, low = struct.unpack(">HH", struct.pack(">i", counts))
    return [high, low] if word_order == "big" else [low, high]


def decode_int32(registers: list[int], word_order: str) -> int:
    high, low = registers if word_order == "big" else registers[::-1]
    return struct.unpack(">i", struct.pack(">HH", high, low))[0]


class SimulatedModbusArm:
    """A Modbus server in front of a simulated stage.

    Parameters
    ----------
    stage : SimulatedStage
        The motion model the requests act on.
    profile : ModbusProfile or path
        Register map; the driver must use the same one.
    host : str
        Interface to listen on (TCP).
    port : int
        TCP port; 0 picks a free one, read :attr:`port` after :meth:`start`.
    serial_port : str, optional
        Serve Modbus RTU on this serial device instead of TCP.
    baudrate, parity, stopbits : int, str, int
        Serial line settings for RTU.

    Attributes
    ----------
    writes_received : int
        Write requests that reached the server, answered or not: a test proves with it
        that a refused move sent nothing.
    requests_received : int
        All requests that reached the server.
    """

    def __init__(
        self,
        stage: SimulatedStage,
        profile: ModbusProfile | str | Path = SIM_STAGE_PROFILE,
        host: str = "127.0.0.1",
        port: int = 0,
        *,
        serial_port: str | None = None,
        baudrate: int = 19200,
        parity: str = "E",
        stopbits: int = 1,
    ):
        self.stage = stage
        self.profile = profile if isinstance(profile, ModbusProfile) else load_profile(profile)
        self.host = host
        self.port = port
        self.serial_port = serial_port
        self.baudrate = baudrate
        self.parity = parity
        self.stopbits = stopbits
        self.writes_received = 0
        self.requests_received = 0
        self._count_lock = threading.Lock()
        self._silent = False
        self._silent_until = 0.0
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server: ModbusTcpServer | ModbusSerialServer | None = None
        self._shutdown: asyncio.Event | None = None
        self._thread: threading.Thread | None = None
        self._startup_error: BaseException | None = None
        commands = self.profile.command
        self._command_codes = {commands.move, commands.stop, commands.home, commands.reset_alarm}

    # -- life cycle --------------------------------------------------------------------
    @property
    def endpoint(self) -> str:
        if self.serial_port:
            return f"rtu://{self.serial_port}"
        return f"tcp://{self.host}:{self.port}"

    def start(self) -> SimulatedModbusArm:
        """Start serving in a background thread; return once the server listens.

        Raises
        ------
        OSError
            If the port cannot be opened (in use, no such serial device).
        """
        if self._thread is not None:
            return self
        ready = threading.Event()
        self._startup_error = None
        self._thread = threading.Thread(
            target=lambda: asyncio.run(self._serve(ready)),
            name=f"simulated Modbus arm {self.endpoint}",
            daemon=True,
        )
        self._thread.start()
        if not ready.wait(timeout=10.0):
            raise OSError(f"simulated Modbus arm: {self.endpoint} did not start within 10 s")
        if self._startup_error is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
            raise OSError(
                f"simulated Modbus arm: cannot serve on {self.endpoint}: {self._startup_error}"
            ) from self._startup_error
        return self

    def stop(self) -> None:
        """Close every connection and the listener, and end the server thread."""
        if self._thread is None:
            return
        if self._loop is not None and self._shutdown is not None:
            self._loop.call_soon_threadsafe(self._shutdown.set)
        self._thread.join(timeout=10.0)
        self._thread = None
        self._loop = None
        self._server = None

    def __enter__(self) -> SimulatedModbusArm:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    async def _serve(self, ready: threading.Event) -> None:
        self._loop = asyncio.get_running_loop()
        self._shutdown = asyncio.Event()
        try:
            device = self._build_device()
            if self.serial_port:
                self._server = ModbusSerialServer(
                    device,
                    framer=FramerType.RTU,
                    port=self.serial_port,
                    baudrate=self.baudrate,
                    parity=self.parity,
                    stopbits=self.stopbits,
                    trace_pdu=self._on_pdu,  # type: ignore[arg-type]  # pymodbus drops a request its hook returns None for; its stubs omit None
                )
            else:
                self._server = ModbusTcpServer(
                    device,
                    address=(self.host, self.port),
                    trace_pdu=self._on_pdu,  # type: ignore[arg-type]  # pymodbus drops a request its hook returns None for; its stubs omit None
                )
            await self._server.serve_forever(background=True)
            if not self.serial_port:
                # A listening server's transport is an asyncio.Server; pymodbus types it as a BaseTransport.
                self.port = self._server.transport.sockets[0].getsockname()[1]  # type: ignore[attr-defined]
        except Exception as exc:  # noqa: BLE001 - whatever fails here must reach start()
            self._startup_error = exc
            ready.set()
            return
        ticker = asyncio.create_task(self._tick_forever())
        ready.set()
        try:
            await self._shutdown.wait()
        finally:
            ticker.cancel()
            await self._server.shutdown()

    async def _tick_forever(self) -> None:
        # Time passes for the stage even when nobody asks: that is what trips the watchdog.
        while True:
            self.stage.tick()
            await asyncio.sleep(TICK_INTERVAL_S)

    # -- fault injection ---------------------------------------------------------------
    def inject_alarm_on_move(self, move_number: int, code: int = ALARM_INJECTED) -> None:
        """The stage raises ``code`` at its ``move_number``-th move (1-based)."""
        self.stage.inject_alarm_on_move(move_number, code)

    def stop_answering(self, silent: bool = True) -> None:
        """Keep connections open but ignore every request (no reply, no effect)."""
        self._silent = bool(silent)
        if not silent:
            self._silent_until = 0.0

    def drop_connections(self) -> None:
        """Close every client connection, as a controller reboot or a cable pull does."""
        if self.serial_port:
            raise RuntimeError("simulated Modbus arm: a serial line has no connections to drop")
        if self._loop is None or self._server is None:
            return

        server = self._server

        async def drop() -> None:
            for connection in list(server.active_connections.values()):
                connection.close()
            # Let the loop close the sockets before the caller goes on.
            await asyncio.sleep(0.01)

        asyncio.run_coroutine_threadsafe(drop(), self._loop).result(timeout=5.0)

    @property
    def connection_count(self) -> int:
        """Open client connections (TCP)."""
        if self._server is None or self.serial_port:
            return 0
        return len(self._server.active_connections)

    # -- request handling --------------------------------------------------------------
    def _answering_paused(self) -> bool:
        return self._silent or time.monotonic() < self._silent_until

    def _on_pdu(self, sending: bool, pdu: ModbusPDU) -> ModbusPDU | None:
        """pymodbus's trace hook: sees every request before it is executed.

        Returning None for a received request makes pymodbus drop it unanswered.
        """
        if sending:
            return pdu
        with self._count_lock:
            self.requests_received += 1
            if pdu.function_code in WRITE_FUNCTION_CODES:
                self.writes_received += 1
        if self._answering_paused():
            return None
        self.stage.touch()
        return pdu

    async def _on_access(
        self,
        function_code: int,
        start_address: int,
        address: int,
        count: int,
        registers: list[int],
        set_values: list[int] | list[bool] | None,
    ) -> ExcCodes | None:
        """pymodbus's device action: called with the register block of every request."""
        if function_code == READ_INPUT_REGISTERS:
            self._refresh_inputs(start_address, registers)
            return None
        if set_values is None:
            return None  # a holding-register read returns what was stored
        written = {address + i: int(value) for i, value in enumerate(set_values)}
        command_address = self.profile.command.address
        if command_address in written and written[command_address] not in self._command_codes:
            return ExcCodes.ILLEGAL_VALUE
        # Store first, so that a move in the same request as its targets sees them.
        for register_address, value in written.items():
            registers[register_address - start_address] = value
        self._apply_side_effects(written, lambda a: registers[a - start_address])
        return None

    def _apply_side_effects(self, written: dict[int, int], stored: Callable[[int], int]) -> None:
        profile = self.profile
        if profile.watchdog is not None and profile.watchdog.address in written:
            self.stage.set_watchdog(written[profile.watchdog.address] / 1000.0)
        simulation = profile.simulation
        if simulation is not None:
            if simulation.inject_alarm_on_move in written:
                code = written.get(simulation.inject_alarm_on_move + 1) or ALARM_INJECTED
                self.stage.inject_alarm_on_move(written[simulation.inject_alarm_on_move], code)
            if written.get(simulation.inject_alarm_now):
                self.stage.inject_alarm_now(written[simulation.inject_alarm_now])
            if simulation.stop_answering_ms in written:
                self._silent_until = time.monotonic() + written[simulation.stop_answering_ms] / 1000.0
        if profile.command.address in written:
            self._run_command(written[profile.command.address], stored)

    def _run_command(self, code: int, stored: Callable[[int], int]) -> None:
        commands = self.profile.command
        if code == commands.move:
            self.stage.move(self._stored_target(stored))
        elif code == commands.stop:
            self.stage.stop()
        elif code == commands.home:
            self.stage.home()
        elif code == commands.reset_alarm:
            self.stage.reset_alarm()

    def _stored_target(self, stored: Callable[[int], int]) -> Pose:
        """The pose in the target registers."""
        word_order = self.profile.device.word_order
        values = []
        for axis in AXES:
            spec = self.profile.axes[axis]
            counts = decode_int32([stored(spec.target), stored(spec.target + 1)], word_order)
            values.append(spec.from_counts(counts))
        return Pose(*values)

    def _refresh_inputs(self, start_address: int, registers: list[int]) -> None:
        profile = self.profile
        stage = self.stage
        alarm_code = stage.alarm_code
        flags = {
            profile.status.moving: stage.moving,
            profile.status.in_position: stage.in_position,
            profile.status.alarm: alarm_code != 0,
            profile.status.homed: stage.homed,
            profile.status.servo_on: stage.servo_on,
        }
        image = {
            profile.status.address: sum(1 << bit for bit, on in flags.items() if on),
            profile.alarm.address: alarm_code,
        }
        pose = stage.readback_pose()
        for axis in AXES:
            spec = profile.axes[axis]
            first, second = encode_int32(spec.to_counts(getattr(pose, axis)), profile.device.word_order)
            image[spec.actual] = first
            image[spec.actual + 1] = second
        for register_address, value in image.items():
            registers[register_address - start_address] = value

    def _build_device(self) -> SimDevice:
        profile = self.profile
        word_order = profile.device.word_order
        target = self.stage.target
        holding = [
            SimData(
                spec.target,
                values=encode_int32(spec.to_counts(getattr(target, axis)), word_order),
                datatype=DataType.REGISTERS,
            )
            for axis, spec in profile.axes.items()
        ]
        holding.append(SimData(profile.command.address, values=0, datatype=DataType.REGISTERS))
        if profile.watchdog is not None:
            holding.append(SimData(profile.watchdog.address, values=0, datatype=DataType.REGISTERS))
        if profile.simulation is not None:
            simulation = profile.simulation
            holding += [
                SimData(simulation.inject_alarm_on_move, count=2, values=0, datatype=DataType.REGISTERS),
                SimData(simulation.inject_alarm_now, values=0, datatype=DataType.REGISTERS),
                SimData(simulation.stop_answering_ms, values=0, datatype=DataType.REGISTERS),
            ]
        inputs = [
            SimData(spec.actual, count=2, values=0, datatype=DataType.REGISTERS) for spec in profile.axes.values()
        ]
        inputs.append(SimData(profile.status.address, values=0, datatype=DataType.REGISTERS))
        inputs.append(SimData(profile.alarm.address, values=0, datatype=DataType.REGISTERS))
        # The stage has no coils or discrete inputs; pymodbus wants one of each all the same.
        return SimDevice(
            id=profile.device.unit_id,
            simdata=(
                [SimData(0, values=False, datatype=DataType.BITS)],
                [SimData(0, values=False, datatype=DataType.BITS)],
                holding,
                inputs,
            ),
            action=self._on_access,
        )


def serve(
    port: int = 5020,
    host: str = "127.0.0.1",
    stage_config: StageConfig | None = None,
    profile: ModbusProfile | str | Path = SIM_STAGE_PROFILE,
) -> None:
    """Serve a simulated stage on ``host:port`` until Ctrl-C (``mirrorgonio simulate arm``)."""
    stage = SimulatedStage(stage_config)
    with SimulatedModbusArm(stage, profile, host=host, port=port) as server:
        print(
            f"simulated arm '{server.profile.device.name}' serving Modbus TCP on "
            f"{server.endpoint} (unit {server.profile.device.unit_id}); Ctrl-C stops it",
            file=sys.stderr,
            flush=True,
        )
        try:
            while True:
                time.sleep(0.5)
        except KeyboardInterrupt:
            pass


__all__ = ["SimulatedModbusArm", "decode_int32", "encode_int32", "serve"]
