"""The rig description: the default geometry, schedules, and one-line refusals."""

import math
import re

import numpy as np
import pytest

from drivers.contracts.rig import DEFAULT_RIG_PATH, RigError, load_rig, rig_from_dict
from drivers.pose import Pose


def _default_data():
    import tomllib

    return tomllib.loads(DEFAULT_RIG_PATH.read_text())


def test_default_rig_matches_the_measurement_page():
    rig = load_rig()
    poses = rig.light_poses()
    assert len(poses) == 66
    np.testing.assert_allclose(poses[0].position, [-0.08125, 0.04, 0.10], atol=1e-12)
    np.testing.assert_allclose(poses[-1].position, [0.08125, 0.04, 0.10], atol=1e-12)
    np.testing.assert_allclose(np.diff([p.x for p in poses]), 0.0025, atol=1e-12)
    # The light axis (+z) aims at the ball centre from the middle position; +x along rig +x.
    rot = poses[0].rotation
    middle = np.array([0.0, 0.04, 0.10])
    np.testing.assert_allclose(rot[:, 2], -middle / np.linalg.norm(middle), atol=1e-12)
    np.testing.assert_allclose(rot[:, 0], [1.0, 0.0, 0.0], atol=1e-12)
    # Camera 20 cm from the ball on +z, looking at it, rig +y up in the image.
    r, t = rig.camera.pose.extrinsics()
    np.testing.assert_allclose(rig.camera.centre(), [0, 0, 0.2], atol=1e-12)
    ball_in_cam = r @ np.zeros(3) + t
    np.testing.assert_allclose(ball_in_cam, [0, 0, 0.2], atol=1e-12)
    up_in_image = r @ np.array([0.0, 1.0, 0.0])
    assert up_in_image[1] < -0.99  # OpenCV's image y points down
    assert rig.camera.f_number == pytest.approx(125.0)
    # Identity light-to-tool: tool poses are the light poses.
    assert rig.tool_poses()[5].distance_to(poses[5])[0] == pytest.approx(0.0, abs=1e-12)


def test_chrome_normal_reflectance_is_about_055():
    rig = load_rig()
    n, k = np.array(rig.ball.n), np.array(rig.ball.k)
    r0 = ((n - 1) ** 2 + k**2) / ((n + 1) ** 2 + k**2)
    assert np.all((r0 > 0.5) & (r0 < 0.6))


def test_light_to_tool_offsets_the_commanded_tool_pose():
    data = _default_data()
    data["light"]["light_to_tool"] = {"position_m": [0.0, 0.0, 0.05], "rotation_deg": [0, 0, 0]}
    rig = rig_from_dict(data)
    light, tool = rig.light_poses()[10], rig.tool_poses()[10]
    # Composing back gives the light pose; the tool sits 5 cm behind the light plane.
    back = tool.compose(rig.light.light_to_tool.to_pose())
    assert back.distance_to(light)[0] < 1e-12
    np.testing.assert_allclose(light.position - tool.position, 0.05 * light.rotation[:, 2], atol=1e-12)


def test_the_arms_base_frame_places_its_tool_poses_in_the_rig():
    """The arm's tool poses are in its base frame: commanded to ``base⁻¹ ∘ light ∘ mount⁻¹``,
    the light lands on the schedule's pose in the rig frame, as the simulated world and the
    processing compose it."""
    from processing.trace import RigGeometry, light_pose_at
    from sim_devices.world import SimWorld

    data = _default_data()
    data["arm"]["base"] = {"position_m": [0.03, -0.02, 0.01], "rotation_deg": [0.5, -1.0, 10.0]}
    data["light"]["light_to_tool"] = {"position_m": [0.0, 0.01, 0.05], "rotation_deg": [2.0, 0.0, 0.0]}
    rig = rig_from_dict(data)
    geometry = RigGeometry.from_rig(rig)
    for light, tool in zip(rig.light_poses(), rig.tool_poses(), strict=True):
        assert rig.light_pose(tool).distance_to(light)[0] < 1e-12
        world = SimWorld(lambda tool=tool: tool, rig.light.light_to_tool.to_pose(), arm_base=rig.arm.base.to_pose())
        assert world.light_pose().distance_to(light)[0] < 1e-12
        assert light_pose_at(geometry, tool).distance_to(light)[0] < 1e-12
    # The tool poses differ from those of an arm whose frame is the rig's: the base moves them.
    in_rig_frame = rig_from_dict(_default_data() | {"light": data["light"]})
    assert rig.tool_poses()[0].distance_to(in_rig_frame.tool_poses()[0])[0] > 0.02


def test_a_version_1_rig_loads_with_the_arm_in_the_rig_frame_and_default_tolerances(tmp_path):
    text = DEFAULT_RIG_PATH.read_text().replace("schema_version = 2", "schema_version = 1")
    (tmp_path / "old.toml").write_text(text)
    old, new = load_rig(tmp_path / "old.toml"), load_rig()
    assert old.schema_version == 1 and new.schema_version == 2
    assert old.arm.base.to_pose() == Pose(0.0, 0.0, 0.0) and old.tolerances == new.tolerances
    assert [p.as_tuple() for p in old.tool_poses()] == [p.as_tuple() for p in new.tool_poses()]


def test_tolerances_are_read_and_checked(tmp_path):
    data = _default_data()
    data["tolerances"] = {"camera_rotation_deg": 0.1, "pinhole_fraction": 0.05}
    rig = rig_from_dict(data)
    assert rig.tolerances.camera_rotation_deg == 0.1 and rig.tolerances.pinhole_fraction == 0.05
    assert rig.tolerances.arm_base_position_m == 0.003  # the others keep their defaults
    for bad in ({"camera_rotation_deg": 0.0}, {"pinhole_fraction": 0.7}, {"camera_yaw_deg": 0.1}):
        with pytest.raises(RigError, match="tolerances"):
            rig_from_dict(_default_data() | {"tolerances": bad})


def test_raster_object_arc_and_pose_list_schedules():
    data = _default_data()
    data["schedule"] = {"kind": "raster", "count_u": 3, "count_v": 2}
    raster = rig_from_dict(data).light_poses()
    assert len(raster) == 6
    np.testing.assert_allclose(raster[1].position - raster[0].position, [0.0025, 0, 0])
    np.testing.assert_allclose(raster[3].position - raster[0].position, [0, 0.0025, 0])

    data["schedule"] = {"kind": "object-arc"}
    data["arm"]["soft_limits"]["z_m"] = [0.0, 0.45]
    arc = rig_from_dict(data).light_poses()
    assert len(arc) == 5
    for pose, angle in zip(arc, [10, 20, 30, 40, 50], strict=True):
        assert np.linalg.norm(pose.position) == pytest.approx(0.30)
        elevation = math.degrees(math.atan2(pose.y, pose.z))
        assert elevation == pytest.approx(angle)
        # Each light looks at the object.
        np.testing.assert_allclose(pose.rotation[:, 2], -pose.position / 0.30, atol=1e-12)

    data["schedule"] = {"kind": "poses", "poses": [{"position_m": [0.0, 0.05, 0.1], "rotation_deg": [160, 0, 0]}]}
    (single,) = rig_from_dict(data).light_poses()
    assert math.degrees(single.rx) == pytest.approx(160)


def test_an_object_dome_covers_rings_of_the_hemisphere_aimed_at_the_object():
    data = _default_data()
    data["arm"]["soft_limits"] = {"x_m": [-0.3, 0.3], "y_m": [-0.3, 0.3], "z_m": [0.0, 0.45]}
    data["schedule"] = {"kind": "object-dome", "centre_m": [0.0, 0.0, 0.01]}
    dome = rig_from_dict(data).light_poses()
    assert len(dome) == 4 + 8 + 10 + 12 + 14
    centre = np.array([0.0, 0.0, 0.01])
    offsets = np.array([p.position for p in dome]) - centre
    assert np.linalg.norm(offsets, axis=1) == pytest.approx(np.full(len(dome), 0.25))
    polar = np.degrees(np.arccos(offsets[:, 2] / 0.25))
    rings = np.repeat([12.0, 27.0, 42.0, 57.0, 72.0], [4, 8, 10, 12, 14])
    assert polar == pytest.approx(rings)
    for pose, offset in zip(dome, offsets, strict=True):  # each light looks at the object
        np.testing.assert_allclose(pose.rotation[:, 2], -offset / 0.25, atol=1e-12)
    azimuth = np.degrees(np.arctan2(offsets[:, 1], offsets[:, 0]))
    assert sorted(np.round(azimuth[4:12] % 360, 6)) == pytest.approx(22.5 + 45.0 * np.arange(8))  # interleaved
    # Walked back and forth: the step from one ring to the next is short.
    assert np.linalg.norm(dome[12].position - dome[11].position) < 0.1

    data["schedule"] = {"kind": "object-dome", "radius_m": [0.2, 0.3], "polar_deg": [20.0, 40.0], "counts": [3, 5]}
    two = rig_from_dict(data).light_poses()
    assert [round(float(np.linalg.norm(p.position)), 9) for p in two] == [0.2] * 3 + [0.3] * 5
    for bad, field in (
        ({"polar_deg": [20.0, 40.0], "counts": [3]}, "counts: 1 rings, but polar_deg has 2"),
        ({"polar_deg": [95.0], "counts": [3]}, "polar_deg[0]: must be < 90"),
        ({"radius_m": [0.2], "polar_deg": [20.0, 40.0], "counts": [3, 3]}, "radius_m: 1 distances for 2 rings"),
    ):
        data["schedule"] = {"kind": "object-dome", **bad}
        assert field in _error(data)


def _error(data) -> str:
    with pytest.raises(RigError) as info:
        rig_from_dict(data, "bad.toml")
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith("bad.toml: ")
    return message


@pytest.mark.parametrize(
    ("edit", "pattern"),
    [
        (lambda d: d["ball"].__setitem__("radius_m", -0.01), r"ball\.radius_m: must be > 0 \(got -0\.01\)"),
        (
            lambda d: d["camera"]["pose"].__setitem__("position_m", [0.0, 0.0, 0.01]),
            r"camera\.pose: the camera is inside the ball",
        ),
        (
            lambda d: d["schedule"].__setitem__("start_m", [0.0, 0.0, 0.01]),
            r"schedule: position 0: the light is inside the ball",
        ),
        (
            lambda d: d["schedule"].update(
                start_m=[0.0, 0.0, 0.1], step_m=[0.0, 0.0, -0.05], count=5, orientation={"rotation_deg": [180, 0, 0]}
            ),
            r"schedule: .*(inside the ball|crosses the ball)",
        ),
        (
            lambda d: d["schedule"].update(
                start_m=[-0.2, 0.0, 0.03], step_m=[0.1, 0.0, 0.0], count=5, orientation={"rotation_deg": [180, 0, 0]}
            ),
            r"schedule: the light's path from position 1 to 2 crosses the ball",
        ),
        (
            lambda d: d["arm"]["soft_limits"].__setitem__("x_m", [-0.05, 0.05]),
            r"schedule: position 0: tool pose x=-0\.081250 m outside the soft limits .*arm\.soft_limits",
        ),
        (lambda d: d["camera"].__setitem__("width", 0), r"camera\.width: must be > 0 \(got 0\)"),
        (lambda d: d["camera"].__setitem__("colour", "red"), r"camera\.colour: unknown field"),
        (lambda d: d["schedule"].__setitem__("kind", "spiral"), r"schedule: .*(discriminator|tag|does not match)"),
        (
            lambda d: d["camera"].__setitem__("black_level_dn", 5000),
            r"camera: black_level_dn must be below the white level",
        ),
        # inf and nan are TOML literals; before, a camera at nan was accepted and every ray came out nan.
        (
            lambda d: d["camera"]["pose"].__setitem__("position_m", [0.0, 0.0, math.nan]),
            r"camera\.pose\.position_m\[2\]: Input should be a finite number \(got nan\)",
        ),
        (
            lambda d: d["ball"].__setitem__("radius_m", math.inf),
            r"ball\.radius_m: Input should be a finite number \(got inf\)",
        ),
        (
            lambda d: d["schedule"].__setitem__("step_m", [-math.inf, 0.0, 0.0]),
            r"schedule\.light-sweep\.step_m\[0\]: Input should be a finite number \(got -inf\)",
        ),
        # Finite but absurd: 1e300 squared to inf in the geometry, which then said "the camera
        # is inside the ball" (or warned of overflow); a count of 1e12 tried to build the schedule.
        (
            lambda d: d["camera"]["pose"].__setitem__("position_m", [0.0, 0.0, 1e300]),
            r"camera\.pose\.position_m: 1e\+300 m is beyond the ±1000 m allowed$",
        ),
        (
            lambda d: d["camera"]["pose"].__setitem__("up", [0.0, 1e300, 0.0]),
            r"camera\.pose\.up: 1e\+300 is beyond the ±1e\+12 allowed$",
        ),
        (
            lambda d: d["light"]["light_to_tool"].__setitem__("rotation_deg", [0.0, 400.0, 0.0]),
            r"light\.light_to_tool\.rotation_deg: 400° is beyond the ±360° allowed$",
        ),
        (
            lambda d: d["schedule"].__setitem__("count", 10**12),
            r"schedule\.light-sweep\.count: must be <= 100000 \(got 1000000000000\)",
        ),
        (
            lambda d: d.__setitem__("schedule", {"kind": "raster", "count_u": 1000, "count_v": 1000}),
            r"schedule\.raster: count_u × count_v = 1000000: more than 100000 positions",
        ),
        (lambda d: d["camera"].__setitem__("height", 10**9), r"camera\.height: must be <= 100000"),
    ],
)
def test_impossible_rigs_are_refused_naming_the_field(edit, pattern):
    data = _default_data()
    edit(data)
    assert re.search(pattern, _error(data)), _error(data)


def test_unreadable_files_get_one_line_errors(tmp_path):
    with pytest.raises(RigError, match=r"missing\.toml: rig file not found"):
        load_rig(tmp_path / "missing.toml")
    broken = tmp_path / "broken.toml"
    broken.write_text("[camera\nwidth = 3\n")
    with pytest.raises(RigError, match=r"broken\.toml: not valid TOML: .*line 1"):
        load_rig(broken)
