"""`mirrorgonio bench ... --record PATH`: each benchmark's section of the generated markdown file,
added or replaced in place, the other sections left as they are."""

from __future__ import annotations

import json
import re

import pytest
from conftest import REDUCED_RIG
from typer.testing import CliRunner

from acquisition.benchmarks.record import (
    HEADER,
    RecordError,
    find_sections,
    record_result,
    result_tables,
    start_recording,
)
from acquisition.cli import app
from drivers.contracts.version import __version__

ACQUIRE = {
    "benchmark": "acquire",
    "frame_shape": [1312, 2000],
    "positions": 5,
    "engine_s_median": 1.234,
    "meets_target": True,
    "how": "a long explanation " * 10,
    "engine_s_all": [1.2, 1.3],
}


def _record(path, name, result, command=None):
    record_result(start_recording(path, command or f"mirrorgonio bench {name} --record {path}"), name, result)


def _section(text: str, name: str) -> str:
    start, end = find_sections(text)[name]
    return text[start:end]


def test_a_missing_file_is_made_with_its_header_and_the_section(tmp_path):
    path = tmp_path / "benchmarks.md"
    _record(path, "acquire", ACQUIRE, command="mirrorgonio bench acquire --positions 5 --record docs/benchmarks.md")
    text = path.read_text()
    assert text.startswith(HEADER) and "generated" in text and "never edit it by hand" in text.lower()
    section = _section(text, "acquire")
    assert section.startswith("<!-- bench:acquire -->\n") and section.endswith("<!-- /bench:acquire -->\n")
    assert "| command | `mirrorgonio bench acquire --positions 5 --record docs/benchmarks.md` |" in section
    assert re.search(r"\| date \| \d{4}-\d\d-\d\d \d\d:\d\d UTC \|\n\| duration \| \d+ s \|", section), section
    assert re.search(r"\| machine \| \d+ cores, .*, [0-9.]+ GB memory \|", section), section
    assert re.search(r"\| load average \(1 min\) \| [0-9.]+ before, [0-9.]+ after \|", section), section
    assert f"| software | mirrorgonio {__version__} |" in section
    # the result's scalar figures and short lists; explanations left out
    assert "| engine_s_median | 1.234 |" in section and "| meets_target | yes |" in section
    assert "| frame_shape | 1312, 2000 |" in section and "| how |" not in section


def test_a_section_is_replaced_in_place_and_the_others_are_untouched(tmp_path):
    path = tmp_path / "benchmarks.md"
    _record(path, "render", {"benchmark": "render", "render_s_median": 1.5})
    _record(path, "acquire", ACQUIRE)
    _record(path, "speed", {"benchmark": "speed", "markdown": "| `bench speed` | 200×132 |\n| --- | --- |"})
    before = path.read_text()
    _record(path, "acquire", {**ACQUIRE, "engine_s_median": 9.876})
    after = path.read_text()
    assert list(find_sections(after)) == ["render", "acquire", "speed"]
    for name in ("render", "speed"):
        assert _section(after, name) == _section(before, name)
    assert "9.876" in _section(after, "acquire") and "1.234" not in after
    # everything outside the replaced section is as it was
    start, end = find_sections(before)["acquire"]
    new_start, new_end = find_sections(after)["acquire"]
    assert after[:new_start] == before[:start] and after[new_end:] == before[end:]
    assert after.count("<!-- bench:acquire -->") == after.count("<!-- /bench:acquire -->") == 1


def test_sections_go_in_the_benchmarks_order_whatever_the_order_they_are_recorded_in(tmp_path):
    path = tmp_path / "benchmarks.md"
    for name in ("speed", "render", "tolerance", "acquire", "some-new-one"):
        _record(path, name, {"benchmark": name, "value": 1})
    assert list(find_sections(path.read_text())) == ["render", "acquire", "tolerance", "speed", "some-new-one"]


def test_a_benchmarks_own_table_is_the_result(tmp_path):
    table = "| rig description | fits |\n| --- | --- |\n| as taken | 1.64 % |"
    assert result_tables("tolerance", {"benchmark": "tolerance", "runs": [], "markdown": table}) == table + "\n"
    hdr = result_tables(
        "hdr",
        {
            "benchmark": "hdr",
            "positions": 3,
            "methods": {
                "mirrorgonio_optimal": {"status": "ok", "ms_per_position": 12.5, "rms_rel_error_pct": 1.1},
                "hdrutils": {"status": "not installed (pip install 'mirrorgonio[bench]')", "ms_per_position": None},
            },
            "speedup_vs_hdrutils": None,
        },
    )
    assert "| positions | 3 |" in hdr
    assert "| mirrorgonio_optimal | ok | 12.5 | — | 1.1 | — |  |" in hdr
    assert "| hdrutils | not installed (pip install 'mirrorgonio[bench]') | — |" in hdr
    accuracy = result_tables(
        "accuracy",
        {"benchmark": "accuracy", "sources": [{"name": "+u", "rms_rel_error": 0.004, "theta_min_deg": 2.5}]},
    )
    assert "| +u | 0.004 | 2.5–— | — | — |" in accuracy


def test_a_broken_file_is_refused_before_the_benchmark_runs_and_left_as_it_is(tmp_path):
    path = tmp_path / "benchmarks.md"
    broken = HEADER + "\n<!-- bench:render -->\n## `bench render`\n"
    path.write_text(broken)
    with pytest.raises(RecordError, match="section 'render' is not closed"):
        start_recording(path, "mirrorgonio bench acquire")
    path.write_text(broken + "<!-- /bench:acquire -->\n")
    with pytest.raises(RecordError, match="section 'acquire' closes where it was not open"):
        start_recording(path, "mirrorgonio bench acquire")
    assert path.read_text() == broken + "<!-- /bench:acquire -->\n"
    with pytest.raises(RecordError, match="does not exist"):
        start_recording(tmp_path / "no-such-folder" / "benchmarks.md", "mirrorgonio bench acquire")


def test_the_command_records_its_section(tmp_path):
    path = tmp_path / "benchmarks.md"
    args = ["bench", "render", "--rig", str(REDUCED_RIG), "--repeat", "1", "--json", "--record", str(path)]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    printed = json.loads(result.stdout.strip().splitlines()[-1])
    assert printed["benchmark"] == "render"
    section = _section(path.read_text(), "render")
    assert f"| command | `mirrorgonio bench render --rig {REDUCED_RIG} --repeat 1 --json --record {path}` |" in section
    assert f"| render_s_median | {printed['render_s_median']:.6g} |" in section
    bad = CliRunner().invoke(app, ["bench", "render", "--record", str(tmp_path / "nowhere" / "b.md")])
    assert bad.exit_code == 2 and "error: --record: " in bad.output


def test_the_repeatability_spread_and_its_tables():
    """bench repeatability's spread over seeds: each source's mean offset, its standard deviation
    (sample, ddof 1), the worst distance, the quoted 1σ against that spread; then its section's
    tables."""
    from acquisition.benchmarks.repeatability import spread

    def row(seed, du, found=2):
        quoted = {"centre_sigma_um": [20.0, 5.0], "fit": {"a": 1.0 + du / 1000}, "fit_sigma": {"a": 0.01}}
        sources = [
            {"name": "a", "centre_offset_um": [du, 0.0], "centre_error_um": abs(du), "rms_rel_error": 0.004, **quoted},
            {"name": "b", "centre_offset_um": [0.0, 2 * du], "centre_error_um": abs(2 * du), "rms_rel_error": 0.006}
            | quoted,
        ]
        result = {"sources": sources, "sources_found": found, "max_rms_rel_error": 0.006, "quality": {"status": "ok"}}
        return {"seed": seed, "result": {**result, "process_s": 80.0}}

    out = spread([row(0, 10.0), row(1, -30.0), row(2, 50.0, found=3)])
    assert out["sources"]["a"]["mean_offset_um"] == [10.0, 0.0]
    assert out["sources"]["a"]["std_um"] == [40.0, 0.0]
    assert out["sources"]["b"]["std_um"] == [0.0, 80.0] and out["sources"]["b"]["worst_distance_um"] == 100.0
    assert out["worst_distance_um"] == 100.0 and out["all_within_100_um"] is True  # 100 µm is within
    assert out["all_five_found"] is False  # seed 2 found a third source
    # a: u spread 40 µm against 20 quoted, v none to compare; the peak 1.01 ± 0.04 against 0.01
    a = out["sources"]["a"]
    assert a["quoted_sigma_um"] == [20.0, 5.0] and a["quoted_over_spread"][:2] == [0.5, None]
    assert a["peak_spread_rel"] == pytest.approx(0.04 / 1.01, abs=1e-5)
    assert a["quoted_over_spread"][2] == 0.25
    assert out["quoted_within_1_5x"] == "0/4"
    text = result_tables("repeatability", {"benchmark": "repeatability", "seeds": 3, **out})
    assert "| a | 10, 0 | 40, 0 | 20, 5 | 0.0396, 0.00992 | 0.5, —, 0.25 | 50 | 0.004 |" in text
    assert "| 2 | 3 | 100 | 0.006 | ok | 80 |" in text


def test_an_old_header_is_brought_up_to_date_and_the_sections_kept(tmp_path):
    path = tmp_path / "benchmarks.md"
    _record(path, "render", {"benchmark": "render", "render_s_median": 1.5})
    old = path.read_text().replace("speed, lab)", "speed)")  # a header from before `bench lab`
    path.write_text(old)
    _record(path, "acquire", ACQUIRE)
    now = path.read_text()
    assert "speed, lab)" in now and _section(now, "render") == _section(old, "render")
    mine = tmp_path / "mine.md"  # a file that is not the generated one: left as it is
    mine.write_text("# My notes\n\n")
    _record(mine, "render", {"benchmark": "render", "render_s_median": 1.5})
    assert mine.read_text().startswith("# My notes\n\n<!-- bench:render -->")
