"""The catalog: every run and every processing job of a rig, or of a lab's rigs.

On one machine the catalog is an SQLite file, ``DATA_DIR/catalog.sqlite`` (the default); a
lab with several rigs, or workers on other machines, puts it on a PostgreSQL server
(``postgresql://USER@HOST/DATABASE``; :mod:`~acquisition.daemon.catalog.backends`). Each
daemon names its rig: its runs, their jobs and its queue are the rig's own, and it reads the
other rigs' runs without changing them. The catalog outlives the daemon: after a restart
:meth:`Catalog.mark_interrupted` turns the runs the previous daemon left in progress into
``interrupted`` ones, which can be resumed. It is shared by the daemon's threads (HTTP
handlers, the run engine) and by separate processing worker processes, which claim jobs
with :meth:`Catalog.claim_job` and prove they are alive with :meth:`Catalog.heartbeat`.

Portability: one schema and its migrations run on both databases; it uses plain SQL types
(``TEXT``, ``INTEGER``, ``DOUBLE PRECISION``) and ``CHECK`` constraints, and the few
statements that differ are written for each. Times are stored as fixed-width UTC text,
``YYYY-MM-DDTHH:MM:SS.ffffffZ``, so that comparing them as strings compares the times.

Concurrency: SQLite's file is in WAL mode (readers never wait for the writer), every write is
one ``BEGIN IMMEDIATE`` transaction (the write lock is taken at the start, so a
transaction never has to upgrade a read snapshot and fail with ``SQLITE_BUSY``), and
other processes holding the lock are waited for up to ``busy_timeout_s``. WAL needs a
local file system: do not put ``DATA_DIR`` on a network share; a lab whose workers are on
other machines uses PostgreSQL. There, writes lock the rows they change; the job claim
skips the rows other claims hold; a rig's checks that must not interleave (one run in
progress, the queue's order) hold an advisory lock named after the rig.

Bad input is refused with a one-line :class:`CatalogError` that names the run or the job
and the states involved. A storage that refuses a read or a write is a one-line
:class:`CatalogFullError` (the disk is full) or :class:`CatalogUnavailableError` (read-only,
an I/O error, locked past the busy timeout, a PostgreSQL server that cannot be reached),
never the database driver's own exception.

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
    OtherRigError,
    UnknownJobError,
    UnknownRunError,
)
from acquisition.daemon.catalog.jobs import JobCatalog
from acquisition.daemon.catalog.queue import QueueCatalog
from acquisition.daemon.catalog.records import (
    ACTIVE_RUN_STATES,
    ALLOWED_JOB_TRANSITIONS,
    ALLOWED_RUN_TRANSITIONS,
    DEFAULT_RIG,
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
    """The catalog of runs and processing jobs, in an SQLite file or on a PostgreSQL server.

    Parameters
    ----------
    location : str or Path
        The SQLite file (``DATA_DIR/catalog.sqlite``, or ``sqlite:///PATH``), or a PostgreSQL
        database's URL (``postgresql://USER:PASSWORD@HOST:PORT/DATABASE``); its schema is
        created if missing, migrated if older. An SQLite file's folder must exist;
        ``":memory:"`` gives a private in-memory catalog (tests).
    clock : callable, optional
        Returns the current time as a timezone-aware ``datetime`` (UTC by default);
        tests inject one they advance by hand.
    rig : str, optional
        The rig this catalog acts for (``default``): its runs are created with this name,
        and only they can be changed, queued, or given jobs through this catalog.
    busy_timeout_s : float, optional
        How long a write waits for another process holding a lock it needs (SQLite's write
        lock, a PostgreSQL row or advisory lock) before it fails as unavailable.

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
    "DEFAULT_RIG",
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
    "OtherRigError",
    "RunRecord",
    "RunState",
    "UnknownJobError",
    "UnknownRunError",
]
