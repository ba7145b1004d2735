"""`mirrorgonio bench speed`: a smoke run at a tiny size, its JSON checked for shape and sense.

No timing is asserted (the machine is shared): only that every figure is there, positive,
and consistent with the others.
"""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from acquisition.benchmarks.hdr import rig_at_size
from acquisition.benchmarks.hdr_methods import UNRESOLVED_MERGE_ONLY, MergeMethod
from acquisition.benchmarks.speed import parse_size
from acquisition.benchmarks.speed_runs import SpeedBenchError, cache_key
from acquisition.benchmarks.speed_steps import _hdr_entries
from acquisition.cli import app
from drivers.contracts.rig import load_rig

W, H, POSITIONS, EXPOSURES = 200, 132, 6, 5


@pytest.fixture(scope="module")
def speed(tmp_path_factory):
    cache = tmp_path_factory.mktemp("speed-cache")
    args = [
        "bench",
        "speed",
        "--json",
        "--sizes",
        f"{W}x{H}",
        "--positions",
        str(POSITIONS),
        "--repeat",
        "2",
        "--process-repeat",
        "2",
        "--hdr-positions",
        "2",
        "--scheduler",
        "local",
        "--workers",
        "1",
        "--cache",
        str(cache),
    ]
    first = CliRunner().invoke(app, args)
    assert first.exit_code == 0, first.output
    again = CliRunner().invoke(app, [*args[:-6], "--scheduler", "none", "--no-peers", "--cache", str(cache)])
    assert again.exit_code == 0, again.output
    return json.loads(first.stdout.strip().splitlines()[-1]), json.loads(again.stdout.strip().splitlines()[-1]), cache


def test_the_json_has_every_measurement(speed):
    result, _, _ = speed
    assert result["benchmark"] == "speed"
    assert result["positions"] == POSITIONS and len(result["exposures_s"]) == EXPOSURES
    assert len(result["load_avg_start"]) == 3 and result["machine"]["cpu_count"] >= 1
    entry = result["sizes"][f"{W}x{H}"]
    assert (entry["width"], entry["height"]) == (W, H)
    assert entry["pixel_pitch_um"] == pytest.approx(5.9 * 2000 / W)
    assert set(entry) >= {"run", "read", "process", "trace", "hdr", "acquire", "load_avg_before", "load_avg_after"}
    frames = POSITIONS * EXPOSURES

    read = entry["read"]
    assert read["frames"] == frames and read["frame_bytes_total"] == frames * W * H * 2
    assert 0 < read["read_s"] and len(read["read_s_all"]) == 2
    assert read["mb_per_s"] == pytest.approx(read["frame_bytes_total"] / 1e6 / read["read_s"], rel=0.05)

    process = entry["process"]
    assert process["positions"] == POSITIONS and process["process_s"] > 0 and len(process["process_s_all"]) == 2
    assert process["process_s_without_images"] > 0
    # timed warm on one cluster; the first processing and one on a cluster of its own apart
    assert (
        process["first_process_s"] > 0
        and process["process_s_fresh_cluster"] > 0
        and process["fresh_cluster_start_s"] > 0
    )
    assert process["fresh_cluster_over_read_floor"] == pytest.approx(
        process["process_s_fresh_cluster"] / read["read_s"], rel=0.02
    )
    assert process["without_images_over_read_floor"] == pytest.approx(
        process["process_s_without_images"] / read["read_s"], rel=0.02
    )
    # where a position task's time goes, per position: every stage of the fused hdr + sources task
    stages = process["task_ms_per_position"]
    assert set(stages) == {"read", "merge", "encode", "write", "images", "masks", "sources", "tasks"}
    assert all(v >= 0 for v in stages.values())
    assert sum(v for k, v in stages.items() if k != "tasks") == pytest.approx(stages["tasks"], rel=0.1, abs=0.5)
    # each timed processing set against a read of the floor just before it; the median of those ratios
    paired = [run / read for run, read in zip(process["process_s_all"], process["paired_read_s_all"], strict=True)]
    assert process["over_read_floor_all"] == pytest.approx(paired, rel=0.02, abs=0.01)
    assert process["over_read_floor"] == pytest.approx(sum(paired) / 2, rel=0.02, abs=0.01)  # two runs: their mean
    assert process["over_separate_read_floor"] == pytest.approx(process["process_s"] / read["read_s"], rel=0.02)
    assert "Dask" in process["compute"] and process["parallel_read_s"] > 0
    # CPU per processing, the client and the workers apart: both did work, within what the cores allow
    cpu = process["cpu_per_processing"]
    assert cpu["workers_user_s"] > 0 and cpu["client_user_s"] > 0 and cpu["workers_system_s"] >= 0
    assert cpu["client_minor_faults"] >= 0 and cpu["workers_minor_faults"] >= 0
    assert (
        cpu["workers_user_s"] + cpu["workers_system_s"]
        < 2 * max(process["process_s_all"]) * result["machine"]["cpu_count"]
    )
    memory = process["memory"]
    assert memory["child_processes"] >= 1 and memory["peak_children_gb"] > 0
    assert memory["peak_total_gb"] >= max(memory["peak_this_process_gb"], memory["peak_children_gb"])
    # three figures each rounded to 1 MB: the sum of the parts may trail the total by 1.5 MB
    assert memory["peak_total_gb"] <= memory["peak_this_process_gb"] + memory["peak_children_gb"] + 2e-3
    assert process["peak_memory_gb"] == memory["peak_total_gb"]
    assert process["outputs"]["exr"] == POSITIONS and process["outputs"]["ies"] == 1
    # the stages of the median run (with two runs, the slower: process_s is then their mean)
    assert process["stages_s"]["total"] == pytest.approx(max(process["process_s_all"]), rel=0.05)

    trace = entry["trace"]
    assert trace["rays"] == W * H and trace["rays_per_s"] > 0
    assert trace["rays_per_s"] == pytest.approx(trace["rays"] / trace["trace_s"], rel=0.02)
    assert 0 < trace["rays_reaching_light_plane"] <= trace["rays_hitting_ball"] < trace["rays"]

    hdr = entry["hdr"]
    assert len(hdr["positions_merged"]) == 2 and hdr["exposures_s"] == pytest.approx(result["exposures_s"])
    ours = hdr["methods"]["mirrorgonio"]["ms_per_position"]
    assert ours > 0
    for peer in ("hdrutils", "colour_hdri"):
        method = hdr["methods"][peer]
        assert method["status"] == "ok", method
        # a timing is checked for presence and sign: a busy host changes its size, never its sign
        assert method["ms_per_position"] > 0 and hdr["speedup_vs"][peer] > 0
        assert hdr["speedup_vs"][peer] == pytest.approx(method["ms_per_position"] / ours, rel=0.02, abs=0.01)

    acquire = entry["acquire"]
    assert acquire["frames"] == frames and acquire["engine_s"] > 0
    assert 0 <= acquire["camera_capture_ms_per_frame"] < acquire["engine_ms_per_frame"]
    assert acquire["overhead_ms_per_frame"] == pytest.approx(
        acquire["engine_ms_per_frame"] - acquire["camera_capture_ms_per_frame"], abs=0.02
    )
    assert acquire["engine_over_plain_throughput"] == pytest.approx(
        acquire["plain_h5py_ms_per_frame"] / acquire["engine_ms_per_frame"], rel=0.05
    )

    assert result["target"]["measured"] is False and result["target"]["meets_target"] is None
    table = result["markdown"]
    assert table.startswith("| `bench speed` |") and f"{W}×{H}" in table and "not measured" in table
    # the paired ratios' spread beside their median: how far the host moved within the run
    low, high = min(process["over_read_floor_all"]), max(process["over_read_floor_all"])
    assert (
        f"{process['over_read_floor']:.2f}× the read floor read just before each, {low:.2f}–{high:.2f}× over 2 runs"
        in table
    )


def test_the_run_is_made_once_and_then_cached(speed):
    first, again, cache = speed
    one, two = first["sizes"][f"{W}x{H}"]["run"], again["sizes"][f"{W}x{H}"]["run"]
    assert one["from_cache"] is False and two["from_cache"] is True
    assert one["file"] == two["file"] and one["created_s"] == two["created_s"] > 0
    assert [p.suffix for p in sorted(cache.iterdir())] == [".h5", ".json"]  # no work folder left behind
    assert again["sizes"][f"{W}x{H}"]["hdr"]["methods"]["hdrutils"]["status"].startswith("skipped")
    # No Dask: no workers (at most multiprocessing's resource tracker, left by the first run's cluster).
    assert again["sizes"][f"{W}x{H}"]["process"]["memory"]["peak_children_gb"] < 0.05
    assert "parallel_read_s" not in again["sizes"][f"{W}x{H}"]["process"]


def test_the_cache_key_follows_the_rig_and_the_bracket():
    rig = load_rig(None)
    small, large = rig_at_size(rig, 2000, 1312), rig_at_size(rig, 4000, 2624)
    assert large.camera.pixel_pitch_m == pytest.approx(2.95e-6)
    assert cache_key(small, (1e-3, 1e-2), 66) == cache_key(rig_at_size(rig, 2000, 1312), (1e-3, 1e-2), 66)
    assert (
        len(
            {
                cache_key(small, (1e-3, 1e-2), 66),
                cache_key(large, (1e-3, 1e-2), 66),
                cache_key(small, (1e-3, 2e-2), 66),
                cache_key(small, (1e-3, 1e-2), 65),
            }
        )
        == 4
    )


def test_bad_sizes_are_one_line_errors():
    assert parse_size("4000x2624") == (4000, 2624)
    with pytest.raises(SpeedBenchError, match="--sizes"):
        parse_size("4000")
    result = CliRunner().invoke(app, ["bench", "speed", "--sizes", "201x132"])
    assert result.exit_code == 2 and "error: --sizes: '201x132'" in result.output


def test_without_a_cache_the_run_is_made_in_a_temporary_folder():
    from acquisition.benchmarks.speed_runs import simulated_run

    made = simulated_run(rig_at_size(load_rig(None), 64, 42), (1e-4, 1e-3), 3, cache=None)
    try:
        assert not made.from_cache and made.created_s > 0 and made.temporary is not None
        assert made.path.is_file() and made.path.parent == made.temporary
        assert made.record["width"] == 64 and made.record["positions"] == 3
    finally:
        import shutil

        shutil.rmtree(made.temporary)


def test_a_peer_whose_part_timed_apart_outlasts_its_call_still_has_a_positive_time():
    """On a busy host HDRutils' demosaic, timed apart, can take longer than the whole call it
    is part of: its merge-only time is then not resolved, and the whole call stands in for it
    (said so), never 0 ms and a speed-up of None."""

    def method(excluded):
        return MergeMethod("m", len, len, len, "", "", "", "1", excluded=excluded, excluded_what="demosaic")

    methods = {"mirrorgonio": method(None), "hdrutils": method(len)}
    times = {"mirrorgonio": [0.010, 0.011], "hdrutils": [0.050, 0.060]}
    excluded = {"mirrorgonio": [0.0, 0.0], "hdrutils": [0.055, 0.040]}  # the first repeat: longer than its call
    entries = _hdr_entries(methods, times, excluded, {}, 2)
    peer = entries["hdrutils"]
    assert peer["merge_only"] == UNRESOLVED_MERGE_ONLY
    assert peer["ms_per_position"] == pytest.approx(1000 * 0.055 / 2)  # the whole call's median
    assert entries["mirrorgonio"]["ms_per_position"] == pytest.approx(1000 * 0.0105 / 2)
    resolved = _hdr_entries(methods, times, {**excluded, "hdrutils": [0.030, 0.040]}, {}, 2)["hdrutils"]
    assert "merge_only" not in resolved and resolved["ms_per_position"] == pytest.approx(1000 * 0.020 / 2)
