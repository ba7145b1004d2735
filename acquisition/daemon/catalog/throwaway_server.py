"""A throwaway PostgreSQL server in a temporary folder, for the tests and the lab benchmark.

It runs the machine's own PostgreSQL programs (Debian's ``postgresql`` package puts them in
``/usr/lib/postgresql/VERSION/bin``), on a free port of the loopback address, trusting local
connections, and is deleted with its folder when stopped. PostgreSQL refuses to run as root:
as root, the server runs as the ``postgres`` user the package creates.
"""

from __future__ import annotations

import glob
import os
import pwd
import shutil
import socket
import subprocess
import tempfile
from pathlib import Path
from typing import Self

import psycopg

#: Settings that trade durability for speed; the tests' clusters use them, the benchmark does not.
FAST_SETTINGS = ("fsync=off", "full_page_writes=off", "synchronous_commit=off")


class PostgresNotFoundError(RuntimeError):
    """The PostgreSQL server programs are not installed."""


def find_postgres_bin() -> Path:
    """The folder of ``initdb`` and ``pg_ctl``: on the PATH, else Debian's newest version.

    Raises
    ------
    PostgresNotFoundError
        Neither is there (``apt-get install postgresql``).
    """
    initdb = shutil.which("initdb")
    if initdb is not None:
        return Path(initdb).resolve().parent
    versions = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"), key=lambda p: int(Path(p).parts[-3]))
    if versions:
        return Path(versions[-1]).parent
    raise PostgresNotFoundError("PostgreSQL's initdb is not installed (apt-get install postgresql)")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class ThrowawayPostgres:
    """A PostgreSQL server of its own, in a temporary folder, until :meth:`stop`.

    Parameters
    ----------
    fast : bool
        Run without fsync (tests); False for a server that behaves as a lab's would.
    listen : str
        The addresses it listens on (PostgreSQL's ``listen_addresses``; ``*`` for all).
    trusted : list of str
        Networks (CIDR) besides the loopback whose connections it trusts.
    """

    def __init__(self, *, fast: bool = True, listen: str = "127.0.0.1", trusted: tuple[str, ...] | list[str] = ()):
        self.bin = find_postgres_bin()
        self.folder = Path(tempfile.mkdtemp(prefix="mirrorgonio-pg-"))
        self.data = self.folder / "data"
        self.log = self.folder / "server.log"
        self.port = _free_port()
        self._settings = FAST_SETTINGS if fast else ()
        self._listen = listen
        self._user = None
        if os.geteuid() == 0:
            try:
                self._user = pwd.getpwnam("postgres")
            except KeyError:
                raise PostgresNotFoundError(
                    "running as root needs the 'postgres' user (apt-get install postgresql)"
                ) from None
            os.chown(self.folder, self._user.pw_uid, self._user.pw_gid)
        self._run("initdb", "-D", str(self.data), "-U", "postgres", "--auth=trust", "--no-sync", "-E", "UTF8")
        with (self.data / "pg_hba.conf").open("a") as hba:
            for network in trusted:
                hba.write(f"host all all {network} trust\n")
        self.start()

    def _run(self, program: str, *args: str) -> None:
        command = [str(self.bin / program), *args]
        if self._user is not None:
            command = ["runuser", "-u", "postgres", "--", *command]
        done = subprocess.run(command, capture_output=True, text=True, check=False, cwd=self.folder)
        if done.returncode != 0:
            log = self.log.read_text(errors="replace")[-2000:] if self.log.exists() else ""
            raise RuntimeError(f"{program} {' '.join(args[:2])} failed: {done.stderr.strip()}\n{log}")

    def start(self) -> None:
        """Start the server (again) on its port; waits until it takes connections."""
        options = " ".join(
            [f"-p {self.port}", f"-c listen_addresses='{self._listen}'", f"-k {self.folder}"]
            + [f"-c {setting}" for setting in self._settings]
        )
        self._run("pg_ctl", "-D", str(self.data), "-l", str(self.log), "-w", "-t", "60", "-o", options, "start")

    def stop(self, mode: str = "fast") -> None:
        """Stop the server (``fast``: its connections are closed; ``immediate``: as if it crashed)."""
        self._run("pg_ctl", "-D", str(self.data), "-w", "-m", mode, "stop")

    def restart(self) -> None:
        """Stop and start the server: every connection to it breaks."""
        self.stop()
        self.start()

    def url(self, database: str = "postgres") -> str:
        return f"postgresql://postgres@127.0.0.1:{self.port}/{database}"

    def create_database(self, name: str) -> str:
        """A new empty database; its URL."""
        with psycopg.connect(self.url(), autocommit=True) as conn:
            conn.execute(f'CREATE DATABASE "{name}"')
        return self.url(name)

    def close(self) -> None:
        """Stop the server and delete its folder."""
        try:
            if (self.data / "postmaster.pid").exists():
                self.stop("immediate")
        finally:
            shutil.rmtree(self.folder, ignore_errors=True)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
