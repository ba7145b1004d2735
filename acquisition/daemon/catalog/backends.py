"""The catalog's two databases: an SQLite file (one machine; the default) and a PostgreSQL
server (a lab: several daemons and workers on several machines).

Both run the same SQL, written with ``?`` placeholders and types both know. Each backend says
how a transaction begins (SQLite takes its write lock at once, so every write is serialised;
PostgreSQL locks rows, and where a check and the change it allows must not interleave, such
as "no other run in progress on this rig", the caller names an advisory lock), how a row gets
its ``seq`` (``MAX(seq) + 1`` under SQLite's write lock; a sequence on PostgreSQL), and which
of its errors mean the storage refused (a one-line 503 or 507) rather than a bug.

A PostgreSQL connection that broke (the server restarted, the network went away) is opened
again at the next operation; the operation under way when it broke fails with a one-line
:class:`~acquisition.daemon.catalog.errors.CatalogUnavailableError`, and nothing it began is
kept (its transaction was never committed).
"""

from __future__ import annotations

import contextlib
import re
import sqlite3
from abc import ABC, abstractmethod
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, cast
from urllib.parse import urlsplit, urlunsplit

import psycopg

from acquisition.daemon.catalog.errors import CatalogError, CatalogFullError, CatalogUnavailableError

#: SQLite's primary result codes of a storage that refused (``sqlite3.Error.sqlite_errorcode & 0xFF``).
_SQLITE_READONLY, _SQLITE_IOERR, _SQLITE_FULL = 8, 10, 13
#: The URL schemes of a PostgreSQL catalog, and of an SQLite one (``sqlite:///relative``,
#: ``sqlite:////absolute``, as SQLAlchemy writes them).
POSTGRESQL_SCHEMES = ("postgresql", "postgres")
SQLITE_PREFIX = "sqlite:///"


class Row(Protocol):
    """A result row, by position or by column name (``sqlite3.Row`` is one)."""

    def __getitem__(self, key: int | str) -> Any: ...


class Cursor(Protocol):
    rowcount: int

    def fetchone(self) -> Any: ...

    def __iter__(self) -> Iterator[Any]: ...


class Connection(Protocol):
    def execute(self, sql: str, params: Any = ..., /) -> Cursor: ...


@dataclass(frozen=True)
class Dialects:
    """One migration statement written for each backend; None: nothing to do on that one."""

    sqlite: str | None
    postgresql: str | None


class Backend(ABC):
    """What differs between the databases (see the module's docstring)."""

    #: ``"sqlite"`` or ``"postgresql"``: which of :class:`Dialects`' statements runs here.
    dialect: str
    #: How messages name the catalog: the file, or the URL without its password.
    where: str
    #: Appended to the job claim's ``SELECT``: the row is locked, and rows other claims
    #: hold are passed over (empty where the whole write is serialised).
    claim_lock = ""

    @abstractmethod
    def begin(self, *, write: bool) -> Connection:
        """Start an operation's transaction (where one is needed) on a live connection."""

    @abstractmethod
    def commit(self, conn: Connection, *, write: bool) -> None:
        """End the operation :meth:`begin` started, keeping what it wrote."""

    @abstractmethod
    def rollback(self) -> None:
        """End the operation under way, dropping what it wrote (quietly: the connection may be gone)."""

    @abstractmethod
    def serialise(self, conn: Connection, key: str) -> None:
        """Within a write: hold ``key`` until it ends, so that writes naming the same key
        happen one after the other."""

    @abstractmethod
    def next_seq(self, conn: Connection, table: str) -> int:
        """The ``seq`` of a row inserted into ``table`` in this write."""

    @abstractmethod
    def storage_error(self, exc: BaseException, doing: str) -> Exception | None:
        """The one-line catalog error of the database's ``exc``: full (507) or unavailable (503);
        ``exc`` itself when it is a bug (a constraint, a bad statement); None when ``exc`` is
        not the database's."""

    @abstractmethod
    def close(self) -> None:
        """Close the connection."""


def open_backend(location: str | Path, busy_timeout_s: float) -> Backend:
    """The backend of a catalog location: a path or ``sqlite:///PATH`` (an SQLite file), or
    ``postgresql://USER:PASSWORD@HOST:PORT/DATABASE``.

    Raises
    ------
    CatalogError
        An unknown URL scheme, or a database that cannot be opened.
    """
    text = str(location)
    scheme = text.split("://", 1)[0].lower() if "://" in text else ""
    if scheme in POSTGRESQL_SCHEMES:
        return PostgresBackend(text, busy_timeout_s)
    if text.startswith(SQLITE_PREFIX):
        return SQLiteBackend(text[len(SQLITE_PREFIX) :], busy_timeout_s)
    if scheme:
        raise CatalogError(
            f"catalog {text!r}: unknown URL scheme {scheme!r} (sqlite:///PATH or postgresql://USER@HOST/DATABASE)"
        )
    return SQLiteBackend(text, busy_timeout_s)


# --- SQLite --------------------------------------------------------------------------------
class SQLiteBackend(Backend):
    """One SQLite file in WAL mode; every write one ``BEGIN IMMEDIATE`` transaction."""

    dialect = "sqlite"

    def __init__(self, path: str, busy_timeout_s: float):
        self.where = path
        try:
            conn = sqlite3.connect(path, timeout=busy_timeout_s, isolation_level=None, check_same_thread=False)
        except sqlite3.Error as exc:
            raise CatalogError(f"cannot open catalog {path}: {exc}") from None
        conn.row_factory = sqlite3.Row
        self._conn = conn
        try:
            conn.execute(f"PRAGMA busy_timeout = {int(busy_timeout_s * 1000)}")
            mode = conn.execute("PRAGMA journal_mode = WAL").fetchone()[0]
            if mode.lower() not in ("wal", "memory"):
                raise CatalogError(f"cannot open catalog {path}: journal mode is {mode}, not wal")
            conn.execute("PRAGMA foreign_keys = ON")
        except sqlite3.Error as exc:
            conn.close()
            raise CatalogError(f"cannot open catalog {path}: {exc}") from None
        except BaseException:
            conn.close()
            raise

    def begin(self, *, write: bool) -> Connection:
        if write:  # the write lock from the start: a transaction never has to upgrade and fail busy
            self._conn.execute("BEGIN IMMEDIATE")
        return cast(Connection, self._conn)  # sqlite3's own, which takes the same calls

    def commit(self, conn: Connection, *, write: bool) -> None:
        if write:  # a read began no transaction: WAL gives each statement its snapshot
            conn.execute("COMMIT")

    def serialise(self, conn: Connection, key: str) -> None:
        pass  # every write holds SQLite's one write lock from its start already

    def next_seq(self, conn: Connection, table: str) -> int:
        return conn.execute(f"SELECT COALESCE(MAX(seq), 0) + 1 FROM {table}").fetchone()[0]

    def rollback(self) -> None:
        if self._conn.in_transaction:  # SQLite may already have rolled back (disk full, I/O error)
            with contextlib.suppress(sqlite3.Error):
                self._conn.execute("ROLLBACK")

    def storage_error(self, exc: BaseException, doing: str) -> Exception | None:
        if not isinstance(exc, sqlite3.DatabaseError):
            return None
        if isinstance(exc, sqlite3.IntegrityError | sqlite3.ProgrammingError):
            return exc
        code = (getattr(exc, "sqlite_errorcode", 0) or 0) & 0xFF
        if code == _SQLITE_FULL:
            return CatalogFullError(f"no space left on device {doing} the catalog {self.where}")
        if code == _SQLITE_READONLY:
            return CatalogUnavailableError(f"the catalog {self.where} cannot be written ({exc})")
        if code == _SQLITE_IOERR:
            return CatalogUnavailableError(f"I/O error {doing} the catalog {self.where}")
        return CatalogUnavailableError(f"catalog {self.where}: {doing} failed: {exc}")

    def close(self) -> None:
        self._conn.close()


# --- PostgreSQL ----------------------------------------------------------------------------
class _PostgresRow:
    """A row by position or by column name, as ``sqlite3.Row``."""

    __slots__ = ("_names", "_values")

    def __init__(self, values: Sequence[Any], names: dict[str, int]):
        self._values = values
        self._names = names

    def __getitem__(self, key: int | str) -> Any:
        return self._values[self._names[key] if isinstance(key, str) else key]


def _row_factory(cursor: Any) -> Any:
    names = {column.name: k for k, column in enumerate(cursor.description or ())}
    return lambda values: _PostgresRow(values, names)


_PLACEHOLDER = re.compile(r"\?")


class _PostgresConnection:
    """A psycopg connection that takes the catalog's ``?`` placeholders."""

    def __init__(self, conn: Any):
        self.raw = conn
        self._statements: dict[str, str] = {}

    def execute(self, sql: str, params: Sequence[object] = ()) -> Cursor:
        statement = self._statements.get(sql)
        if statement is None:
            statement = self._statements[sql] = _PLACEHOLDER.sub("%s", sql.replace("%", "%%"))
        return self.raw.execute(statement, params)


#: The SQLSTATEs of a storage that refused: out of space (507); read-only, or a lock not
#: granted within the busy timeout (503).
_PG_DISK_FULL = ("53100",)
_PG_BUGS = ("23", "42", "22")  # integrity constraint, syntax or access rule, data exception


def redact_url(url: str) -> str:
    """``url`` without its password, for messages and logs."""
    parts = urlsplit(url)
    if parts.password is None:
        return url
    host = parts.hostname or ""
    netloc = f"{parts.username}@{host}" if parts.username else host
    if parts.port is not None:
        netloc += f":{parts.port}"
    return urlunsplit((parts.scheme, netloc, parts.path, parts.query, parts.fragment))


class PostgresBackend(Backend):
    """A PostgreSQL database through psycopg 3, autocommit with explicit transactions
    (``READ COMMITTED``): a job is claimed with ``SELECT ... FOR UPDATE SKIP LOCKED``, and
    a check that must not interleave with another write takes an advisory lock."""

    dialect = "postgresql"
    claim_lock = " FOR UPDATE SKIP LOCKED"

    def __init__(self, url: str, busy_timeout_s: float):
        self.url = url
        self.where = redact_url(url)
        self._busy_timeout_ms = int(busy_timeout_s * 1000)
        self._psycopg = psycopg
        self._conn: _PostgresConnection | None = None
        try:
            self._connect()
        except CatalogUnavailableError as exc:
            raise CatalogError(f"cannot open catalog {self.where}: {exc}") from None

    def _connect(self) -> _PostgresConnection:
        try:
            raw = self._psycopg.connect(
                self.url,
                autocommit=True,
                row_factory=_row_factory,
                connect_timeout=max(1, self._busy_timeout_ms // 1000),
                application_name="mirrorgonio",
            )
        except self._psycopg.Error as exc:
            raise CatalogUnavailableError(f"cannot reach the catalog {self.where}: {_first_line(exc)}") from None
        try:
            # The busy timeout's equivalent: how long a statement waits for a lock.
            raw.execute(f"SET lock_timeout = {self._busy_timeout_ms}")
        except self._psycopg.Error as exc:
            raw.close()
            raise CatalogUnavailableError(f"catalog {self.where}: {_first_line(exc)}") from None
        self._conn = _PostgresConnection(raw)
        return self._conn

    def begin(self, *, write: bool) -> Connection:
        conn = self._conn if self._conn is not None and not self._conn.raw.closed else self._connect()
        try:
            conn.execute("BEGIN")
        except self._psycopg.OperationalError:
            # The connection went away between operations (a server restart): nothing had
            # begun, so open it again and begin once more.
            with contextlib.suppress(self._psycopg.Error):
                conn.raw.close()
            conn = self._connect()
            conn.execute("BEGIN")
        return conn

    def commit(self, conn: Connection, *, write: bool) -> None:
        conn.execute("COMMIT")  # a read's too: it ends the transaction its BEGIN opened

    def rollback(self) -> None:
        raw = self._conn.raw if self._conn is not None else None
        if raw is None or raw.closed:
            return
        with contextlib.suppress(self._psycopg.Error):
            raw.execute("ROLLBACK")

    def serialise(self, conn: Connection, key: str) -> None:
        conn.execute("SELECT pg_advisory_xact_lock(hashtext(?))", (f"mirrorgonio:{key}",))

    def next_seq(self, conn: Connection, table: str) -> int:
        return conn.execute(f"SELECT nextval('{table}_seq')").fetchone()[0]

    def storage_error(self, exc: BaseException, doing: str) -> Exception | None:
        psycopg = self._psycopg
        if not isinstance(exc, psycopg.Error):
            return None
        state = exc.sqlstate or ""
        if isinstance(exc, psycopg.IntegrityError | psycopg.ProgrammingError | psycopg.DataError) or (
            state.startswith(_PG_BUGS)
        ):
            return exc
        if state in _PG_DISK_FULL:
            return CatalogFullError(f"no space left on device {doing} the catalog {self.where}")
        if state == "25006":
            return CatalogUnavailableError(f"the catalog {self.where} cannot be written (read-only)")
        if self._conn is not None and self._conn.raw.broken:
            return CatalogUnavailableError(f"catalog {self.where}: {doing} failed: the connection was lost")
        return CatalogUnavailableError(f"catalog {self.where}: {doing} failed: {_first_line(exc)}")

    def close(self) -> None:
        if self._conn is not None:
            with contextlib.suppress(self._psycopg.Error):
                self._conn.raw.close()
            self._conn = None


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__
