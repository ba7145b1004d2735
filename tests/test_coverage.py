"""The highlight coverage of a schedule, before a run: counts against the mirror geometry
worked out here, the dome against the arc, and the command's files and errors."""

from __future__ import annotations

import json
import math
import tomllib

import numpy as np
import pytest

from acquisition.cli import main
from drivers.contracts.rig import DEFAULT_RIG_PATH, load_rig, rig_from_dict
from processing import ReflectanceError, highlight_coverage, write_coverage
from sim_devices.objects import relief_plate_mesh, write_obj

ROOT = DEFAULT_RIG_PATH.parent


def plate_rig(tmp_path, schedule):
    """The default rig with a flat 24 × 16 cm plate facing the camera, a thin lens, a small sensor."""
    plate = write_obj(tmp_path / "plate.obj", relief_plate_mesh(size_m=(0.24, 0.16), spacing_m=0.02, bumps_mm=()))
    data = tomllib.loads(DEFAULT_RIG_PATH.read_text())
    data["camera"].update(
        width=240, height=160, pixel_pitch_m=100e-6, thin_lens={"focus_distance_m": 0.2, "f_number": 8.0}
    )
    data["camera"].pop("pinhole_diameter_m")
    data["arm"]["soft_limits"] = {"x_m": [-0.4, 0.4], "y_m": [-0.4, 0.4], "z_m": [0.0, 0.45]}
    data["schedule"] = schedule
    data["object"] = {"mesh": str(plate)}
    return rig_from_dict(data)


def test_counts_are_the_lights_whose_mirror_direction_the_lobe_reaches(tmp_path):
    rig = plate_rig(tmp_path, {"kind": "object-dome", "polar_deg": [10.0, 25.0], "counts": [3, 6], "radius_m": 0.3})
    alpha, fraction = 0.2, 0.25
    cover = highlight_coverage(rig, roughness=alpha, lobe_fraction=fraction, texture_size=64)
    assert cover.positions == 9

    # Where each superpixel's chief ray meets the plate z = 0, and the lobe there, worked out here.
    camera = rig.camera
    k = camera.camera_matrix()
    r, t = camera.pose.extrinsics()
    centre = -r.T @ np.asarray(t, float)
    rows, cols = np.mgrid[0:80, 0:120]
    d = np.stack([(2 * cols + 0.5 - k[0, 2]) / k[0, 0], (2 * rows + 0.5 - k[1, 2]) / k[1, 1], np.ones(rows.shape)], -1)
    d = d @ r
    points = centre + (-centre[2] / d[..., 2])[..., None] * d
    view = centre - points
    view /= np.linalg.norm(view, axis=-1, keepdims=True)
    expected = np.zeros(rows.shape, int)
    margin = np.zeros(rows.shape, bool)  # points where the lobe is within 2 % of the threshold
    for pose in rig.light_poses():
        towards = pose.position - points
        towards /= np.linalg.norm(towards, axis=-1, keepdims=True)
        half = towards + view
        cos_h = half[..., 2] / np.linalg.norm(half, axis=-1)
        lobe = alpha**4 / (cos_h**2 * (alpha**2 - 1) + 1) ** 2
        expected += lobe >= fraction
        margin |= np.abs(lobe / fraction - 1) < 0.02
    usable = cover.counts >= 0
    assert usable.mean() > 0.9  # the plate fills the view
    agree = usable & ~margin
    assert np.array_equal(cover.counts[agree], expected[agree])
    assert expected[agree].max() >= 2 and (expected[agree] == 0).any()  # a test with something in it
    # The UV map holds the same counts (u along x, v along y, row 0 at v = 1): texels are
    # means of the counts that land in them.
    seen = np.isfinite(cover.texture)
    assert seen.mean() > 0.5
    assert (
        np.nanmin(cover.texture) >= -1e-9 and np.nanmax(cover.texture) <= cover.counts.max() + 1e-9
    )  # fill: round-off
    u = (points[..., 0] + 0.12) / 0.24
    v = (points[..., 1] + 0.08) / 0.16
    texel = cover.texture[np.clip(((1 - v) * 64).astype(int), 0, 63), np.clip((u * 64).astype(int), 0, 63)]
    inside = agree & np.isfinite(texel)
    assert np.mean(np.abs(texel[inside] - expected[inside]) <= 0.5) > 0.8


def test_the_dome_gives_the_glazed_vase_highlights_the_arc_does_not(tmp_path):
    data = tomllib.loads((ROOT / "object-vase-glazed.toml").read_text())
    data["camera"].update(width=400, height=264, pixel_pitch_m=5 * 5.9e-6)
    data["object"]["mesh"] = str(ROOT / "objects" / "vase.obj")
    dome = rig_from_dict(data)
    data["schedule"] = {"kind": "object-arc"}
    data["arm"]["soft_limits"]["z_m"] = [0.0, 0.45]
    arc = rig_from_dict(data)
    share = {}
    for name, rig in (("dome", dome), ("arc", arc)):
        for alpha in (0.15, 0.35):
            share[name, alpha] = highlight_coverage(rig, roughness=alpha).share()
    assert share["dome", 0.35] > 0.75 and share["dome", 0.15] > 0.45
    assert share["arc", 0.35] < 0.5 * share["dome", 0.35]
    assert share["dome", 0.35] > share["dome", 0.15]  # a broader lobe is easier to meet

    written = write_coverage([highlight_coverage(dome, roughness=0.35, texture_size=128)], tmp_path / "plan")
    assert sorted(p.name for p in written) == ["coverage-uv-0.35.png", "coverage-view-0.35.png", "coverage.json"]
    (summary,) = json.loads((tmp_path / "plan" / "coverage.json").read_text())
    assert summary["positions"] == 48 and summary["share_with_highlight"] == pytest.approx(share["dome", 0.35])


def test_the_coverage_command_writes_its_plan_and_refuses_bad_input_in_one_line(tmp_path, capsys):
    rig = load_rig(ROOT / "object-vase-glazed.toml")
    assert rig.schedule.kind == "object-dome" and len(rig.light_poses()) == 48
    small = tmp_path / "small.toml"
    text = (ROOT / "object-vase-glazed.toml").read_text()
    text = text.replace("width = 2000", "width = 400").replace("height = 1312", "height = 264")
    text = text.replace("pixel_pitch_m = 5.9e-6", "pixel_pitch_m = 2.95e-5")
    small.write_text(text.replace('mesh = "objects/vase.obj"', f'mesh = "{ROOT / "objects" / "vase.obj"}"'))
    with pytest.raises(SystemExit) as done:
        main(["coverage", "--rig", str(small), "--roughness", "0.3", "--out", str(tmp_path / "out")])
    assert done.value.code == 0
    assert "0.3" in capsys.readouterr().out
    assert (tmp_path / "out" / "coverage-uv-0.3.png").stat().st_size > 0

    with pytest.raises(SystemExit) as done:
        main(["coverage", "--rig", str(DEFAULT_RIG_PATH)])
    assert done.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "no [object]" in err and "\n" not in err
    with pytest.raises(SystemExit) as done:
        main(["coverage", "--rig", str(small), "--roughness", "0"])
    assert done.value.code == 2 and "--roughness" in capsys.readouterr().err
    with pytest.raises(ReflectanceError, match="lobe_fraction"):
        highlight_coverage(rig, lobe_fraction=0.0)
    assert math.isfinite(highlight_coverage(load_rig(small), roughness=1.0).share())
