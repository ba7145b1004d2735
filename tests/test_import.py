"""`mirrorgonio import`: real raw files (DNGs written like a camera's) into a run file.

Every raw file here is a real DNG written by :func:`sim_devices.dng.write_dng` (or by the
simulated camera) and decoded by the same :func:`drivers.raw_decode.decode_raw` that reads
a real camera's NEF or CR2. Frames are small (64 x 48) so the tests stay fast.
"""

from __future__ import annotations

import math
import struct
from pathlib import Path

import numpy as np
import pytest
from conftest import REDUCED_RIG
from typer.testing import CliRunner

from acquisition.cli import app
from acquisition.importer import RunImportError, format_ranges, import_run
from drivers.contracts.rig import load_rig
from drivers.contracts.runfile import RunFile
from processing.options import ProcessingOptions
from sim_devices.dng import write_dng

runner = CliRunner()
WIDTH, HEIGHT = 64, 48
T0 = 1_760_000_000.0
PER_SITE_BLACK = np.array([[60, 61], [62, 63]])


@pytest.fixture()
def tiny_rig(tmp_path) -> Path:
    path = tmp_path / "tiny.toml"
    path.write_text(f"[camera]\nwidth = {WIDTH}\nheight = {HEIGHT}\n")
    return path


def _mosaic(seed: int, shape=(HEIGHT, WIDTH)) -> np.ndarray:
    return np.random.default_rng(seed).integers(64, 4095, size=shape, dtype=np.uint16)


def write_frames(folder: Path, specs) -> dict[str, np.ndarray]:
    """DNGs named ``name`` with ``exposure_s``; their mosaics by name."""
    folder.mkdir(parents=True, exist_ok=True)
    mosaics = {}
    for k, (name, exposure_s, *shape) in enumerate(specs):
        mosaic = _mosaic(k, tuple(shape[0]) if shape else (HEIGHT, WIDTH))
        write_dng(folder / name, mosaic, exposure_s=exposure_s, black_level=PER_SITE_BLACK, timestamp=T0 + k)
        mosaics[name] = mosaic
    return mosaics


def write_csv(path: Path, *lines: str) -> Path:
    path.write_text("\n".join(lines) + "\n")
    return path


def leftovers(folder: Path) -> list[str]:
    """Anything an import may have left in the output's folder."""
    return sorted(p.name for p in folder.iterdir())


# --- a good import ---------------------------------------------------------------------------
def test_import_builds_a_run_file_holding_the_files_mosaics(tmp_path, tiny_rig):
    raw = tmp_path / "raw"
    mosaics = write_frames(
        raw,
        [
            ("a1.dng", 0.001),
            ("a2.dng", 0.004),
            ("b1.dng", 0.001),
            ("b2.dng", 1 / 250),
            ("c1.dng", 0.5),
            ("stray.dng", 0.01),
        ],
    )
    csv = write_csv(
        tmp_path / "positions.csv",
        "file,position,exposure_s,x_m,y_m,z_m,rx_deg,ry_deg,rz_deg",
        "a2.dng,5,,,,,,,",
        "a1.dng,5,,,,,,,",
        "b1.dng,6,,0.01,0.02,0.3,180,0,90",
        "",
        "b2.dng, 6 ,,,,,,,",
        f"{raw / 'c1.dng'},7,0.002,,,,,,",
    )
    out = tmp_path / "runs" / "imported.h5"
    result = runner.invoke(
        app,
        [
            "import",
            str(raw),
            "--csv",
            str(csv),
            "--rig",
            str(tiny_rig),
            "--out",
            str(out),
            "--operator",
            "Ada",
            "--notes",
            "bench test",
        ],
    )
    assert result.exit_code == 0, result.output
    assert f"imported 5 frames into {out} (run imported): 3 of 66 positions, 64x48 RGGB" in result.output
    assert "positions without frames (left incomplete): 0-4, 8-65" in result.output
    assert "exposure times from the CSV for 1 frames" in result.output
    assert "1 raw files in" in result.output and "stray.dng" in result.output
    assert leftovers(out.parent) == ["imported.h5"]  # no temporary or lock file left behind

    rig = load_rig(tiny_rig)
    with RunFile.open(out) as run:
        assert run.n_positions == 66 and run.frame_shape == (HEIGHT, WIDTH) and run.max_exposures == 2
        assert run.completed_positions().tolist() == [5, 6, 7]
        assert run.status == "complete" and "positions 0-4, 8-65 have none" in run.status_message
        # frames in the CSV's order within a position, equal to the files' mosaics
        np.testing.assert_array_equal(run.frames(5), np.stack([mosaics["a2.dng"], mosaics["a1.dng"]]))
        np.testing.assert_array_equal(run.frames(6), np.stack([mosaics["b1.dng"], mosaics["b2.dng"]]))
        np.testing.assert_array_equal(run.frames(7), mosaics["c1.dng"][None])
        assert run.exposures(5).tolist() == [0.004, 0.001]
        assert run.exposures(6).tolist() == [0.001, 0.004]
        assert run.exposures(7).tolist() == [0.002]  # the CSV's exposure, not the file's 0.5 s
        np.testing.assert_array_equal(run.black_level(5)[0], PER_SITE_BLACK)
        assert run.white_level(5).tolist() == [4095, 4095] and run.cfa_pattern(6) == ["RGGB", "RGGB"]
        assert run.timestamps(5)[0] == pytest.approx(T0 + 1, abs=1e-3)
        times = run.times(5)
        assert (times.move_started, times.frames_done) == pytest.approx((T0, T0 + 1), abs=1e-3)
        # the planned pose unless the CSV gives one (metres, degrees -> radians)
        assert run.measured_pose(5) == rig.tool_poses()[5]
        pose = run.measured_pose(6)
        assert pose.as_tuple() == pytest.approx((0.01, 0.02, 0.3, math.pi, 0.0, math.pi / 2))
        header = run.header
        assert header.run_id == "imported" and header.preset == "import"
        assert header.tool_poses == rig.tool_poses() and header.light_poses == rig.light_poses()
        assert header.rig == rig
        assert header.bracket["mode"] == "auto"  # positions differ in their exposures
        assert header.metadata["operator"] == "Ada" and header.metadata["notes"] == "bench test"
        assert header.metadata["imported_from"]["csv"] == str(csv.resolve())
        assert "simulated pinhole camera" in header.devices["camera"]


def test_a_common_bracket_is_recorded_as_fixed(tmp_path, tiny_rig):
    raw = tmp_path / "raw"
    write_frames(raw, [("p0-1.dng", 0.01), ("p0-2.dng", 0.001), ("p1-1.dng", 0.001), ("p1-2.dng", 0.01)])
    csv = write_csv(tmp_path / "p.csv", "position,file", "0,p0-1.dng", "0,p0-2.dng", "1,p1-1.dng", "1,p1-2.dng")
    report = import_run(raw, csv, tiny_rig, tmp_path / "run.h5", run_id="run-x")
    assert report.positions_with_frames == [0, 1] and report.empty_positions == list(range(2, 66))
    with RunFile.open(tmp_path / "run.h5") as run:
        assert run.header.bracket == {"mode": "fixed", "exposures_s": [0.001, 0.01], "source": "import"}
        assert run.header.run_id == "run-x"


def test_calibration_frames_are_imported_by_their_role(tmp_path, tiny_rig):
    raw = tmp_path / "raw"
    specs = [("s1.dng", 0.001), ("s2.dng", 0.004), ("amb1.dng", 0.02), ("amb2.dng", 0.08)]
    specs += [("dark1.dng", 0.02), ("dark2.dng", 0.02), ("late.dng", 0.02)]
    mosaics = write_frames(raw, specs)
    csv = write_csv(
        tmp_path / "p.csv",
        "file,position,role,when,exposure_s",
        "amb1.dng,,ambient,,",
        "s1.dng,0,,,",
        "amb2.dng,,Ambient,before,",
        "dark1.dng,,dark,,",
        "dark2.dng,,dark,before,0.03",  # a repeated exposure is fine in a calibration set
        "s2.dng,0,sweep,,",
        "late.dng,,ambient,after,",
    )
    out = tmp_path / "run.h5"
    report = import_run(raw, csv, tiny_rig, out)
    assert report.positions_with_frames == [0] and report.frames == 7 and report.exposures_s == [0.001, 0.004]
    assert report.calibration_sets == {"ambient before": 2, "ambient after": 1, "dark before": 2}
    with RunFile.open(out) as run:
        assert run.header.calibration == {
            "switch": "import",
            "sets": [["ambient", "before"], ["ambient", "after"], ["dark", "before"]],
        }
        np.testing.assert_array_equal(run.frames(0), np.stack([mosaics["s1.dng"], mosaics["s2.dng"]]))
        ambient = run.calibration_frames("ambient")
        np.testing.assert_array_equal(ambient.frames, np.stack([mosaics["amb1.dng"], mosaics["amb2.dng"]]))
        assert ambient.exposures_s.tolist() == [0.02, 0.08] and ambient.cfa_pattern == "RGGB"
        np.testing.assert_array_equal(ambient.black_level, PER_SITE_BLACK)
        assert ambient.timestamps.tolist() == pytest.approx([T0 + 2, T0 + 3], abs=1e-3)
        dark = run.calibration_frames("dark", "before")
        np.testing.assert_array_equal(dark.frames, np.stack([mosaics["dark1.dng"], mosaics["dark2.dng"]]))
        assert dark.exposures_s.tolist() == [0.02, 0.03]
        np.testing.assert_array_equal(run.calibration_frames("ambient", "after").frames, mosaics["late.dng"][None])
        assert run.calibration_frames("dark", "after") is None
    # Without a role column every frame is the sweep's, and the run says it has no calibration frames.
    plain = write_csv(tmp_path / "plain.csv", "file,position", "s1.dng,1")
    import_run(raw, plain, tiny_rig, tmp_path / "plain.h5")
    with RunFile.open(tmp_path / "plain.h5") as run:
        assert run.calibration_sets() == [] and run.header.calibration["sets"] == []


def test_format_ranges():
    assert format_ranges([8, 0, 1, 2, 5, 7]) == "0-2, 5, 7-8"
    assert format_ranges([]) == ""


# --- bad input: one line, naming the row or the field, and nothing written -------------------
GOOD = [("a.dng", 0.001), ("b.dng", 0.004), ("c.dng", 0.004)]


@pytest.mark.parametrize(
    ("lines", "frames", "message"),
    [
        (["file,position", "a.dng,1", "nope.dng,1"], GOOD, "line 3: file: 'nope.dng' not found in"),
        (["file,position", "a.dng,1", "b.dng,2", "a.dng,3"], GOOD, "line 4: file: 'a.dng' repeats the frame of line 2"),
        (
            ["file,position", "a.dng,1", "./b.dng,1", "b.dng,2"],
            GOOD,
            "line 4: file: 'b.dng' repeats the frame of line 3",
        ),
        (
            ["file,position", "b.dng,1", "c.dng,1"],
            GOOD,
            "line 3: position 1 already has a frame of exposure 0.004 s (line 2): the frame is repeated",
        ),
        (
            ["file,position,exposure_s", "a.dng,1,0.01", "b.dng,1,0.01"],
            GOOD,
            "line 3: position 1 already has a frame of exposure 0.01 s (line 2)",
        ),
        (
            ["file,position", "a.dng,1", "b.dng,2"],
            [("a.dng", 0.001), ("b.dng", 0.004, (48, 80))],
            "line 3: b.dng is 80x48 but line 2 (a.dng) is 64x48: the frames mix sizes",
        ),
        (["file,position", "a.dng,66"], GOOD, "line 2: position: 66 is outside the rig's schedule (0 to 65)"),
        (["file,position", "a.dng,-1"], GOOD, "line 2: position: -1 is outside the rig's schedule (0 to 65)"),
        (["file,position", "a.dng,one"], GOOD, "line 2: position: 'one' is not a whole number"),
        (["file,position", "a.dng,"], GOOD, "line 2: position: empty"),
        (["file,exposure_s", "a.dng,0.1"], GOOD, "line 1: missing required column 'position'"),
        (["position", "1"], GOOD, "line 1: missing required column 'file'"),
        (["file,position,exposure", "a.dng,1,0.1"], GOOD, "line 1: unknown column 'exposure'"),
        (
            ["file,position,exposure_s", "a.dng,1,0"],
            GOOD,
            "line 2: exposure_s: must be a positive number of seconds (got '0')",
        ),
        (
            ["file,position,exposure_s", "a.dng,1,0.01", "b.dng,1,-0.5"],
            GOOD,
            "line 3: exposure_s: must be a positive number of seconds (got '-0.5')",
        ),
        (["file,position,exposure_s", "a.dng,1,fast"], GOOD, "line 2: exposure_s: 'fast' is not a number"),
        (["file,position,x_m,y_m,z_m", "a.dng,1,0,0,0"], GOOD, "line 1: missing column 'rx_deg'"),
        (["file,position,x_m,y_m,z_m,rx_deg,ry_deg,rz_deg", "a.dng,1,0,0,0.3,0,,0"], GOOD, "line 2: ry_deg: empty"),
        (
            ["file,position,x_m,y_m,z_m,rx_deg,ry_deg,rz_deg", "a.dng,1,0,0,0.3,0,0,0", "b.dng,1,0,0,0.3,0,0,1"],
            GOOD,
            "line 3: x_m..rz_deg: position 1 was given another pose on line 2",
        ),
        (["file,position", "a.dng,1,extra"], GOOD, "line 2: 3 fields but the header names 2 columns"),
        (["file,position"], GOOD, "no frames: the CSV has a header but no rows"),
        (["file,position,role", "a.dng,1,flat"], GOOD, "line 2: role: 'flat' is not one of sweep, ambient, dark"),
        (["file,position,role", "a.dng,1,ambient"], GOOD, "line 2: position: an ambient frame belongs to no position"),
        (
            ["file,position,role,when", "a.dng,,dark,during"],
            GOOD,
            "line 2: when: 'during' is not one of before, after",
        ),
        (
            ["file,position,when", "a.dng,1,after"],
            GOOD,
            "line 2: when: only for calibration frames (role ambient or dark), not sweep",
        ),
        (
            ["file,position,role,x_m,y_m,z_m,rx_deg,ry_deg,rz_deg", "a.dng,,dark,0,0,0.3,0,0,0"],
            GOOD,
            "line 2: x_m..rz_deg: a dark frame has no pose",
        ),
        (["file,position,role", "a.dng,,ambient"], GOOD, "no frames of the sweep: every row is a calibration frame"),
        (
            ["file,position,role,exposure_s", *(f"f{k}.dng,,dark,0.01" for k in range(17))],
            [(f"f{k}.dng", 0.01) for k in range(17)],
            "line 18: role: more than 16 dark frames before the sweep (at most 16 a set)",
        ),
        ([], GOOD, "empty CSV"),
    ],
)
def test_bad_input_is_one_line_and_writes_nothing(tmp_path, tiny_rig, lines, frames, message):
    raw = tmp_path / "raw"
    write_frames(raw, frames)
    csv = write_csv(tmp_path / "positions.csv", *lines)
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    result = runner.invoke(
        app, ["import", str(raw), "--csv", str(csv), "--rig", str(tiny_rig), "--out", str(out_dir / "run.h5")]
    )
    assert result.exit_code == 2, result.output
    assert len(result.output.strip().splitlines()) == 1, result.output
    assert result.output.startswith("error: ")
    assert message in result.output, result.output
    if "line " in message and "line 1:" not in message and "empty CSV" not in message:
        assert f"{csv}: line" in result.output  # the CSV is named with the line
    assert leftovers(out_dir) == []


def test_a_rig_whose_sensor_size_does_not_match_is_named(tmp_path, tiny_rig):
    raw = tmp_path / "raw"
    write_frames(raw, [("a.dng", 0.001, (40, 64))])
    csv = write_csv(tmp_path / "p.csv", "file,position", "a.dng,3")
    result = runner.invoke(
        app, ["import", str(raw), "--csv", str(csv), "--rig", str(tiny_rig), "--out", str(tmp_path / "r.h5")]
    )
    assert result.exit_code == 2
    assert result.output.strip() == (
        f"error: {tiny_rig}: camera.width x camera.height is 64x48 but the raw files are 64x40 (line 2: a.dng)"
    )
    assert not (tmp_path / "r.h5").exists()


def _strip_exposure_time(path: Path) -> None:
    """The file's ExposureTime entry (tag 33434, RATIONAL, count 1) renumbered to an unknown tag."""
    data = path.read_bytes()
    entry = struct.pack("<HHI", 33434, 5, 1)
    assert data.count(entry) == 1
    path.write_bytes(data.replace(entry, struct.pack("<HHI", 33435, 5, 1)))


def test_files_without_an_exposure_time_take_the_csvs_and_are_refused_without_it(tmp_path, tiny_rig):
    raw = tmp_path / "raw"
    mosaics = write_frames(raw, [("a.dng", 0.001), ("b.dng", 0.004)])
    _strip_exposure_time(raw / "b.dng")
    csv = write_csv(tmp_path / "p.csv", "file,position,exposure_s", "a.dng,3,", "b.dng,3,0.008")
    result = runner.invoke(
        app, ["import", str(raw), "--csv", str(csv), "--rig", str(tiny_rig), "--out", str(tmp_path / "r.h5")]
    )
    assert result.exit_code == 0, result.output
    with RunFile.open(tmp_path / "r.h5") as run:
        assert run.exposures(3).tolist() == [0.001, 0.008]  # a's from its file, b's from the CSV
        assert np.array_equal(run.frames(3)[1], mosaics["b.dng"])
    # Without the CSV's exposure, the file's missing one is named in one line, and nothing is written.
    csv = write_csv(tmp_path / "q.csv", "file,position", "a.dng,3", "b.dng,3")
    result = runner.invoke(
        app, ["import", str(raw), "--csv", str(csv), "--rig", str(tiny_rig), "--out", str(tmp_path / "s.h5")]
    )
    assert result.exit_code == 2
    assert (
        result.output.strip().startswith(f"error: {csv}: line 3: ")
        and "no exposure time in the file's metadata" in result.output
    )
    assert not (tmp_path / "s.h5").exists()


def test_a_file_that_is_not_raw_is_named_with_its_row(tmp_path, tiny_rig):
    raw = tmp_path / "raw"
    write_frames(raw, GOOD)
    (raw / "notes.dng").write_text("not a raw file at all")
    csv = write_csv(tmp_path / "p.csv", "file,position", "a.dng,0", "notes.dng,0")
    with pytest.raises(RunImportError) as err:
        import_run(raw, csv, tiny_rig, tmp_path / "r.h5")
    assert str(err.value).startswith(f"{csv}: line 3: {raw / 'notes.dng'}: decode: ")
    assert "\n" not in str(err.value)
    assert not (tmp_path / "r.h5").exists()


@pytest.mark.parametrize(
    ("setup", "message"),
    [
        ("no-folder", "no such folder"),
        ("no-csv", "CSV file not found"),
        ("bad-rig", "ball.radius_m: must be > 0"),
        ("exists", "already exists"),
    ],
)
def test_bad_paths_are_named(tmp_path, tiny_rig, setup, message):
    raw = tmp_path / "raw"
    write_frames(raw, GOOD)
    csv = write_csv(tmp_path / "p.csv", "file,position", "a.dng,0")
    rig, out = tiny_rig, tmp_path / "r.h5"
    if setup == "no-folder":
        raw = tmp_path / "nowhere"
    elif setup == "no-csv":
        csv = tmp_path / "missing.csv"
    elif setup == "bad-rig":
        rig = tmp_path / "bad.toml"
        rig.write_text("[ball]\nradius_m = -0.01\n")
    elif setup == "exists":
        out.write_bytes(b"precious")
    result = runner.invoke(app, ["import", str(raw), "--csv", str(csv), "--rig", str(rig), "--out", str(out)])
    assert result.exit_code == 2
    assert len(result.output.strip().splitlines()) == 1 and result.output.startswith("error: ")
    assert message in result.output, result.output
    if setup == "exists":
        assert out.read_bytes() == b"precious"
    else:
        assert not out.exists()


def test_a_failure_while_writing_leaves_nothing(tmp_path, tiny_rig, monkeypatch):
    """Even past the checks (a file changed, the disk filled), no half-built run remains."""
    import acquisition.importer as importer

    raw = tmp_path / "raw"
    write_frames(raw, [("a.dng", 0.001), ("b.dng", 0.004), ("c.dng", 0.01)])
    csv = write_csv(tmp_path / "p.csv", "file,position", "a.dng,0", "b.dng,1", "c.dng,2")
    real, calls = importer._decode, []

    def failing(row, csv_path):
        calls.append(row.line)
        if len(calls) == 5:  # the second file of the writing stage
            raise RunImportError(f"{csv_path}: line {row.line}: disk on fire")
        return real(row, csv_path)

    monkeypatch.setattr(importer, "_decode", failing)
    out_dir = tmp_path / "out"
    with pytest.raises(RunImportError, match="line 3: disk on fire"):
        import_run(raw, csv, tiny_rig, out_dir / "run.h5")
    assert leftovers(out_dir) == []


# --- an imported run processes -----------------------------------------------------------------
def test_an_imported_simulated_capture_processes(tmp_path):
    """Frames captured by the simulated camera as DNGs, imported, then merged to HDR."""
    from processing.light_run.run import process_run
    from processing.results import Results
    from sim_devices.camera import SimulatedCamera
    from sim_devices.world import SimWorld

    rig = load_rig(REDUCED_RIG)
    tools = rig.tool_poses()
    here = {"pose": tools[0]}
    raw = tmp_path / "captures"
    camera = SimulatedCamera(rig, SimWorld(lambda: here["pose"]), raw, seed=5)
    lines, written = ["file,position"], {}
    for index in (30, 33):
        here["pose"] = tools[index]
        for exposure in (0.0002, 0.002, 0.02):
            name = f"pos{index}-{exposure:g}.dng"
            camera.capture_to(raw / name, exposure)
            written[name] = camera.last_mosaic
            lines.append(f"{name},{index}")
    csv = write_csv(tmp_path / "positions.csv", *lines)
    run_path = tmp_path / "imported.h5"
    result = runner.invoke(
        app, ["import", str(raw), "--csv", str(csv), "--rig", str(REDUCED_RIG), "--out", str(run_path)]
    )
    assert result.exit_code == 0, result.output
    with RunFile.open(run_path) as run:
        for k, name in enumerate(n for n in written if n.startswith("pos33")):
            np.testing.assert_array_equal(run.frame(33, k).mosaic, written[name])
    report = process_run(run_path, tmp_path / "results", ProcessingOptions.checked(steps=("hdr",)))
    assert report.positions == 2
    with Results.open(report.results_file) as results:
        assert results.hdr_done.nonzero()[0].tolist() == [30, 33]
        radiance = results.radiance(33)
        assert np.isfinite(radiance).any() and np.nanmax(radiance) > 0
