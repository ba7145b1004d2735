"""An arm behind a Mitsubishi MELFA controller, over RS-232 with the computer-link protocol.

The controller is driven with the ASCII request/reply protocol of MELFA controllers
(the "R3 protocol" or computer link): every request is one frame
``<robot>;<slot>;<COMMAND>`` terminated by CR, and every reply is one CR-terminated
line that starts with ``QoK`` (success, data follows) or ``QeR`` (refused, an error
number follows). The commands, the replies this driver parses and the line settings are
listed in ``docs/serial-arm.md``.

The session commands (``OPEN``, ``CNTLON``, ``SRVON``, ``EXEC``, ``PPOSF``, ``STOP``,
``RSTALRM``...) follow MELFA's computer link. The replies of the status query
(``STATE``) and the error query (``ERROR``) differ between controller generations; this
driver parses a documented subset of them (see :func:`parse_state` and
:func:`parse_error`), which the simulated peer in ``sim_devices.serial_peer`` speaks.
A real controller whose replies differ needs only those two parsers adapted.

Units on the wire are millimetres and degrees; :class:`~drivers.pose.Pose` is metres and
radians with the same fixed-axis X-Y-Z (A, B, C) angle convention, so only the scale
changes.
"""

from __future__ import annotations

import math
import re
import threading
import time
from collections.abc import Callable
from typing import TypeVar, overload

import serial

from drivers.arm import Arm, ArmStatus, SoftLimits
from drivers.errors import CommunicationError, DeviceError, DeviceTimeoutError, LimitsError
from drivers.pose import AXES, Pose

TERMINATOR = b"\r"

#: Slot used for commands that act on the robot (session, motion, reset).
COMMAND_SLOT = 1
#: Slot used for the read-only monitor queries (position, error number).
MONITOR_SLOT = 9

_PARITIES = {
    "N": serial.PARITY_NONE,
    "E": serial.PARITY_EVEN,
    "O": serial.PARITY_ODD,
    "M": serial.PARITY_MARK,
    "S": serial.PARITY_SPACE,
}

# Longest excerpt of a bad reply quoted in an error message: enough to recognise it,
# short enough to keep the message on one readable line.
_QUOTE_LIMIT = 80

_ParsedT = TypeVar("_ParsedT")


def _quote(raw: bytes | str) -> str:
    """A reply as a one-line, printable, bounded excerpt for error messages."""
    text = repr(raw[:_QUOTE_LIMIT])
    return text + ("..." if len(raw) > _QUOTE_LIMIT else "")


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


def key_value_fields(data: str) -> dict[str, str]:
    """Fields of a ``KEY;value;KEY;value...`` reply, keys upper-cased.

    A token is a key when it starts with a letter and is followed by another token;
    empty tokens and trailing fields that are not pairs (MELFA appends structure flags
    and other data after the C angle of ``PPOSF``) are skipped. The first occurrence
    of a key wins.
    """
    tokens = [token.strip() for token in data.split(";")]
    fields: dict[str, str] = {}
    i = 0
    while i < len(tokens) - 1:
        key = tokens[i].upper()
        if key[:1].isalpha() and key not in fields:
            fields[key] = tokens[i + 1]
            i += 2
        else:
            i += 1
    return fields


def parse_pposf(data: str) -> Pose:
    """The current position from the data of a ``PPOSF`` reply.

    Parameters
    ----------
    data : str
        What follows ``QoK``, e.g. ``X;123.45;Y;-6.7;Z;300.0;A;180.0;B;0.0;C;90.0;;7,0``:
        millimetres for X, Y, Z and degrees for A, B, C; extra fields are ignored.

    Returns
    -------
    Pose
        In metres and radians.

    Raises
    ------
    ValueError
        If a coordinate is missing or not a number.
    """
    fields = key_value_fields(data)
    values = []
    for key in ("X", "Y", "Z", "A", "B", "C"):
        if key not in fields:
            raise ValueError(f"no {key} field")
        value = float(fields[key])
        if not math.isfinite(value):
            raise ValueError(f"{key}={fields[key]} is not a finite number")
        values.append(value)
    x, y, z, a, b, c = values
    return Pose(x / 1000.0, y / 1000.0, z / 1000.0, math.radians(a), math.radians(b), math.radians(c))


def parse_state(data: str) -> dict[str, bool]:
    """The motion flags from the data of this driver's ``STATE`` reply.

    The documented subset is ``MOVING;<0|1>;INPOS;<0|1>[;SERVO;<0|1>][;HOMED;<0|1>]``
    with further fields ignored. ``MOVING`` and ``INPOS`` are required; ``SERVO`` and
    ``HOMED`` default to 1 (a MELFA arm has absolute encoders and needs no homing).

    Raises
    ------
    ValueError
        If a required flag is missing or a flag is not ``0`` or ``1``.
    """
    fields = key_value_fields(data)
    flags = {}
    for key, default in (("MOVING", None), ("INPOS", None), ("SERVO", "1"), ("HOMED", "1")):
        value = fields.get(key, default)
        if value is None:
            raise ValueError(f"no {key} field")
        if value not in ("0", "1"):
            raise ValueError(f"{key}={value!r} is not 0 or 1")
        flags[key] = value == "1"
    return flags


_ERROR_REPLY = re.compile(r"^\s*([A-Za-z]?)([0-9A-Fa-f]{1,8})\s*(?:;(.*))?$", re.DOTALL)


def parse_error(data: str) -> tuple[int, str]:
    """The latched error from the data of an ``ERROR`` reply.

    The documented subset is ``[level]<digits>[;<text>]``: an optional MELFA level
    letter (H, L, C), the error number as up to eight digits, and an optional text.
    The digits are read as hexadecimal so that :class:`~drivers.errors.AlarmError`,
    which prints codes in hex, shows them digit for digit (error 3810 -> ``0x3810``).
    ``0`` means no error.

    Returns
    -------
    code : int
        0 when the controller has no error.
    text : str
        The controller's text, or a description built from the number.

    Raises
    ------
    ValueError
        If the data is not an error number.
    """
    match = _ERROR_REPLY.match(data)
    if match is None:
        raise ValueError("not an error number")
    level, digits, text = match.group(1), match.group(2), (match.group(3) or "").strip()
    code = int(digits, 16)
    if code == 0:
        return 0, ""
    label = f"controller error {level.upper()}{digits}"
    return code, f"{label}: {text}" if text else label


class MelfaSerialArm(Arm):
    """A MELFA robot controller on a serial port, speaking the computer-link protocol.

    Each request waits for its reply under a lock, so :meth:`stop` may be called from
    another thread while :meth:`move_to` polls the status.

    Parameters
    ----------
    port : str
        Serial device, e.g. ``/dev/ttyUSB0`` or ``COM3``.
    baudrate, bytesize, parity, stopbits
        Line settings; they must match the controller's RS-232 parameters. The default
        9600 baud, 8 data bits, even parity, 2 stop bits is MELFA's factory setting.
        ``parity`` is one of ``"N"``, ``"E"``, ``"O"``, ``"M"``, ``"S"``.
    rtscts, xonxoff : bool
        Hardware or software flow control; off by default.
    timeout_s : float
        How long to wait for one reply (also the write timeout).
    retries : int
        Extra attempts after a reply that timed out or came back garbled. Every command
        this driver sends is idempotent (re-sending a move re-targets the same pose),
        so repeating one is safe.
    robot : int
        Robot number, the first field of every frame.
    limits : SoftLimits, optional
        Checked before any byte of a move is sent.
    name : str, optional
        Device name in error messages; defaults to ``"MELFA arm on <port>"``.
    poll_interval_s : float
        Pause between status reads while waiting for a move.
    sleep, clock : callable
        Injected for tests and simulations.
    client_name : str
        Sent with ``OPEN=`` to identify this host to the controller.
    position_variable : str
        Controller position variable that receives each move target.
    home_position : str
        Controller position variable taught as the rig's home pose; :meth:`home` moves
        there (a MELFA arm has absolute encoders, so homing is a move).
    structure_flags : tuple of int
        MELFA's (FL1, FL2) posture flags sent with every target; 7 is RIGHT, ABOVE,
        NONFLIP, the usual posture of a vertical six-axis arm.
    """

    def __init__(
        self,
        port: str,
        *,
        baudrate: int = 9600,
        bytesize: int = 8,
        parity: str = "E",
        stopbits: float = 2,
        rtscts: bool = False,
        xonxoff: bool = False,
        timeout_s: float = 1.0,
        retries: int = 2,
        robot: int = 1,
        limits: SoftLimits | None = None,
        name: str | None = None,
        poll_interval_s: float = 0.02,
        sleep: Callable[[float], None] = time.sleep,
        clock: Callable[[], float] = time.monotonic,
        client_name: str = "mirrorgonio",
        position_variable: str = "P1",
        home_position: str = "PHOME",
        structure_flags: tuple[int, int] = (7, 0),
    ):
        super().__init__(
            name or f"MELFA arm on {port}",
            limits=limits,
            poll_interval_s=poll_interval_s,
            sleep=sleep,
            clock=clock,
        )
        parity_key = str(parity).upper()[:1]
        if parity_key not in _PARITIES:
            raise ValueError(f"parity must be one of {sorted(_PARITIES)}, not {parity!r}")
        if retries < 0:
            raise ValueError(f"retries must be >= 0, not {retries}")
        self.port = port
        self.baudrate = int(baudrate)
        self.bytesize = int(bytesize)
        self.parity = parity_key
        self.stopbits = stopbits
        self.rtscts = rtscts
        self.xonxoff = xonxoff
        self.timeout_s = float(timeout_s)
        self.retries = int(retries)
        self.robot = int(robot)
        self.client_name = client_name
        self.position_variable = position_variable
        self.home_position = home_position
        self.structure_flags = structure_flags
        self.controller_reply = ""
        self._serial: serial.Serial | None = None
        self._lock = threading.Lock()

    # -- life cycle -------------------------------------------------------------------
    def connect(self) -> None:
        """Open the port, then open the link, take control and switch the servos on.

        Raises
        ------
        CommunicationError
            If the port cannot be opened (the message names it) or a reply is garbled.
        DeviceTimeoutError
            If the controller does not answer.
        DeviceError
            If the controller refuses a command.
        """
        if self._serial is not None:
            return
        try:
            port = serial.Serial(
                self.port,
                baudrate=self.baudrate,
                bytesize=self.bytesize,
                parity=_PARITIES[self.parity],
                stopbits=self.stopbits,
                timeout=self.timeout_s,
                write_timeout=self.timeout_s,
                rtscts=self.rtscts,
                xonxoff=self.xonxoff,
                exclusive=True,  # a second host talking on the same line corrupts both
            )
        except (serial.SerialException, OSError, ValueError) as exc:
            raise CommunicationError(
                self.name, "connect", f"cannot open serial port {self.port}: {_one_line(exc)}"
            ) from exc
        self._serial = port
        try:
            self.controller_reply = self._request(f"OPEN={self.client_name}", "connect")
            self._request("CNTLON", "connect")
            self._request("SRVON", "connect")
        except BaseException:
            self._close_port()
            raise

    def close(self) -> None:
        """Switch the servos off, release control, close the link and the port.

        Best effort: a refused command does not prevent the next ones, a dead link
        stops the sequence, and the port is closed in every case.
        """
        if self._serial is None:
            return
        try:
            for command in ("SRVOFF", "CNTLOFF", "CLOSE"):
                try:
                    self._request(command, "close", retries=0)
                except (DeviceTimeoutError, CommunicationError):
                    break  # the link is gone: the remaining commands would time out too
                except DeviceError:
                    continue
        finally:
            self._close_port()

    @property
    def connected(self) -> bool:
        return self._serial is not None

    @property
    def identity(self) -> str:
        line = f"{self.baudrate} {self.bytesize}{self.parity}{self.stopbits:g}"
        text = f"{self.name} (MELFA computer link, robot {self.robot}, {self.port} {line})"
        if self.controller_reply:
            text += f", controller: {self.controller_reply}"
        return text

    # -- Arm primitives ----------------------------------------------------------------
    def _start_move(self, pose: Pose) -> None:
        for axis in AXES:
            value = getattr(pose, axis)
            if not math.isfinite(value):
                raise LimitsError(self.name, "move_to", f"{axis}={value} is not a finite number")
        fl1, fl2 = self.structure_flags
        coordinates = (
            pose.x * 1000.0,
            pose.y * 1000.0,
            pose.z * 1000.0,
            math.degrees(pose.rx),
            math.degrees(pose.ry),
            math.degrees(pose.rz),
        )
        # 0.1 µm and 0.0001° are far below the arm's repeatability, so nothing is lost.
        numbers = ",".join(f"{value:.4f}" for value in coordinates)
        self._request(f"EXEC{self.position_variable}=({numbers})({fl1},{fl2})", "move_to")
        self._request(f"EXECMOV {self.position_variable}", "move_to")

    def _start_home(self) -> None:
        self._request(f"EXECMOV {self.home_position}", "home")

    def position(self) -> Pose:
        """The position the controller reads back (``PPOSF``), in metres and radians."""
        return self._request("PPOSF", "position", slot=MONITOR_SLOT, parse=parse_pposf)

    def status(self) -> ArmStatus:
        """Motion flags from ``STATE`` and the latched error from ``ERROR``."""
        flags = self._request("STATE", "status", parse=parse_state)
        code, text = self._request("ERROR", "status", slot=MONITOR_SLOT, parse=parse_error)
        return ArmStatus(
            moving=flags["MOVING"],
            in_position=flags["INPOS"],
            alarm_code=code,
            alarm_text=text,
            homed=flags["HOMED"],
            servo_on=flags["SERVO"],
        )

    def stop(self) -> None:
        """Stop the arm where it is (``STOP``)."""
        self._request("STOP", "stop")

    def reset_alarm(self) -> None:
        """Clear the controller's latched error (``RSTALRM``)."""
        self._request("RSTALRM", "reset_alarm")

    def send_command(self, command: str, *, slot: int = COMMAND_SLOT) -> str:
        """Send one raw command and return the data after ``QoK``.

        For maintenance and diagnostics; the robot number and the terminator are added.

        Raises
        ------
        DeviceError
            If the controller answers ``QeR``; the message names the error number.
        """
        return self._request(command, "send_command", slot=slot)

    # -- the exchange ------------------------------------------------------------------
    @overload
    def _request(
        self, command: str, operation: str, *, slot: int = ..., retries: int | None = ..., parse: None = None
    ) -> str: ...

    @overload
    def _request(
        self,
        command: str,
        operation: str,
        *,
        slot: int = ...,
        retries: int | None = ...,
        parse: Callable[[str], _ParsedT],
    ) -> _ParsedT: ...

    def _request(
        self,
        command: str,
        operation: str,
        *,
        slot: int = COMMAND_SLOT,
        retries: int | None = None,
        parse: Callable[[str], _ParsedT] | None = None,
    ) -> str | _ParsedT:
        """Send one frame, read its reply and return its data (parsed if asked).

        A reply that times out or is garbled (including data that ``parse`` rejects) is
        retried; a ``QeR`` refusal is an answer and is not.
        """
        frame = f"{self.robot};{slot};{command}"
        where = f"{operation} [{frame}]"
        attempts = 1 + (self.retries if retries is None else retries)
        with self._lock:
            if self._serial is None:
                raise CommunicationError(self.name, where, "not connected (call connect() first)")
            failure: DeviceError | None = None
            for _ in range(attempts):
                raw = self._exchange(frame, where)
                if raw is None:
                    failure = DeviceTimeoutError(
                        self.name,
                        where,
                        f"no reply within {self.timeout_s:g} s after {attempts} attempt(s)",
                    )
                    continue
                try:
                    data = self._decode_reply(raw, where)
                    if parse is None:
                        return data
                    try:
                        return parse(data)
                    except ValueError as exc:
                        raise CommunicationError(self.name, where, f"unexpected reply {_quote(raw)}: {exc}") from exc
                except CommunicationError as garbled:
                    failure = garbled
            assert failure is not None  # attempts >= 1, so the loop has set it
            raise failure

    def _exchange(self, frame: str, where: str) -> bytes | None:
        """Write ``frame`` and read one CR-terminated reply; None on a timeout."""
        port = self._serial
        assert port is not None  # _request holds the lock and has checked it
        try:
            # A late reply to an earlier, timed-out request must not be taken for this one.
            port.reset_input_buffer()
            port.write(frame.encode("ascii") + TERMINATOR)
            port.flush()
            raw = port.read_until(TERMINATOR)
        except serial.SerialTimeoutException:
            return None
        except (serial.SerialException, OSError) as exc:
            raise CommunicationError(self.name, where, f"serial port {self.port} failed: {_one_line(exc)}") from exc
        if not raw.endswith(TERMINATOR):
            return None
        return raw

    def _decode_reply(self, raw: bytes, where: str) -> str:
        """The data of a ``QoK`` reply; DeviceError for ``QeR``; CommunicationError else."""
        try:
            text = raw[: -len(TERMINATOR)].decode("ascii")
        except UnicodeDecodeError as exc:
            raise CommunicationError(self.name, where, f"garbled reply {_quote(raw)}") from exc
        text = text.lstrip("\n")  # tolerate a controller set to CR LF line ends
        if not text.isprintable():
            raise CommunicationError(self.name, where, f"garbled reply {_quote(raw)}")
        # Lower-case "Qok" / "Qer" is how MELFA marks a reply sent while an error is
        # latched; the error itself is read with the ERROR query, so both are accepted.
        if text[:3] in ("QoK", "Qok"):
            return text[3:]
        if text[:2] == "Qe":
            body = text[2:]
            if body[:1] in ("R", "r"):
                body = body[1:]
            code = body.strip() or "(no number)"
            raise DeviceError(self.name, where, f"controller refused the command: error {code}")
        raise CommunicationError(self.name, where, f"garbled reply {_quote(raw)}")

    def _close_port(self) -> None:
        with self._lock:  # never pull the port from under an exchange in another thread
            port, self._serial = self._serial, None
        if port is not None:
            try:
                port.close()
            except (serial.SerialException, OSError):
                pass  # closing a port whose device vanished must not hide the real error


__all__ = [
    "COMMAND_SLOT",
    "MONITOR_SLOT",
    "MelfaSerialArm",
    "key_value_fields",
    "parse_error",
    "parse_pposf",
    "parse_state",
]
