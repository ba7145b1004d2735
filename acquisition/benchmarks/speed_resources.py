"""What a processing costs beyond its time: peak memory and CPU, of this process and of the
Dask workers it starts (``bench speed``'s whole-run processing)."""

from __future__ import annotations

import resource
import statistics
import threading
from collections.abc import Callable

import psutil

from processing.parallel import Compute


class MemorySampler:
    """Peak resident memory of this process and of all its descendants, sampled in a thread.

    Resident set sizes are summed over the processes at each sample (pages shared between
    processes, such as the libraries every Dask worker maps, are counted once per process:
    an upper bound of the physical memory). The page cache is not counted.
    """

    def __init__(self, interval_s: float = 0.05):
        self.interval_s = interval_s
        self.me = psutil.Process()
        self.baseline_self = self.me.memory_info().rss
        self.peak_total = self.peak_self = self.peak_children = 0
        self.max_children = 0
        self.samples = 0
        self.list_every = max(1, round(1.0 / interval_s))
        self._kids: list[psutil.Process] = []
        self._since_listed = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="memory-sampler", daemon=True)

    def sample(self) -> None:
        """One sample: the resident memory of this process and of its descendants, peaks kept."""
        own = self.me.memory_info().rss
        children = 0
        # Listing the descendants reads every process's /proc entry: once a second is enough (the
        # cluster's processes live for the whole processing), the RSS of each every sample.
        if self._since_listed % self.list_every == 0:
            try:
                self._kids = self.me.children(recursive=True)
            except psutil.Error:
                self._kids = []
        kids = self._kids
        for child in kids:
            try:
                children += child.memory_info().rss
            except psutil.Error:  # ended between the listing and the look
                pass
        self.peak_self = max(self.peak_self, own)
        self.peak_children = max(self.peak_children, children)
        self.peak_total = max(self.peak_total, own + children)
        self.max_children = max(self.max_children, len(kids))
        self.samples += 1
        self._since_listed += 1

    def _loop(self) -> None:
        while not self._stop.is_set():
            self.sample()
            self._stop.wait(self.interval_s)

    def __enter__(self) -> MemorySampler:
        self.sample()
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        self._since_listed = 0  # the last sample lists the descendants again
        self.sample()

    def report(self) -> dict:
        """The peaks in GB, and how they were sampled."""
        gb = 1e9
        return {
            "peak_total_gb": round(self.peak_total / gb, 3),
            "peak_this_process_gb": round(self.peak_self / gb, 3),
            "peak_children_gb": round(self.peak_children / gb, 3),
            "this_process_before_gb": round(self.baseline_self / gb, 3),
            "child_processes": self.max_children,
            "samples": self.samples,
            "sampling": f"psutil RSS of this process + all descendants every {1000 * self.interval_s:g} ms; "
            "the peak of the sum (shared pages counted per process)",
        }


def rusage() -> tuple[float, float, int]:
    """This process's user and system CPU seconds and minor page faults so far."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime, usage.ru_stime, usage.ru_minflt


def cpu_usage(compute: Compute) -> dict[str, tuple[float, float, int]]:
    """:func:`rusage` of this process (``"client"``) and of every Dask worker (by address)."""
    usage = {"client": rusage()}
    if compute.client is not None:  # compute.dask
        usage.update(compute.client.run(rusage))
    return usage


def cpu_report(runs: list[dict]) -> dict:
    """CPU seconds (user, system) and minor page faults per processing, medians over ``runs``:
    the client's and the workers' summed. Faults are worth watching on a VM that hands freed
    memory back to its host (free page reporting): writing into pages handed back costs
    several times writing into pages a process reuses."""

    def median_of(pick: Callable[[dict], float]) -> float:
        return float(statistics.median([pick(run["cpu"]) for run in runs]))

    def workers(cpu: dict, i: int) -> float:
        return sum(v[i] for k, v in cpu.items() if k != "client")

    return {
        "client_user_s": round(median_of(lambda c: c["client"][0]), 2),
        "client_system_s": round(median_of(lambda c: c["client"][1]), 2),
        "client_minor_faults": int(median_of(lambda c: c["client"][2])),
        "workers_user_s": round(median_of(lambda c: workers(c, 0)), 2),
        "workers_system_s": round(median_of(lambda c: workers(c, 1)), 2),
        "workers_minor_faults": int(median_of(lambda c: workers(c, 2))),
        "how": "getrusage(RUSAGE_SELF) of this process and of each worker (Client.run) before and after each "
        "timed processing; medians of the sums",
    }
