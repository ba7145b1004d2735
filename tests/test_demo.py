"""``mirrorgonio demo`` end to end: daemon and worker as real processes, the sweep through
the REST API, the worker's job, the result files, the accuracy, and nothing left running.

On the reduced rig (500 x 328) and the first positions of the sweep, so that it stays in
the normal suite (about a minute on two cores).
"""

from __future__ import annotations

import json
import math
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import REDUCED_RIG, ROOT

POSITIONS = 12


def _sessions_alive(session_ids: set[int]) -> list[str]:
    """Processes whose session is one of ``session_ids`` (the demo starts each child in its own)."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            text = stat.read_text()
        except OSError:
            continue
        # pid (comm) state ppid pgrp session ...: comm may hold spaces, so split after ')'.
        fields = text[text.rindex(")") + 2 :].split()
        if fields[0] != "Z" and int(fields[3]) in session_ids:
            found.append(f"{stat.parent.name} {text[: text.rindex(')') + 1]}")
    return found


def _process_gone(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return True
    return state[state.rindex(")") + 2] == "Z"


@pytest.mark.slow
@pytest.mark.timeout(420)
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="checks processes through /proc")
@pytest.mark.parametrize("layout_option", [[], ["--truth-layout"]], ids=["found-in-the-data", "truth-layout"])
def test_demo_runs_the_whole_chain_and_leaves_nothing_running(tmp_path, layout_option):
    exe = Path(sys.executable).with_name("mirrorgonio")
    env = {k: v for k, v in os.environ.items() if not k.startswith("MG_")}
    env.update(COLUMNS="400", PYTHONUNBUFFERED="1")
    root = tmp_path / "demo-data"
    started = time.monotonic()
    done = subprocess.run(
        [
            str(exe),
            "demo",
            "--rig",
            str(REDUCED_RIG),
            "--positions",
            str(POSITIONS),
            "--data-root",
            str(root),
            *layout_option,
        ],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=400,
    )
    elapsed = time.monotonic() - started
    output = done.stdout + done.stderr
    assert done.returncode == 0, output[-4000:]

    # The child processes, and everything in their sessions (Dask's too), are gone.
    pids = {name: int(pid) for name, pid in re.findall(r"(daemon|worker) pid (\d+)", done.stdout)}
    assert set(pids) == {"daemon", "worker"}, done.stdout
    assert all(_process_gone(pid) for pid in pids.values()), pids
    assert _sessions_alive(set(pids.values())) == []

    # Every file the summary prints exists: the run's folder, then each file's name in it.
    (folder_shown,) = re.findall(r"^files in (\S+)/$", done.stdout, flags=re.MULTILINE)
    runs_dir = Path(folder_shown) if Path(folder_shown).is_absolute() else tmp_path / folder_shown
    rows = dict(
        re.findall(
            r"│ (run file|report \(HTML\)|IES|EULUMDAT \(LDT\)|TM-25 ray file|light model \(JSON\)|"
            r"HDR results)\s*│ (\S+)\s*│",
            done.stdout,
        )
    )
    assert set(rows) >= {"run file", "report (HTML)", "IES", "TM-25 ray file", "light model (JSON)"}, done.stdout
    for label, name in rows.items():
        assert (runs_dir / name).is_file(), f"{label}: {runs_dir / name}"
    assert (
        rows["run file"].endswith(".h5")
        and rows["IES"].endswith(".ies")
        and rows["TM-25 ray file"].endswith(".tm25ray")
    )
    assert (runs_dir / rows["report (HTML)"]).read_text(errors="replace").lstrip().lower().startswith("<!doctype html")

    # The accuracy: a number per source of the truth, and the maximum; times for both steps.
    printed = re.findall(r"│ (centre|[+-][uv])\s*│\s*([0-9.]+) %.*│\s*$", done.stdout, flags=re.MULTILINE)
    assert [name for name, _ in printed] == ["centre", "+u", "-u", "+v", "-v"], done.stdout
    assert all(math.isfinite(float(value)) for _, value in printed)
    # Found in the data, each source's distance from the truth's is shown. On this rig (23.6 µm
    # pixels, the five sources imaged 2-3 px apart, 12 positions on one side: the rig held, the
    # pinhole fitted) the seeded run is the same run on every machine and every try
    # (tests/test_repeatable_runs.py), and its five come out 415, 46, 103, 163 and 65 µm from the
    # truth: the centre one is where the coarse sensor merges its image with its neighbours'.
    # Before the search screened a second seed the centre one was missed, the nearest source
    # found 3.3 mm from it. The search's accuracy at the default resolutions is tested in
    # test_sources and test_process.
    offsets = [float(um) for um in re.findall(r"│\s*([0-9]+) µm off\s*│", done.stdout)]
    assert len(offsets) == (0 if layout_option else 5), done.stdout
    assert not offsets or (max(offsets) < 450 and sorted(offsets)[-2] < 200), offsets  # measured: 415, then 163
    assert re.search(r"│ max\s*│\s*[0-9.]+ %", done.stdout), done.stdout
    for step in ("acquisition", "processing", "whole demo"):
        assert re.search(rf"{step}[^│]*│\s*[0-9.]+ s", done.stdout), step

    # The same, for programs: summary.json in the demo's folder.
    (folder,) = [p for p in root.iterdir() if p.is_dir()]
    summary = json.loads((folder / "summary.json").read_text())
    assert summary["positions"] == POSITIONS
    assert summary["pids"] == pids
    assert {Path(summary["artifacts"][k]).name for k in ("report", "ies", "tm25", "light_model")} <= set(rows.values())
    assert summary["layout"].startswith("given to the worker" if layout_option else "found in the data")
    # The worker fits the pinhole's diameter where it searches for the sources (its default), and
    # keeps the rig's with the layout given; the summary says which.
    if layout_option:
        assert summary["aperture"] == "as described by the rig", summary["aperture"]
    else:
        assert re.fullmatch(r"0\.\d+ mm, fitted to the data \(the rig says 0\.2 mm\)", summary["aperture"]), summary[
            "aperture"
        ]
    assert re.search(r"│ camera aperture\s*│ " + re.escape(summary["aperture"][:20]), done.stdout), done.stdout
    assert len(summary["accuracy"]) == 5
    for source in summary["accuracy"]:
        assert math.isfinite(source["rms_rel_error"]) and source["rms_rel_error"] >= 0
        assert source["theta_min_deg"] < source["theta_max_deg"]
    assert summary["max_rms_rel_error"] == max(s["rms_rel_error"] for s in summary["accuracy"])
    assert 0 < summary["acquire_s"] and 0 < summary["process_s"] and summary["total_s"] <= elapsed
    assert not (folder / "daemon.toml").read_text().count("token ="), "the token is not written to disk"


def test_demo_folders_are_fresh_and_old_ones_cleaned(tmp_path):
    from acquisition.demo import MARKER, new_data_dir

    notes: list[str] = []
    unrelated = tmp_path / "keep-me"
    unrelated.mkdir()
    first = new_data_dir(tmp_path, keep=1, note=notes.append)
    second = new_data_dir(tmp_path, keep=1, note=notes.append)
    assert first != second and (first / MARKER).is_file() and (second / MARKER).is_file()
    (first / "run.h5").write_bytes(b"the first demo's data")
    third = new_data_dir(tmp_path, keep=1, note=notes.append)
    demos = {p for p in tmp_path.iterdir() if (p / MARKER).is_file()}
    assert demos == {second, third}, "the newest older one is kept, the others removed"
    assert not (first / "run.h5").exists() and list(third.iterdir()) == [third / MARKER], "a fresh folder"
    assert unrelated.exists(), "only the demo's own folders are removed"
    assert notes == [f"removed an older demo folder: {first}"]


def test_demo_data_is_gitignored():
    ignored = (ROOT / ".gitignore").read_text().split()
    assert "demo-data/" in ignored
