"""``mirrorgonio bench hdr`` at a tiny size: the report's structure, our merge's error, missing peers."""

from __future__ import annotations

import json
import sys

import pytest
from typer.testing import CliRunner

from acquisition.benchmarks.hdr import OURS, PEERS, BenchmarkError, _speedups_and_target, bench_hdr
from acquisition.benchmarks.hdr_methods import merge_only_s, significant
from acquisition.cli import app

METHOD_KEYS = {"time_s", "ms_per_position", "mean_abs_rel_error_pct", "rms_rel_error_pct", "bias_pct", "notes"}
TINY = {"positions": 3, "exposures": 3, "width": 200, "height": 160, "distinct_scenes": 2}


@pytest.fixture(scope="module")
def report():
    # A first call compiles numba kernels the benchmark's own warm-up does not reach in a
    # fresh clone (no JIT cache yet); the figures under test are the steady state's.
    bench_hdr(**{**TINY, "positions": 1})
    return bench_hdr(**TINY)


def test_report_structure(report):
    assert report["benchmark"] == "hdr"
    assert (report["width"], report["height"], report["positions"], report["exposures_per_position"]) == (
        200,
        160,
        3,
        3,
    )
    assert report["exposures_s"] == sorted(report["exposures_s"])
    assert set(report["methods"]) == set(OURS) | set(PEERS)
    for name, entry in report["methods"].items():
        assert METHOD_KEYS <= set(entry), name
        assert entry["status"], name
    for peer in PEERS:
        assert f"speedup_vs_{peer}" in report
    assert isinstance(report["meets_target"], bool) or report["meets_target"] is None
    assert report["scene"]["description"]
    assert report["pixel_set"]["pixels_compared"] > 10_000
    json.dumps(report)  # plain JSON all the way down


def test_our_merge_is_accurate(report):
    floor = report["pixel_set"]["noise_floor_rms_rel_error_pct"]
    for name in OURS:
        ours = report["methods"][name]
        assert ours["status"] == "ok"
        assert ours["time_s"] > 0
        assert ours["pixels_compared"] == report["pixel_set"]["pixels_compared"]
        assert ours["nonfinite_pixels"] == 0
        # The pixel set reaches down to 10 DN in the longest frame, where photon noise alone
        # is ~10 %: the error is judged by its bias and against the ideal merge's noise floor.
        assert abs(ours["bias_pct"]) < 1.0, name
        assert ours["rms_rel_error_pct"] < 1.15 * floor, name
    assert (
        report["methods"]["mirrorgonio_optimal"]["rms_rel_error_pct"]
        <= report["methods"]["mirrorgonio_poisson"]["rms_rel_error_pct"]
    )


def test_measured_peers_are_compared(report):
    ours = report["methods"]["mirrorgonio_optimal"]
    for peer in report["peers_measured"]:
        entry = report["methods"][peer]
        assert entry["status"] == "ok"
        assert entry["pixels_compared"] == ours["pixels_compared"]
        assert report[f"speedup_vs_{peer}"] > 0
        assert {"speedup", "at_least_3x_faster", "error_not_higher"} <= set(report["target_per_peer"][peer])
    # OpenCV is a core dependency and (from version 5) merges 16-bit images.
    opencv = report["methods"]["opencv_debevec"]["status"]
    assert opencv == "ok" or opencv.startswith("rejects 16-bit input")


def test_missing_peers_are_reported_not_fatal(monkeypatch):
    for module in ("HDRutils", "HDRutils.merge", "colour_hdri", "colour_demosaicing"):
        monkeypatch.setitem(sys.modules, module, None)  # importing it now raises ImportError
    result = bench_hdr(**{**TINY, "positions": 1})
    for peer in ("hdrutils", "colour_hdri"):
        assert result["methods"][peer]["status"].startswith("not installed")
        assert result[f"speedup_vs_{peer}"] is None
    assert result["methods"]["mirrorgonio_optimal"]["status"] == "ok"


def test_no_peers():
    result = bench_hdr(**{**TINY, "positions": 1}, peers=False)
    assert all(result["methods"][p]["status"].startswith("skipped") for p in PEERS)
    assert result["meets_target"] is None


def test_bad_size_is_one_line():
    with pytest.raises(BenchmarkError, match="width: must be an even number"):
        bench_hdr(width=201, height=160)
    result = CliRunner().invoke(app, ["bench", "hdr", "--width", "201", "--height", "160", "--json"])
    assert result.exit_code == 2
    assert result.output.strip().splitlines() == [
        "error: width: must be an even number of pixels, at least 4 (a Bayer mosaic), got 201"
    ]


def test_cli_prints_json():
    result = CliRunner().invoke(
        app,
        [
            "bench",
            "hdr",
            "--positions",
            "1",
            "--exposures",
            "3",
            "--width",
            "200",
            "--height",
            "160",
            "--no-peers",
            "--json",
        ],
    )
    assert result.exit_code == 0, result.output
    data = json.loads(result.output)
    assert data["benchmark"] == "hdr"
    assert data["methods"]["mirrorgonio_optimal"]["status"] == "ok"


def test_a_speed_up_keeps_its_significant_digits_and_never_reads_zero():
    """A ratio is rounded to significant digits, not decimals; a peer whose demosaic, timed
    apart, outlasted its whole call (a busy host) is compared by its whole call."""
    assert significant(0.004321) == 0.00432 and significant(1234.5) == 1230.0
    assert merge_only_s(0.05, 0.02) == pytest.approx(0.03) and merge_only_s(0.05, 0.06) is None
    ours = {"status": "ok", "time_s": 0.002, "time_s_first_call": 0.003, "mean_abs_rel_error_pct": 1.0}
    ours["rms_rel_error_pct"] = 1.0
    peer = {**ours, "time_s": 0.05, "time_s_first_call": 0.06, "excluded_part_s": 0.07}  # no merge-only time
    missing = {"status": "not installed", "time_s": None}
    result = _speedups_and_target({"mirrorgonio_optimal": ours, "hdrutils": peer, "colour_hdri": missing})
    assert result["speedup_vs_hdrutils"] == pytest.approx(25.0)
    assert result["target_per_peer"]["hdrutils"]["speedup_first_call"] == pytest.approx(20.0)
    assert result["speedup_vs_colour_hdri"] is None and result["peers_measured"] == ["hdrutils"]
