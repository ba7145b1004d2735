"""The daemon and the worker as child processes of the demo.

Each is a ``mirrorgonio`` subcommand in its own session (a Ctrl-C in the terminal reaches
only the demo, which stops them in order), logging to a file; on Linux they also get
SIGTERM should the demo die. :meth:`Child.stop` ends one with SIGTERM, then SIGKILL of its
whole process group if it lingers, so that no process is left behind.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path


class DemoError(RuntimeError):
    """The demo could not finish: one line naming the log to read; ``details``, the end of that log."""

    def __init__(self, message: str, details: str = ""):
        super().__init__(message)
        self.details = details


def free_port() -> int:
    """A TCP port on loopback that no program holds now (another may take it before the daemon does)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _parent_death_signal():
    """Linux: a function for the child, between fork and exec, that asks for SIGTERM when the
    demo dies (``prctl(PR_SET_DEATHSIG)``); looked up here, before the fork, so the child
    imports nothing."""
    if sys.platform != "linux":
        return None
    try:
        prctl = ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None

    def set_signal() -> None:  # pragma: no cover - runs in the child
        prctl(1, int(signal.SIGTERM))  # PR_SET_PDEATHSIG

    return set_signal


class Child:
    """A ``mirrorgonio`` subcommand in its own session (its process group is its pid), logging to a file."""

    def __init__(self, name: str, args: list[str], log: Path, env: dict[str, str]):
        self.name, self.log_path = name, log
        exe = Path(sys.executable).with_name("mirrorgonio")
        command = [str(exe)] if exe.exists() else [sys.executable, "-m", "acquisition.cli"]
        self._log = open(log, "ab")  # noqa: SIM115 - closed in stop()
        self.proc = subprocess.Popen(
            command + args,
            stdout=self._log,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            env=env,
            start_new_session=True,
            preexec_fn=_parent_death_signal(),
        )

    @property
    def pid(self) -> int:
        """The child's process id (also its process group's)."""
        return self.proc.pid

    def alive(self) -> bool:
        """Whether the child itself still runs."""
        return self.proc.poll() is None

    def log_tail(self, lines: int = 15) -> str:
        """The last ``lines`` lines of its log ("" when it cannot be read)."""
        try:
            text = self.log_path.read_text(errors="replace").splitlines()
        except OSError:
            return ""
        return "\n".join(text[-lines:])

    def check(self) -> None:
        """Raise :class:`DemoError` (with the end of its log) if the child has exited."""
        if not self.alive():
            raise DemoError(
                f"the {self.name} exited (status {self.proc.returncode}): see its log, {self.log_path}", self.log_tail()
            )

    def _group_alive(self) -> bool:
        """Whether a process of its group still runs (zombies, which only wait to be reaped, do not count)."""
        proc = Path("/proc")
        if not proc.is_dir():
            try:
                os.killpg(self.proc.pid, 0)
                return True
            except (ProcessLookupError, PermissionError):
                return False
        for stat in proc.glob("[0-9]*/stat"):
            try:
                text = stat.read_text()
            except OSError:
                continue
            fields = text[text.rfind(")") + 2 :].split()  # state ppid pgrp ... (the name may hold spaces)
            if len(fields) > 2 and fields[0] != "Z" and fields[2] == str(self.proc.pid):
                return True
        return False

    def stop(self, timeout: float) -> None:
        """SIGTERM and wait; then SIGKILL whatever is left of its process group (Dask workers too)."""
        try:
            if self.alive():
                self.proc.terminate()
                with contextlib.suppress(subprocess.TimeoutExpired):
                    self.proc.wait(timeout)
            # The leader did not stop in time, or left processes of its group behind.
            deadline = time.monotonic() + 10.0
            while (self.alive() or self._group_alive()) and time.monotonic() < deadline:
                with contextlib.suppress(ProcessLookupError, PermissionError):
                    os.killpg(self.proc.pid, signal.SIGKILL)
                with contextlib.suppress(subprocess.TimeoutExpired):
                    self.proc.wait(0.2)
        finally:
            self._log.close()


def child_env(token: str | None = None) -> dict[str, str]:
    """This environment without the user's ``MG_*`` settings (the demo's file says everything)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("MG_")}
    env["PYTHONUNBUFFERED"] = "1"
    if token:
        env["MG_TOKEN"] = token
    return env
