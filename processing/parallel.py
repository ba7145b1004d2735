"""Where the processing's position tasks run: a Dask cluster, or this process.

A run is processed position by position (``processing.light_run``): every task opens the
run file itself, by path, reads one position, and returns only that position's result,
so a run is never loaded whole and the tasks can run anywhere that sees the files.
:class:`Compute` hands them out:

``local`` (the default)
    a ``distributed.LocalCluster`` on this machine: one worker process per core, one
    thread each (the numerical kernels are single-threaded in a task, so the processes
    do not compete for the cores);
``tcp://HOST:8786``
    an existing Dask scheduler and its workers (``dask scheduler``, ``dask worker``); they
    must see the run files and the output folder at the same paths;
``none`` or ``synchronous``
    no Dask at all: the tasks run one after the other in this process (tests, debugging).

Results stream back: at most a few tasks per worker thread are in flight, and each
result is handed to the caller as it completes (``distributed.as_completed``) and
released, so memory stays bounded whatever the number of positions.
"""

from __future__ import annotations

import ctypes
import logging
import os
import resource
import sys
import uuid
from collections.abc import Callable, Hashable, Iterable
from itertools import islice
from typing import TYPE_CHECKING, Any

from threadpoolctl import threadpool_limits

if TYPE_CHECKING:
    import distributed

log = logging.getLogger("mirrorgonio.compute")

LOCAL = "local"
#: Scheduler names that mean "no Dask: run the tasks here, in order".
NO_DASK = ("none", "synchronous")
_ADDRESS_SCHEMES = ("tcp://", "tls://", "inproc://", "ws://", "wss://", "ucx://")


class ComputeError(ValueError):
    """A Dask cluster that cannot be started or reached (one line)."""


def default_workers() -> int:
    """The cores this process may use: the local cluster's default number of workers."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def in_dask_worker() -> bool:
    """Whether the caller runs inside a Dask worker (without importing Dask when it is not)."""
    distributed = sys.modules.get("distributed")
    if distributed is None:  # a Dask worker has imported it long before any task
        return False
    try:
        distributed.get_worker()
        return True
    except ValueError:
        return False


#: Dask settings of the local cluster. Its scheduler, the workers' nannies and this client
#: share this process, and two worker processes share the cores with it: the statistical
#: profiler (a sample of every worker thread every 10 ms), the system and memory monitors
#: polling psutil several times a second, the 20 ms event-loop tick and work stealing (useless
#: with a few tasks handed out per worker at a time) cost 0.1 CPU-s of the client and ~4 % of every
#: task on a 66-position run (measured on 2 cores, interleaved runs). A dashboard-less local cluster
#: loses nothing by them; an existing ``tcp://`` cluster keeps its own settings.
LOCAL_CLUSTER_CONFIG = {
    "distributed.worker.profile.enabled": False,
    "distributed.admin.system-monitor.interval": "2s",
    "distributed.worker.memory.monitor-interval": "1s",
    "distributed.admin.tick.interval": "500ms",
    "distributed.scheduler.work-stealing": False,
    # Dask sets MALLOC_TRIM_THRESHOLD_ in its workers, which makes every large array a fresh
    # mmap (see tune_malloc); unset, glibc adapts by itself.
    "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None,
    # Tasks run on the worker's executor thread, and glibc gives each thread its own arena,
    # whose 64 MiB heaps are unmapped whole once free, whatever tune_malloc asks: a worker
    # faulted in 80-800 MB of fresh pages per 66-position run (20-210 k minor faults; 3-5 k
    # in one thread). One arena keeps them: ~1 k faults, and ~0.3 CPU-s less system time a
    # worker (measured on 2 cores). Only an environment variable set before the process
    # starts does it: mallopt(M_ARENA_MAX) comes after the executor thread has its arena.
    "distributed.nanny.pre-spawn-environ.MALLOC_ARENA_MAX": "1",
}

_MALLOC_TUNED = False


def _task_key(func: Callable, suffix: str) -> str:
    """A Dask key that names the function (the task stream and errors show it)."""
    return f"{getattr(func, '__name__', 'task')}-{suffix}"


def tune_malloc() -> None:
    """Keep glibc from returning every large array's memory to the system at once.

    Dask starts its workers with ``MALLOC_TRIM_THRESHOLD_`` set (64 KiB by default), and any
    such setting switches off glibc's adaptive mmap threshold: every array above 128 KiB is
    then a fresh ``mmap`` whose pages fault in zeroed, and is unmapped when freed. A
    position task allocates and frees hundreds of MB in arrays of 1–30 MB, and measured
    1.6x slower that way. Arrays of every size come from the heap here (arrays above
    32 MiB, glibc's largest mmap threshold, are not mmapped at all: at 4000x2624 a task's
    frames are 105 MB, and mmapped each task would fault in ~350 MB afresh, 700 k faults and
    ~5 CPU-s of system time a run on 2 workers, against ~1 k here), and the heap keeps
    up to 256 MiB of freed memory (so a worker's memory stays bounded). Once per process; a
    no-op where the C library is not glibc. (Threads with arenas of their own fall back to
    the main heap for what their 64 MiB heaps cannot hold; ``LOCAL_CLUSTER_CONFIG`` gives
    the workers one arena anyway.)
    """
    global _MALLOC_TUNED
    if _MALLOC_TUNED:
        return
    _MALLOC_TUNED = True
    try:
        libc = ctypes.CDLL("libc.so.6")
        m_trim_threshold, m_mmap_threshold, m_mmap_max = -1, -3, -4
        libc.mallopt(m_mmap_threshold, 32 << 20)
        libc.mallopt(m_trim_threshold, 256 << 20)
        libc.mallopt(m_mmap_max, 0)
    except (OSError, AttributeError):  # pragma: no cover - not glibc
        pass


def _peak_rss_bytes() -> int:
    """This process's peak resident set size (Linux reports kilobytes)."""
    return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024


class Compute:
    """Runs position tasks on a Dask client, or in this process when there is none.

    Use :func:`open_compute` to make one; close it (or use it as a context manager) to
    stop a local cluster.

    Parameters
    ----------
    client : distributed.Client, optional
        None: no Dask, the tasks run in order in this process.
    cluster : distributed.LocalCluster, optional
        The cluster this object started and closes.
    description : str
        Where the tasks run, for people.
    in_flight_per_thread : int
        Tasks submitted ahead per worker thread: 4 keeps every worker busy while its
        last result travels back, lets them be submitted two per thread at a time (one graph
        update each), and bounds the results held at once.
    """

    def __init__(
        self,
        client: distributed.Client | None = None,
        cluster: distributed.LocalCluster | None = None,
        description: str = "this process (no Dask)",
        in_flight_per_thread: int = 4,
    ) -> None:
        self.client = client
        self.cluster = cluster
        self.description = description
        self.in_flight_per_thread = max(1, int(in_flight_per_thread))

    @property
    def dask(self) -> bool:
        """Whether tasks go to Dask workers (each then runs its kernels single-threaded)."""
        return self.client is not None

    def threads(self) -> int:
        """Worker threads available now (1 without Dask)."""
        if self.client is None:
            return 1
        try:
            return max(1, sum(self.client.nthreads().values()))
        except Exception:  # noqa: BLE001 - a scheduler that does not answer: submit little
            return 1

    def max_in_flight(self) -> int:
        return self.threads() * self.in_flight_per_thread

    def map_unordered(
        self, func: Callable, items: Iterable, *args: Any, on_result: Callable[[Any, Any], None], **kwargs: Any
    ) -> None:
        """Call ``func(item, *args, **kwargs)`` for every item; ``on_result(item, result)`` as each completes.

        With Dask at most :meth:`max_in_flight` tasks are submitted at a time, the next
        ones half that many together as soon as as many have ended; results arrive in
        completion order. An exception from a task (re-raised here with its own
        type) or from ``on_result`` cancels the tasks still pending and propagates.
        ``func`` must be importable by the workers (a module-level function).
        """
        items = list(items)
        if self.client is None:
            # One BLAS thread, as in a Dask worker (its nanny sets OMP_NUM_THREADS=1): a
            # least-squares solve summed by two threads differs in the last bits, and a run
            # processed here or on a cluster gives the same numbers to the last digit.
            with threadpool_limits(limits=1, user_api="blas"):
                for item in items:
                    on_result(item, func(item, *args, **kwargs))
            return
        from distributed import as_completed  # noqa: PLC0415 - heavy: dask, only where a cluster runs

        token = uuid.uuid4().hex[:8]
        pending = iter(items)
        running: dict[Hashable, tuple[Any, Any]] = {}  # key: (future, item)
        count = iter(range(len(items)))
        most = self.max_in_flight()  # asks the scheduler: once
        batch = max(1, most // 2)

        def submit(chunk: list) -> list:
            # One graph update for the whole chunk: the scheduler's cost is per update as much as
            # per task (1.5 ms of this process's CPU a task when they went one by one).
            keys = [_task_key(func, f"{token}-{next(count)}") for _ in chunk]
            assert self.client is not None  # checked above
            futures = self.client.map(func, chunk, *[[a] * len(chunk) for a in args], key=keys, pure=False, **kwargs)
            running.update({f.key: (f, item) for f, item in zip(futures, chunk, strict=True)})
            return futures

        # with_results: the client fetches each result as its task ends, in its event loop, rather
        # than in a round trip to the scheduler and the worker per result here.
        queue = as_completed(submit(list(islice(pending, most))), with_results=True)
        try:
            for future, result in queue:
                _, item = running.pop(future.key)
                future.release()
                on_result(item, result)
                if len(running) <= most - batch:
                    chunk = list(islice(pending, batch))
                    if chunk:
                        queue.update(submit(chunk))
        except BaseException:
            self.client.cancel([future for future, _ in running.values()])
            raise

    def submit(self, func: Callable[..., Any], *args: Any, **kwargs: Any) -> distributed.Future[Any]:
        """Start ``func(*args, **kwargs)`` on a worker now; a future whose ``result()`` waits for it
        (and re-raises its exception). Dask only: without Dask there is nowhere to start it, and
        the caller runs ``func`` itself (ComputeError)."""
        if self.client is None:
            raise ComputeError("no Dask workers to submit to: call the function in this process")
        return self.client.submit(func, *args, key=_task_key(func, uuid.uuid4().hex[:8]), pure=False, **kwargs)

    def warm_up(self, func: Callable[[], None]) -> None:
        """Run ``func()`` once on every worker (imports, compiled kernels): the cost of a
        fresh worker, paid when it starts rather than in a run's first tasks. A worker
        plugin (``processing.dask_plugins.WarmUpPlugin``), so that workers that join the
        cluster later are warmed too. A worker it fails on is logged and left to warm up
        on its own. No-op without Dask."""
        if self.client is None:
            return
        from processing.dask_plugins import WarmUpPlugin  # noqa: PLC0415 - it imports dask's distributed (heavy)

        try:
            self.client.register_plugin(WarmUpPlugin(func))
        except Exception as exc:  # noqa: BLE001 - a slower first run, not an error
            log.warning("warming up the Dask workers failed: %s", exc)

    def worker_peak_rss(self) -> dict[str, int]:
        """Peak resident memory of every worker process, in bytes (this process without Dask)."""
        if self.client is None:
            return {"local": _peak_rss_bytes()}
        return dict(self.client.run(_peak_rss_bytes))

    def close(self) -> None:
        """Close the client, and the local cluster if this object started it. Idempotent."""
        client, cluster, self.client, self.cluster = self.client, self.cluster, None, None
        if client is not None:
            client.close()
        if cluster is not None:
            cluster.close()

    def __enter__(self) -> Compute:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"Compute({self.description})"


def check_scheduler(scheduler: str | None, workers: int | None = None) -> str:
    """The scheduler's name as :func:`open_compute` takes it, checked without starting anything.

    Raises
    ------
    ComputeError
        A name that is not ``local``, ``none``, ``synchronous`` nor a Dask address; fewer than one worker.
    """
    name = (scheduler or LOCAL).strip()
    if workers is not None and workers < 1:
        raise ComputeError(f"--workers: must be at least 1, not {workers}")
    if name.lower() not in (LOCAL, *NO_DASK) and not name.startswith(_ADDRESS_SCHEMES):
        raise ComputeError(
            f"--scheduler: {name!r} is not 'local', 'none', 'synchronous' or a Dask scheduler "
            "address such as tcp://HOST:8786"
        )
    return name


def open_compute(
    scheduler: str | None = LOCAL,
    *,
    workers: int | None = None,
    timeout_s: float = 30.0,
    warm_up: Callable[[], None] | None = None,
) -> Compute:
    """Start or reach the Dask cluster that ``scheduler`` names.

    Parameters
    ----------
    scheduler : str, optional
        ``"local"`` (default): a new ``LocalCluster`` of ``workers`` processes, 1 thread
        each; ``"tcp://HOST:PORT"`` (or another Dask address): an existing scheduler, with
        at least one worker; ``"none"`` or ``"synchronous"``: no Dask.
    workers : int, optional
        Worker processes of a local cluster (default: the cores, :func:`default_workers`).
    timeout_s : float
        How long to wait for a scheduler to answer and for its first worker.
    warm_up : callable, optional
        Run on every worker once it is up (:meth:`Compute.warm_up`), e.g.
        :func:`processing.light_run.position.warm_up_worker`.

    Raises
    ------
    ComputeError
        A name that is none of these, a cluster that does not start, a scheduler that
        cannot be reached or has no worker.
    """
    name = check_scheduler(scheduler, workers)
    if name.lower() in NO_DASK:
        return Compute()
    from distributed import Client  # noqa: PLC0415 - heavy: dask, only where a cluster runs

    if name.lower() == LOCAL:
        import dask  # noqa: PLC0415 - heavy
        from distributed import LocalCluster  # noqa: PLC0415 - heavy

        n = workers or default_workers()
        try:
            with dask.config.set(LOCAL_CLUSTER_CONFIG):
                # No dashboard; the scheduler's small HTTP server (health, metrics) on a free
                # port rather than 8787, which another cluster may hold.
                cluster = LocalCluster(
                    n_workers=n,
                    threads_per_worker=1,
                    processes=True,
                    host="127.0.0.1",
                    dashboard_address=None,
                    scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
                    silence_logs=logging.ERROR,
                )
        except Exception as exc:  # noqa: BLE001 - any failure to start is one line for the user
            raise ComputeError(f"cannot start a local Dask cluster of {n} workers: {exc}") from None
        try:
            client = Client(cluster, timeout=timeout_s)
        except Exception as exc:  # noqa: BLE001
            cluster.close()
            raise ComputeError(f"cannot connect to the local Dask cluster: {exc}") from None
        return _warmed(Compute(client, cluster, f"local Dask cluster: {n} worker processes x 1 thread"), warm_up)
    try:
        client = Client(name, timeout=timeout_s)
    except Exception as exc:  # noqa: BLE001 - OSError, TimeoutError, CommClosedError ...
        raise ComputeError(
            f"--scheduler {name}: cannot reach the Dask scheduler ({' '.join(str(exc).split()) or type(exc).__name__})"
        ) from None
    try:
        client.wait_for_workers(1, timeout=timeout_s)
    except Exception:  # noqa: BLE001
        client.close()
        raise ComputeError(f"--scheduler {name}: the scheduler has no worker (start `dask worker {name}`)") from None
    return _warmed(Compute(client, None, f"Dask scheduler {name}: {len(client.nthreads())} workers"), warm_up)


def _warmed(compute: Compute, warm_up: Callable[[], None] | None) -> Compute:
    if warm_up is not None:
        compute.warm_up(warm_up)
    return compute
