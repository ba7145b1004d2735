"""The simulated stage as a MELFA-like controller on a pseudo-terminal serial port.

A :class:`SimulatedSerialArm` opens a pty pair, listens on the master side and answers
the computer-link frames described in ``docs/serial-arm.md``; a driver opens the slave
side (:attr:`SimulatedSerialArm.device_path`) with pyserial as it would a real RS-232
port. The frames are parsed here from that description, independently of the driver,
so that a misreading of the protocol on either side shows up as a failing test.

Units on the wire are millimetres and degrees; the stage works in metres and radians.
"""

from __future__ import annotations

import errno
import fcntl
import math
import os
import re
import select
import threading
import tty

from drivers.pose import Pose
from sim_devices.stage import ALARM_INJECTED, SimulatedStage

# Error numbers of this simulated controller, sent as ``QeR<number>``. A real MELFA
# controller has its own numbers (see its manual); these are the project's subset.
ERR_UNKNOWN_COMMAND = "0001"
ERR_BAD_ARGUMENT = "0002"
ERR_UNDEFINED_POSITION = "0003"
ERR_BAD_FRAME = "0004"
ERR_NO_CONTROL = "0005"
ERR_SERVO_OFF = "0006"
ERR_NOT_OPEN = "0007"

ERROR_TEXT = {
    ERR_UNKNOWN_COMMAND: "unknown command",
    ERR_BAD_ARGUMENT: "bad argument",
    ERR_UNDEFINED_POSITION: "position variable not defined",
    ERR_BAD_FRAME: "malformed frame or wrong robot number",
    ERR_NO_CONTROL: "operation rights not taken (CNTLON)",
    ERR_SERVO_OFF: "servo is off (SRVON)",
    ERR_NOT_OPEN: "link not opened (OPEN=)",
}

_NUMBER = r"\s*[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?\s*"
_DEFINE_POSITION = re.compile(
    rf"^EXEC\s*(P[A-Z0-9_]*)\s*=\s*\(({_NUMBER}(?:,{_NUMBER}){{5}})\)"
    r"(?:\s*\(\s*-?\d+\s*,\s*-?\d+\s*\))?\s*$",
    re.IGNORECASE,
)
_MOVE = re.compile(r"^EXEC\s*MOV\s+(P[A-Z0-9_]*)\s*$", re.IGNORECASE)

# What a corrupted line looks like: a framing error's junk bytes, still CR-terminated
# so that the host sees a complete but unreadable reply rather than a timeout.
_GARBLE = b"\xfe\x13Q\x8fo?K\x00#\r"

_SELECT_INTERVAL_S = 0.02


class SimulatedSerialArm:
    """A :class:`SimulatedStage` answering MELFA computer-link frames on a pty.

    Parameters
    ----------
    stage : SimulatedStage
        The motion model behind the protocol.
    robot : int
        The robot number this controller answers to.
    home_variable : str
        Position variable that stands for the stage's home pose: ``EXECMOV <it>`` homes.
    identity : str, optional
        Sent after ``QoK`` in the reply to ``OPEN=``; defaults to the stage's name.

    Attributes
    ----------
    device_path : str
        The slave side of the pty, for the driver to open (set by :meth:`start`).
    frames_received : list of str
        Every frame received, in order, without its terminator.
    bytes_received : int
        Every byte received, complete frames or not.
    garbled_replies : int
        How many replies were replaced by junk (see :meth:`garble_next_reply`).
    """

    def __init__(
        self,
        stage: SimulatedStage,
        *,
        robot: int = 1,
        home_variable: str = "PHOME",
        identity: str | None = None,
    ):
        self.stage = stage
        self.robot = robot
        self.home_variable = home_variable.upper()
        self.identity = identity or stage.config.name
        self.device_path = ""
        self.frames_received: list[str] = []
        self.bytes_received = 0
        self.garbled_replies = 0
        self._positions: dict[str, Pose] = {}
        self._opened = False
        self._control = False
        self._servo = True
        self._silent = False
        self._garble_count = 0
        self._faults_lock = threading.Lock()
        self._master: int | None = None
        self._slave: int | None = None
        self._thread: threading.Thread | None = None
        self._running = threading.Event()
        self._buffer = bytearray()

    # -- life cycle -------------------------------------------------------------------
    def start(self) -> SimulatedSerialArm:
        """Open the pty pair and start answering on its master side."""
        if self._thread is not None:
            return self
        master, slave = os.openpty()
        # Raw on both ends: no echo, no CR->LF translation, no line buffering, so the
        # bytes on the wire are exactly those of the protocol.
        tty.setraw(master)
        tty.setraw(slave)
        fcntl.fcntl(master, fcntl.F_SETFL, fcntl.fcntl(master, fcntl.F_GETFL) | os.O_NONBLOCK)
        self._master, self._slave = master, slave
        # The peer keeps the slave open too: when the driver closes it, the master must
        # not see a hang-up, as a real controller does not when a host disconnects.
        self.device_path = os.ttyname(slave)
        self._running.set()
        self._thread = threading.Thread(target=self._serve, name="serial-peer", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop answering and close the pty pair."""
        self._running.clear()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        for fd in (self._master, self._slave):
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self._master = self._slave = None

    def __enter__(self) -> SimulatedSerialArm:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- fault injection ---------------------------------------------------------------
    def stop_answering(self, silent: bool = True) -> None:
        """Drop every frame without acting on it or answering (a dead controller)."""
        with self._faults_lock:
            self._silent = bool(silent)

    def garble_next_reply(self, count: int = 1) -> None:
        """Replace the next ``count`` replies by junk; the commands still take effect."""
        with self._faults_lock:
            self._garble_count += int(count)

    def inject_alarm_on_move(self, move_number: int, code: int = ALARM_INJECTED) -> None:
        """Latch alarm ``code`` on the stage's ``move_number``-th move (1-based)."""
        self.stage.inject_alarm_on_move(move_number, code)

    # -- serving -----------------------------------------------------------------------
    def _serve(self) -> None:
        while self._running.is_set():
            master = self._master
            if master is None:  # stop() closed the pty while this thread was finishing
                return
            readable, _, _ = select.select([master], [], [], _SELECT_INTERVAL_S)
            self.stage.tick()  # lets the watchdog fire while the host is silent
            if not readable:
                continue
            try:
                chunk = os.read(master, 4096)
            except BlockingIOError:
                continue
            except OSError as exc:
                if exc.errno == errno.EIO:  # no slave open at this instant
                    continue
                raise
            self.bytes_received += len(chunk)
            self._buffer.extend(chunk)
            while b"\r" in self._buffer:
                raw, _, rest = bytes(self._buffer).partition(b"\r")
                self._buffer = bytearray(rest)
                self._handle(raw)

    def _handle(self, raw: bytes) -> None:
        raw = raw.strip(b"\n")  # tolerate a host that ends frames with CR LF
        try:
            frame = raw.decode("ascii")
            readable = True
        except UnicodeDecodeError:
            frame = raw.decode("ascii", errors="replace")
            readable = False
        self.frames_received.append(frame)
        with self._faults_lock:
            if self._silent:
                return
        self.stage.touch()
        reply = self._answer(frame) if readable else self._refuse(ERR_BAD_FRAME)
        with self._faults_lock:
            if self._garble_count > 0:
                self._garble_count -= 1
                self.garbled_replies += 1
                self._write(_GARBLE)
                return
        self._write(reply.encode("ascii", errors="replace") + b"\r")

    def _write(self, data: bytes) -> None:
        """Write all of ``data``; drop the rest if the host has stopped reading."""
        view = memoryview(data)
        while view and self._running.is_set():
            master = self._master
            if master is None:  # stop() closed the pty
                return
            _, writable, _ = select.select([], [master], [], 0.5)
            if not writable:
                return  # the host's input queue is full: a real line would lose it too
            try:
                view = view[os.write(master, view) :]
            except BlockingIOError:
                continue

    # -- the protocol ------------------------------------------------------------------
    def _ok(self, data: str = "") -> str:
        # MELFA answers in lower case ("Qok") while an error is latched.
        return ("Qok" if self.stage.alarm_code else "QoK") + data

    def _refuse(self, number: str) -> str:
        return ("Qer" if self.stage.alarm_code else "QeR") + number

    def _answer(self, frame: str) -> str:
        parts = frame.split(";", 2)
        if len(parts) != 3 or not frame.isprintable():
            return self._refuse(ERR_BAD_FRAME)
        robot, slot, command = (part.strip() for part in parts)
        if not (robot.isdigit() and slot.isdigit()) or int(robot) != self.robot:
            return self._refuse(ERR_BAD_FRAME)
        keyword = command.upper()

        if keyword.startswith("OPEN="):
            if not keyword[len("OPEN=") :].strip():
                return self._refuse(ERR_BAD_ARGUMENT)  # the host must name itself
            self._opened = True
            return self._ok(self.identity.replace(";", ","))
        if not self._opened:
            return self._refuse(ERR_NOT_OPEN)
        if keyword == "CLOSE":
            self._opened = self._control = False
            return self._ok()
        if keyword == "CNTLON":
            self._control = True
            return self._ok()
        if keyword == "CNTLOFF":
            self._control = False
            return self._ok()
        if keyword == "SRVON":
            if not self._control:
                return self._refuse(ERR_NO_CONTROL)
            self._servo = True
            return self._ok()
        if keyword == "SRVOFF":
            if not self._control:
                return self._refuse(ERR_NO_CONTROL)
            self._servo = False
            return self._ok()
        if keyword == "STOP":  # always allowed: stopping must never need rights
            self.stage.stop()
            return self._ok()
        if keyword == "RSTALRM":
            self.stage.reset_alarm()
            return self._ok()
        if keyword == "PPOSF":
            return self._ok(self._pposf())
        if keyword == "STATE":
            return self._ok(self._state())
        if keyword == "ERROR":
            return self._ok(self._error())
        if keyword.startswith("EXEC"):
            return self._execute(command)
        return self._refuse(ERR_UNKNOWN_COMMAND)

    def _execute(self, command: str) -> str:
        """``EXEC<var>=(X,Y,Z,A,B,C)(FL1,FL2)`` and ``EXECMOV <var>``."""
        if not self._control:
            return self._refuse(ERR_NO_CONTROL)
        definition = _DEFINE_POSITION.match(command)
        if definition is not None:
            values = [float(v) for v in definition.group(2).split(",")]
            if not all(math.isfinite(v) for v in values):
                return self._refuse(ERR_BAD_ARGUMENT)
            variable = definition.group(1).upper()
            if variable == self.home_variable:
                return self._refuse(ERR_BAD_ARGUMENT)  # home is taught on the controller
            x, y, z, a, b, c = values
            self._positions[variable] = Pose(
                x / 1000.0, y / 1000.0, z / 1000.0, math.radians(a), math.radians(b), math.radians(c)
            )
            return self._ok()
        move = _MOVE.match(command)
        if move is not None:
            if not self._servo:
                return self._refuse(ERR_SERVO_OFF)
            variable = move.group(1).upper()
            if variable == self.home_variable:
                self.stage.home()
            elif variable in self._positions:
                self.stage.move(self._positions[variable])
            else:
                return self._refuse(ERR_UNDEFINED_POSITION)
            # Accepted; an alarm the move raised shows in the reply's case and in ERROR.
            return self._ok()
        if command.upper().startswith(("EXECMOV", "EXECP")):
            return self._refuse(ERR_BAD_ARGUMENT)
        return self._refuse(ERR_UNKNOWN_COMMAND)

    def _pposf(self) -> str:
        p = self.stage.readback_pose()
        values = (
            ("X", p.x * 1000.0),
            ("Y", p.y * 1000.0),
            ("Z", p.z * 1000.0),
            ("A", math.degrees(p.rx)),
            ("B", math.degrees(p.ry)),
            ("C", math.degrees(p.rz)),
        )
        fields = ";".join(f"{key};{value:.4f}" for key, value in values)
        # MELFA appends the posture flags and more after C; hosts must skip them.
        return fields + ";;7,0;100;0.00;00000000"

    def _state(self) -> str:
        stage = self.stage
        return (
            f"MOVING;{int(stage.moving)};INPOS;{int(stage.in_position)};"
            f"SERVO;{int(self._servo)};HOMED;{int(stage.homed)}"
        )

    def _error(self) -> str:
        code = self.stage.alarm_code
        if not code:
            return "0000"
        text = self.stage.alarm_text.replace(";", ",").replace("\r", " ")
        return f"{code:04X};{text}"


__all__ = [
    "ERROR_TEXT",
    "ERR_BAD_ARGUMENT",
    "ERR_BAD_FRAME",
    "ERR_NOT_OPEN",
    "ERR_NO_CONTROL",
    "ERR_SERVO_OFF",
    "ERR_UNDEFINED_POSITION",
    "ERR_UNKNOWN_COMMAND",
    "SimulatedSerialArm",
]
