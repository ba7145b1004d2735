"""The catalog's database: opening and migrating it, its transactions, its clock, new ids,
and the checks of the values the runs and the jobs are given."""

from __future__ import annotations

import json
import math
import os
import re
import secrets
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from datetime import UTC, datetime
from pathlib import Path
from typing import Self

from acquisition.daemon.catalog.backends import Backend, Connection, Dialects, open_backend
from acquisition.daemon.catalog.errors import CatalogError, CatalogFullError, CatalogUnavailableError
from acquisition.daemon.catalog.records import format_time
from acquisition.daemon.catalog.schema import DEFAULT_RIG, MIGRATIONS, SCHEMA_VERSION

#: A rig's name: lowercase letters, digits, ``-``, ``_`` and ``.``, at most 63 characters.
RIG_NAME_PATTERN = r"^[a-z0-9][a-z0-9_.-]{0,62}$"
_RIG_NAME = re.compile(RIG_NAME_PATTERN)


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


def check_rig(rig: object) -> str:
    """``rig`` if it is a rig's name (lowercase letters, digits, ``-``, ``_``, ``.``; at most 63
    characters), else a CatalogError."""
    if not isinstance(rig, str) or not _RIG_NAME.fullmatch(rig):
        raise CatalogError(
            f"rig {rig!r} is not a rig's name (lowercase letters, digits, '-', '_' and '.', at most 63, "
            "starting with a letter or digit)"
        )
    return rig


class CatalogDatabase:
    """The catalog's database connection, shared by the threads of a process under a lock.

    The runs (:class:`~acquisition.daemon.catalog.runs.RunCatalog`) and the jobs
    (:class:`~acquisition.daemon.catalog.jobs.JobCatalog`) are built on it; see
    :class:`acquisition.daemon.catalog.Catalog` for the parameters and the reasons for one connection.
    """

    def __init__(
        self,
        location: str | Path,
        clock: Callable[[], datetime] = _utc_now,
        *,
        rig: str = DEFAULT_RIG,
        busy_timeout_s: float = 10.0,
    ):
        self.rig = check_rig(rig)
        self._clock = clock
        self._lock = threading.RLock()
        self._pid = os.getpid()
        busy_timeout_s = check_real("busy_timeout_s", busy_timeout_s, 0.0)
        self._backend: Backend | None = open_backend(location, busy_timeout_s)
        self.path = self._backend.where
        try:
            self._migrate()
        except (CatalogFullError, CatalogUnavailableError) as exc:
            self._backend.close()
            self._backend = None
            raise CatalogError(f"cannot open catalog {self.path}: {exc}") from None
        except BaseException:
            self._backend.close()
            self._backend = None
            raise

    # --- plumbing ------------------------------------------------------------------
    def __repr__(self) -> str:
        return f"Catalog({self.path!r}, rig={self.rig!r})"

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def dialect(self) -> str:
        """``"sqlite"`` or ``"postgresql"``."""
        return self._open_backend().dialect

    def close(self) -> None:
        """Close the connection; the catalog cannot be used afterwards. Idempotent."""
        with self._lock:
            if self._backend is not None and os.getpid() == self._pid:
                self._backend.close()
            self._backend = None

    def _open_backend(self) -> Backend:
        if os.getpid() != self._pid:
            raise CatalogError(
                f"catalog {self.path} was opened in process {self._pid}: open a new Catalog in process {os.getpid()}"
            )
        if self._backend is None:
            raise CatalogError(f"catalog {self.path} is closed")
        return self._backend

    @contextmanager
    def _read(self) -> Iterator[Connection]:
        with self._transaction(write=False) as conn:
            yield conn

    @contextmanager
    def _write(self, *serialised: str) -> Iterator[Connection]:
        """One write transaction; where the backend does not serialise every write, the
        ``serialised`` keys are held to its end (writes naming one key never interleave)."""
        with self._transaction(write=True, serialised=serialised) as conn:
            yield conn

    @contextmanager
    def _transaction(self, *, write: bool, serialised: tuple[str, ...] = ()) -> Iterator[Connection]:
        doing = "writing" if write else "reading"
        with self._lock:
            backend = self._open_backend()
            conn: Connection | None = None
            try:
                conn = backend.begin(write=write)
                try:
                    for key in serialised:
                        backend.serialise(conn, key)
                    yield conn
                except BaseException:
                    backend.rollback()
                    raise
                backend.commit(conn, write=write)
            except Exception as exc:
                mapped = backend.storage_error(exc, doing)
                if mapped is None:
                    raise
                if conn is not None:
                    backend.rollback()  # a failed COMMIT leaves the transaction open
                if mapped is exc:
                    raise
                raise mapped from None

    def _now(self) -> datetime:
        now = self._clock()
        if not isinstance(now, datetime) or now.tzinfo is None or now.utcoffset() is None:
            raise CatalogError(f"the catalog's clock must return a timezone-aware datetime, not {now!r}")
        return now.astimezone(UTC)

    def _migrate(self) -> None:
        with self._write("migrate") as conn:
            dialect = self.dialect
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
                    text = getattr(statement, dialect) if isinstance(statement, Dialects) else statement
                    if text is not None:
                        conn.execute(text)
                conn.execute("INSERT INTO schema_version (version, applied_utc) VALUES (?, ?)", (number, stamp))

    def _new_id(self, conn: Connection, table: str, prefix: str, now: datetime) -> str:
        """A new row's id, free in ``table``; the write that inserts it holds the table's id key
        to its end, so that two processes cannot pick the same one (SQLite serialises every write)."""
        self._open_backend().serialise(conn, f"ids:{table}")
        while True:
            candidate = f"{prefix}-{now:%Y%m%d-%H%M%S}-{secrets.token_hex(2)}"
            if conn.execute(f"SELECT 1 FROM {table} WHERE id = ?", (candidate,)).fetchone() is None:
                return candidate

    def _next_seq(self, conn: Connection, table: str) -> int:
        return self._open_backend().next_seq(conn, table)
