"""processing.parallel.tune_malloc: a task's large arrays reuse the heap instead of
faulting in fresh pages (measured in a fresh interpreter, glibc only)."""

from __future__ import annotations

import json
import platform
import subprocess
import sys

import pytest

pytestmark = pytest.mark.skipif(
    platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc's mallopt"
)

PROBE = """
import json, resource, sys, numpy as np
from processing.parallel import tune_malloc
if sys.argv[1] == "tuned":
    tune_malloc()

def faults_of(make):
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    array = make()
    array[...] = 1
    del array
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before

sizes = {"64 MiB": 8 << 20, "24 MiB": 3 << 20}  # a 4000x2624 task's frames are 105 MB
for n in sizes.values():
    faults_of(lambda: np.empty(n))  # the heap grows once
print(json.dumps({name: [faults_of(lambda: np.empty(n)) for _ in range(3)] for name, n in sizes.items()}))
"""


def _faults(mode: str) -> dict[str, list[int]]:
    done = subprocess.run([sys.executable, "-c", PROBE, mode], capture_output=True, text=True, check=True)
    return json.loads(done.stdout)


def test_large_arrays_are_served_from_the_heap_again_after_tuning():
    plain, tuned = _faults("plain"), _faults("tuned")
    # Untuned, an array above glibc's largest mmap threshold (32 MiB) is a fresh mapping
    # every time: its pages fault in again (a 64 MiB array: 32 huge pages or 16 k pages).
    assert min(plain["64 MiB"]) >= 32
    # Tuned, every size comes back from the heap: nothing new to fault in.
    assert max(tuned["64 MiB"]) <= 4 and max(tuned["24 MiB"]) <= 4
