"""The catalog's SQLite file: opening and migrating it, its transactions, its clock, new ids,
and the checks of the values the runs and the jobs are given."""

from __future__ import annotations

import contextlib
import json
import math
import os
import secrets
import sqlite3
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from datetime import UTC, datetime
from pathlib import Path
from typing import Self

from acquisition.daemon.catalog.errors import CatalogError, CatalogFullError, CatalogUnavailableError
from acquisition.daemon.catalog.records import format_time
from acquisition.daemon.catalog.schema import MIGRATIONS, SCHEMA_VERSION

#: SQLite's primary result codes of a storage that refused (``sqlite3.Error.sqlite_errorcode & 0xFF``).
_SQLITE_READONLY, _SQLITE_IOERR, _SQLITE_FULL = 8, 10, 13


def _utc_now() -> datetime:
    return datetime.now(UTC)


# --- checks of the values given ---------------------------------------------------------
def to_json(value: dict, what: str) -> str:
    """``value`` as JSON text; a CatalogError naming ``what`` unless it is a dict of plain JSON data."""
    if not isinstance(value, dict):
        raise CatalogError(f"{what} must be a JSON object (a dict), not {type(value).__name__}")
    try:
        return json.dumps(value, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise CatalogError(f"{what} is not plain JSON: {exc}") from None


def check_int(name: str, value: object, lo: int, hi: int | None = None) -> int:
    """``value`` if it is an integer in ``[lo, hi]`` (no upper bound if ``hi`` is None), else a CatalogError."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise CatalogError(f"{name} must be an integer, not {value!r}")
    if value < lo or (hi is not None and value > hi):
        bounds = f">= {lo}" if hi is None else f"in [{lo}, {hi}]"
        raise CatalogError(f"{name} must be {bounds}, not {value}")
    return value


def check_real(name: str, value: object, lo: float, hi: float | None = None) -> float:
    """``value`` as a float if it is a finite number in ``[lo, hi]``, else a CatalogError."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise CatalogError(f"{name} must be a finite number, not {value!r}")
    if value < lo or (hi is not None and value > hi):
        bounds = f">= {lo}" if hi is None else f"in [{lo}, {hi}]"
        raise CatalogError(f"{name} must be {bounds}, not {value}")
    return float(value)


def check_text(name: str, value: object) -> str:
    """``value`` if it is a non-empty one-line string, else a CatalogError."""
    if not isinstance(value, str) or not value.strip() or "\n" in value:
        raise CatalogError(f"{name} must be a non-empty one-line string, not {value!r}")
    return value


class CatalogDatabase:
    """The catalog's SQLite connection, shared by the threads of a process under a lock.

    The runs (:class:`~acquisition.daemon.catalog.runs.RunCatalog`) and the jobs
    (:class:`~acquisition.daemon.catalog.jobs.JobCatalog`) are built on it; see
    :class:`acquisition.daemon.catalog.Catalog` for the parameters and the reasons for one connection.
    """

    def __init__(
        self,
        path: str | Path,
        clock: Callable[[], datetime] = _utc_now,
        *,
        busy_timeout_s: float = 10.0,
    ):
        self.path = str(path)
        self._clock = clock
        self._lock = threading.RLock()
        self._pid = os.getpid()
        busy_timeout_s = check_real("busy_timeout_s", busy_timeout_s, 0.0)
        try:
            conn = sqlite3.connect(self.path, timeout=busy_timeout_s, isolation_level=None, check_same_thread=False)
        except sqlite3.Error as exc:
            raise CatalogError(f"cannot open catalog {self.path}: {exc}") from None
        conn.row_factory = sqlite3.Row
        self._conn: sqlite3.Connection | None = conn
        try:
            conn.execute(f"PRAGMA busy_timeout = {int(busy_timeout_s * 1000)}")
            mode = conn.execute("PRAGMA journal_mode = WAL").fetchone()[0]
            if mode.lower() not in ("wal", "memory"):
                raise CatalogError(f"cannot open catalog {self.path}: journal mode is {mode}, not wal")
            conn.execute("PRAGMA foreign_keys = ON")
            self._migrate()
        except sqlite3.Error as exc:
            conn.close()
            self._conn = None
            raise CatalogError(f"cannot open catalog {self.path}: {exc}") from None
        except BaseException:
            conn.close()
            self._conn = None
            raise

    # --- plumbing ------------------------------------------------------------------
    def __repr__(self) -> str:
        return f"Catalog({self.path!r})"

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Close the connection; the catalog cannot be used afterwards. Idempotent."""
        with self._lock:
            if self._conn is not None and os.getpid() == self._pid:
                self._conn.close()
            self._conn = None

    def _connection(self) -> sqlite3.Connection:
        if os.getpid() != self._pid:
            raise CatalogError(
                f"catalog {self.path} was opened in process {self._pid}: open a new Catalog in process {os.getpid()}"
            )
        if self._conn is None:
            raise CatalogError(f"catalog {self.path} is closed")
        return self._conn

    @contextmanager
    def _read(self) -> Iterator[sqlite3.Connection]:
        with self._lock:
            conn = self._connection()
            try:
                yield conn
            except sqlite3.DatabaseError as exc:
                raise self._storage_error(exc, "reading") from None

    @contextmanager
    def _write(self) -> Iterator[sqlite3.Connection]:
        """One write transaction, holding SQLite's write lock from its start."""
        with self._lock:
            conn = self._connection()
            try:
                conn.execute("BEGIN IMMEDIATE")
                try:
                    yield conn
                except BaseException:
                    if conn.in_transaction:  # SQLite may already have rolled back (disk full, I/O error)
                        with contextlib.suppress(sqlite3.Error):
                            conn.execute("ROLLBACK")
                    raise
                conn.execute("COMMIT")
            except sqlite3.DatabaseError as exc:
                if conn.in_transaction:  # a failed COMMIT leaves the transaction open
                    with contextlib.suppress(sqlite3.Error):
                        conn.execute("ROLLBACK")
                raise self._storage_error(exc, "writing") from None

    def _storage_error(self, exc: sqlite3.DatabaseError, doing: str) -> Exception:
        """The one-line catalog error of SQLite's ``exc``: full (507) or unavailable (503);
        ``exc`` itself when it is a bug rather than the storage (a constraint, a bad statement)."""
        if isinstance(exc, sqlite3.IntegrityError | sqlite3.ProgrammingError):
            return exc
        code = (getattr(exc, "sqlite_errorcode", 0) or 0) & 0xFF
        if code == _SQLITE_FULL:
            return CatalogFullError(f"no space left on device {doing} the catalog {self.path}")
        if code == _SQLITE_READONLY:
            return CatalogUnavailableError(f"the catalog {self.path} cannot be written ({exc})")
        if code == _SQLITE_IOERR:
            return CatalogUnavailableError(f"I/O error {doing} the catalog {self.path}")
        return CatalogUnavailableError(f"catalog {self.path}: {doing} failed: {exc}")

    def _now(self) -> datetime:
        now = self._clock()
        if not isinstance(now, datetime) or now.tzinfo is None or now.utcoffset() is None:
            raise CatalogError(f"the catalog's clock must return a timezone-aware datetime, not {now!r}")
        return now.astimezone(UTC)

    def _migrate(self) -> None:
        with self._write() as conn:
            conn.execute(
                "CREATE TABLE IF NOT EXISTS schema_version (version INTEGER PRIMARY KEY, applied_utc TEXT NOT NULL)"
            )
            version = conn.execute("SELECT MAX(version) FROM schema_version").fetchone()[0] or 0
            if version > SCHEMA_VERSION:
                raise CatalogError(
                    f"catalog {self.path} has schema version {version}, newer than this program's {SCHEMA_VERSION}"
                )
            stamp = format_time(self._now())
            for number in range(version + 1, SCHEMA_VERSION + 1):
                for statement in MIGRATIONS[number - 1]:
                    conn.execute(statement)
                conn.execute("INSERT INTO schema_version (version, applied_utc) VALUES (?, ?)", (number, stamp))

    @staticmethod
    def _new_id(conn: sqlite3.Connection, table: str, prefix: str, now: datetime) -> str:
        while True:
            candidate = f"{prefix}-{now:%Y%m%d-%H%M%S}-{secrets.token_hex(2)}"
            if conn.execute(f"SELECT 1 FROM {table} WHERE id = ?", (candidate,)).fetchone() is None:
                return candidate

    @staticmethod
    def _next_seq(conn: sqlite3.Connection, table: str) -> int:
        return conn.execute(f"SELECT COALESCE(MAX(seq), 0) + 1 FROM {table}").fetchone()[0]
