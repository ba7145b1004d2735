"""The catalog: every run and every processing job, in one SQLite file next to the data.

The catalog lives at ``DATA_DIR/catalog.sqlite`` and outlives the daemon: after a restart
:meth:`Catalog.mark_interrupted` turns the runs the previous daemon left in progress into
``interrupted`` ones, which can be resumed. It is shared by the daemon's threads (HTTP
handlers, the run engine) and by separate processing worker processes, which claim jobs
with :meth:`Catalog.claim_job` and prove they are alive with :meth:`Catalog.heartbeat`.

Portability: the schema uses plain SQL types (``TEXT``, ``INTEGER``, ``REAL``) and
``CHECK`` constraints only, so that it can move to PostgreSQL; SQLite-specific settings
are confined to ``PRAGMA`` statements at open. Times are stored as fixed-width UTC text,
``YYYY-MM-DDTHH:MM:SS.ffffffZ``, so that comparing them as strings compares the times.

Concurrency: the file is in WAL mode (readers never wait for the writer), every write is
one ``BEGIN IMMEDIATE`` transaction (the write lock is taken at the start, so a
transaction never has to upgrade a read snapshot and fail with ``SQLITE_BUSY``), and
other processes holding the lock are waited for up to ``busy_timeout_s``. WAL needs a
local file system: do not put ``DATA_DIR`` on a network share.

Bad input is refused with a one-line :class:`CatalogError` that names the run or the job
and the states involved. A storage that refuses a read or a write is a one-line
:class:`CatalogFullError` (the disk is full) or :class:`CatalogUnavailableError` (read-only,
an I/O error, locked past the busy timeout), never SQLite's own exception.

The package's modules: :mod:`~acquisition.daemon.catalog.records` (the states, their transitions and
the records handed out), :mod:`~acquisition.daemon.catalog.errors`, :mod:`~acquisition.daemon.catalog.schema`
(the tables and their migrations), :mod:`~acquisition.daemon.catalog.database` (the connection, its
transactions and the checks of the values given), :mod:`~acquisition.daemon.catalog.runs` and
:mod:`~acquisition.daemon.catalog.jobs` (the operations on each), :mod:`~acquisition.daemon.catalog.queue`
(the runs waiting their turn), joined here in :class:`Catalog`.
"""

from acquisition.daemon.catalog.errors import (
    ActiveRunError,
    CatalogError,
    CatalogFullError,
    CatalogUnavailableError,
    InvalidTransitionError,
    JobClaimError,
    NotQueuedError,
    UnknownJobError,
    UnknownRunError,
)
from acquisition.daemon.catalog.jobs import JobCatalog
from acquisition.daemon.catalog.queue import QueueCatalog
from acquisition.daemon.catalog.records import (
    ACTIVE_RUN_STATES,
    ALLOWED_JOB_TRANSITIONS,
    ALLOWED_RUN_TRANSITIONS,
    IN_PROGRESS_RUN_STATES,
    JOB_STATES,
    RUN_STATES,
    JobRecord,
    JobState,
    RunRecord,
    RunState,
)
from acquisition.daemon.catalog.schema import SCHEMA_VERSION


class Catalog(QueueCatalog, JobCatalog):
    """The catalog of runs and processing jobs in one SQLite file.

    Parameters
    ----------
    path : str or Path
        The database file (``DATA_DIR/catalog.sqlite``); created with its schema if
        missing, migrated if older. Its folder must exist. ``":memory:"`` gives a
        private in-memory catalog (tests).
    clock : callable, optional
        Returns the current time as a timezone-aware ``datetime`` (UTC by default);
        tests inject one they advance by hand.
    busy_timeout_s : float, optional
        How long a write waits for another process holding the write lock before
        ``sqlite3.OperationalError: database is locked``.

    Raises
    ------
    CatalogError
        The file cannot be opened as a catalog, or its schema is newer than this program's.

    Notes
    -----
    One connection per :class:`Catalog`, shared by the threads of the process under a
    lock (``check_same_thread=False``). Every operation is a few indexed statements that
    take well under a millisecond, at a rate of a few per position or per HTTP poll, so
    serialising them costs nothing, whereas a connection per thread would leave one open
    connection behind for every thread of the web server's pool. Within a process the
    lock also means that threads never compete for SQLite's write lock, so "database is
    locked" can only come from another process, which ``busy_timeout`` and
    ``BEGIN IMMEDIATE`` handle. Other processes (workers) open their own
    :class:`Catalog`; one opened before a ``fork`` refuses to be used in the child.
    """


__all__ = [
    "ACTIVE_RUN_STATES",
    "ALLOWED_JOB_TRANSITIONS",
    "ALLOWED_RUN_TRANSITIONS",
    "IN_PROGRESS_RUN_STATES",
    "JOB_STATES",
    "RUN_STATES",
    "SCHEMA_VERSION",
    "ActiveRunError",
    "Catalog",
    "CatalogError",
    "CatalogFullError",
    "CatalogUnavailableError",
    "InvalidTransitionError",
    "JobClaimError",
    "JobRecord",
    "JobState",
    "NotQueuedError",
    "RunRecord",
    "RunState",
    "UnknownJobError",
    "UnknownRunError",
]
