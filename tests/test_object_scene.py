"""The simulated object scene against answers computed here, not by the renderer.

Each check recomputes the physics of docs/measurement.md ("Diffuse reflectance under near
light") with its own small formulas: its own chief rays, its own plane intersections and shadow geometry, its own
irradiance ``E = I(θ, φ)·cos/d²`` and the aperture average of ``cos⁴β`` by quadrature.
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

import numpy as np
import pytest
import trimesh

from drivers.contracts.rig import DEFAULT_RIG_PATH, load_rig, look_rotation, rig_from_dict
from drivers.pose import Pose
from drivers.raw_decode import decode_raw
from sim_devices.brdf import brdf, specular_lobe
from sim_devices.camera import SimulatedCamera
from sim_devices.lights import TruthLight
from sim_devices.object_scene import ObjectSceneRenderer
from sim_devices.objects import (
    OBJECTS_DIR,
    SurfaceError,
    SurfaceTruth,
    load_surface,
    relief_plate_mesh,
    surface_finish_at,
    surface_truth_at,
    write_obj,
    write_shipped,
)
from sim_devices.world import SimWorld

ROOT = DEFAULT_RIG_PATH.parent.parent
K = 1000.0  # the default sensitivity_e_per_s
PITCH = 23.6e-6  # 4x the default pixel: 0.19 mm on the object at 20 cm
W, H = 240, 160


def object_rig(mesh_path, *, width=W, height=H, pitch=PITCH, focus=0.2, surface="uniform", **extra):
    """The default rig with an object, a thin lens (f/8) and a small sensor."""
    data = tomllib.loads(DEFAULT_RIG_PATH.read_text())
    data["camera"].update(
        width=width, height=height, pixel_pitch_m=pitch, thin_lens={"focus_distance_m": focus, "f_number": 8.0}
    )
    data["camera"].pop("pinhole_diameter_m")
    data["schedule"] = {"kind": "object-arc"}
    data["simulation"].update(diffraction=False, noise=False, surface=surface)
    data["object"] = {"mesh": str(mesh_path)}
    for key, value in extra.items():
        data[key] = value
    return rig_from_dict(data)


def single_emitter(intensity, centre=(0.0, 0.0), spectrum=(1.0, 1.0, 1.0)) -> TruthLight:
    return TruthLight.model_validate(
        {
            "emitters": [
                {"name": "e", "centre_m": centre, "radius_m": 0.5e-3, "spectrum": spectrum, "intensity": intensity}
            ]
        }
    )


def arc_pose(angle_deg, radius=0.30, x_hint=(1.0, 0.0, 0.0)) -> Pose:
    """The light on the object arc (rising from +z towards +y), aimed at the origin."""
    a = math.radians(angle_deg)
    direction = np.array([0.0, math.sin(a), math.cos(a)])
    return Pose.from_rotation(radius * direction, look_rotation(-direction, x_hint))


def chief_rays(rig, cols, rows):
    """Lens-centre rays through pixel centres: origin, unit directions (rig frame)."""
    cam = rig.camera
    r, _ = cam.pose.extrinsics()
    cx, cy = cam.principal_point
    d = np.stack(
        [(cols - cx) * cam.pixel_pitch_m, (rows - cy) * cam.pixel_pitch_m, np.full(cols.shape, cam.sensor_distance_m)],
        axis=-1,
    )
    d = d @ r
    return cam.centre(), d / np.linalg.norm(d, axis=-1, keepdims=True)


def mean_cos4_over_aperture(rig, cols, rows, n_r=24, n_a=48):
    """⟨cos⁴β⟩ over the aperture disc (midpoint quadrature in r², angle), per pixel centre.

    The sensor point sits at −s behind the lens, the aperture point at a: the ray's
    sensor-side segment is (a + s, f), β its angle to the axis.
    """
    cam = rig.camera
    f, a_max = cam.sensor_distance_m, cam.aperture_diameter_m / 2
    cx, cy = cam.principal_point
    sx, sy = (cols - cx) * cam.pixel_pitch_m, (rows - cy) * cam.pixel_pitch_m
    r = a_max * np.sqrt((np.arange(n_r) + 0.5) / n_r)
    t = 2 * math.pi * (np.arange(n_a) + 0.5) / n_a
    ax, ay = (r[:, None] * np.cos(t)).ravel(), (r[:, None] * np.sin(t)).ravel()
    q = (sx[..., None] + ax) ** 2 + (sy[..., None] + ay) ** 2
    return np.mean((f * f / (q + f * f)) ** 2, axis=-1)


def irradiance(points, normal, pose: Pose, emitter, intensity_fn):
    """E = I(θ, φ)·max(0, n·ω)/d² per point (the emitter a point at its centre)."""
    rot = pose.rotation
    p_e = pose.position + rot @ np.array([*emitter.centre_m, 0.0])
    w = p_e - points
    d = np.linalg.norm(w, axis=-1)
    local = (points - p_e) @ rot  # the direction from the emitter, light frame
    theta = np.arccos(np.clip(local[..., 2] / d, -1, 1))
    phi = np.arctan2(local[..., 1], local[..., 0])
    cos_n = np.clip(np.sum(w * normal, axis=-1) / d, 0, None)
    return np.where(local[..., 2] > 0, intensity_fn(theta, phi), 0.0) * cos_n / d**2, p_e


@pytest.fixture(scope="module")
def flat_plate(tmp_path_factory):
    path = tmp_path_factory.mktemp("plate") / "plate.obj"
    return write_obj(path, relief_plate_mesh(spacing_m=5e-3, bumps_mm=()))


def pixel_grid():
    rows, cols = np.mgrid[0:H, 0:W].astype(float)
    return cols, rows


# --- 1. analytic: a flat Lambertian plate -------------------------------------------------------
def test_flat_plate_matches_the_irradiance_formula(flat_plate):
    rig = object_rig(flat_plate)
    # An anisotropic lobe off the light's centre, with the light rolled: θ and φ both matter.
    intensity = {
        "model": "anisotropic-gaussian",
        "peak_w_sr": 2.0,
        "sigma_major_deg": 25.0,
        "sigma_minor_deg": 12.0,
        "azimuth_deg": 30.0,
    }
    truth = single_emitter(intensity, centre=(0.003, -0.002), spectrum=(1.0, 0.8, 0.6))
    pose = arc_pose(30.0, x_hint=(1.0, 0.4, 0.0))
    renderer = ObjectSceneRenderer(rig, truth, samples_per_pixel=16, diffraction=False, seed=3)
    rate = renderer.render(pose).rate

    cols, rows = pixel_grid()
    origin, d = chief_rays(rig, cols, rows)
    t = -origin[2] / d[..., 2]  # the plate is the plane z = 0
    points = origin + t[..., None] * d
    emitter = truth.emitters[0]
    e, _ = irradiance(points, np.array([0.0, 0.0, 1.0]), pose, emitter, emitter.intensity)
    albedo = np.array([0.60, 0.55, 0.50])
    spectrum = np.array(emitter.spectrum)
    expected = K * (albedo * spectrum)[:, None, None] / math.pi * e * mean_cos4_over_aperture(rig, cols, rows)

    assert np.all(np.abs(points[..., :2]) < [0.029, 0.019])  # the whole view is on the plate
    ratio = rate / expected
    assert e.max() / e.min() > 1.15  # a light from close by: far from uniform
    assert np.median(np.abs(ratio - 1)) < 1e-3
    assert np.max(np.abs(ratio - 1)) < 5e-3


# --- 2. cast shadows -------------------------------------------------------------------------------
def test_cast_shadow_of_a_floating_square(tmp_path):
    h, half = 0.006, 0.004
    plate = relief_plate_mesh(spacing_m=5e-3, bumps_mm=())
    sq_v = np.array([[-half, -half, h], [half, -half, h], [half, half, h], [-half, half, h]])
    sq_uv = np.zeros((4, 2))
    vertices = np.vstack([plate.vertices, sq_v])
    faces = np.vstack([plate.faces, len(plate.vertices) + np.array([[0, 1, 2], [0, 2, 3]])])
    uv = np.vstack([plate.visual.uv, sq_uv])
    mesh = trimesh.Trimesh(vertices, faces, visual=trimesh.visual.TextureVisuals(uv=uv), process=False)
    rig = object_rig(write_obj(tmp_path / "occluder.obj", mesh))
    truth = single_emitter({"model": "cos-power", "peak_w_sr": 1.0, "mu": 2.0})
    pose = arc_pose(40.0)
    rate = ObjectSceneRenderer(rig, truth, samples_per_pixel=4, diffraction=False, seed=5).render(pose).rate[1]

    cols, rows = pixel_grid()
    origin, d = chief_rays(rig, cols, rows)
    on_square = np.all(np.abs((origin + ((h - origin[2]) / d[..., 2])[..., None] * d)[..., :2]) < half, axis=-1)
    points = origin + (-origin[2] / d[..., 2])[..., None] * d  # on the plate
    p_e = pose.position
    s = h / (p_e[2] - points[..., 2])  # where the way to the light crosses z = h
    crossing = points + s[..., None] * (p_e - points)
    shadowed = ~on_square & np.all(np.abs(crossing[..., :2]) < half, axis=-1)
    lit = ~on_square & ~shadowed

    from scipy.ndimage import distance_transform_edt

    # Keep pixels at least 3 px from every edge (the defocus blur is < 1 px here).
    far_shadow = distance_transform_edt(shadowed) > 3
    far_lit = distance_transform_edt(lit) > 3
    near_shadow = far_lit & (distance_transform_edt(~shadowed) < 15)
    assert far_shadow.sum() > 200 and near_shadow.sum() > 200
    assert np.all(rate[far_shadow] == 0.0)
    e, _ = irradiance(points, np.array([0.0, 0.0, 1.0]), pose, truth.emitters[0], truth.emitters[0].intensity)
    expected = K * 0.55 / math.pi * e * mean_cos4_over_aperture(rig, cols, rows)
    assert np.max(np.abs(rate[near_shadow] / expected[near_shadow] - 1)) < 5e-3


# --- 3. painted patches ----------------------------------------------------------------------------
def test_patch_to_base_ratio_is_the_albedo_ratio(flat_plate):
    rig = object_rig(flat_plate)
    base = (0.60, 0.55, 0.50)
    patch = (0.20, 0.40, 0.90)
    painted = SurfaceTruth(
        base_albedo=base, patches=[{"centre_uv": (0.5, 0.5), "radius_uv": (0.08, 0.12), "albedo": patch}]
    )
    plain = SurfaceTruth(base_albedo=base)
    truth = single_emitter({"model": "gaussian", "peak_w_sr": 1.0, "sigma_deg": 20.0})
    pose = arc_pose(20.0)
    options = dict(samples_per_pixel=4, diffraction=False, seed=11)
    with_patch = ObjectSceneRenderer(rig, truth, surface=painted, **options).render(pose).rate
    without = ObjectSceneRenderer(rig, truth, surface=plain, **options).render(pose).rate

    cols, rows = pixel_grid()
    origin, d = chief_rays(rig, cols, rows)
    points = origin + (-origin[2] / d[..., 2])[..., None] * d
    u, v = (points[..., 0] + 0.03) / 0.06, (points[..., 1] + 0.02) / 0.04
    s = np.hypot((u - 0.5) / 0.08, (v - 0.5) / 0.12)  # normalised radius in the patch
    inside, outside = s < 0.8, s > 1.2
    assert inside.sum() > 500 and outside.sum() > 500
    ratio = with_patch / without
    expected = np.array(patch) / np.array(base)
    for ch in range(3):
        assert np.max(np.abs(ratio[ch][inside] / expected[ch] - 1)) < 0.01
        assert np.max(np.abs(ratio[ch][outside] - 1)) < 0.01
    # A patch pixel against a base pixel 3 mm away: albedo ratio times their irradiance ratio.
    i_in = np.unravel_index(np.argmin(np.where(inside, s, np.inf)), s.shape)
    i_out = np.unravel_index(np.argmin(np.where(outside, np.abs(s - 1.35), np.inf)), s.shape)
    e, _ = irradiance(points, np.array([0.0, 0.0, 1.0]), pose, truth.emitters[0], truth.emitters[0].intensity)
    c4 = mean_cos4_over_aperture(rig, cols, rows)
    geometric = (e[i_in] * c4[i_in]) / (e[i_out] * c4[i_out])
    for ch in range(3):
        assert with_patch[ch][i_in] / with_patch[ch][i_out] == pytest.approx(expected[ch] * geometric, rel=0.01)


# --- 3b. parameters as image maps in UV space ---------------------------------------------------------
def write_maps_of(surface, folder, size=(512, 1024)):
    """``surface`` rasterised at the texel centres into the map files a surface file names:
    the albedo as a 16-bit sRGB PNG, roughness, specular and metalness as one-channel EXRs."""
    import cv2
    import OpenEXR

    h, w = size
    v, u = np.mgrid[0:h, 0:w]
    uv = np.column_stack([((u + 0.5) / w).ravel(), (1.0 - (v + 0.5) / h).ravel()])
    albedo = surface.albedo_at(uv).reshape(h, w, 3)
    encoded = np.where(albedo <= 0.0031308, 12.92 * albedo, 1.055 * albedo ** (1 / 2.4) - 0.055)
    cv2.imwrite(str(folder / "albedo.png"), np.round(encoded[..., ::-1] * 65535).astype(np.uint16))
    finish = surface.finish_at(uv)
    for name in ("roughness", "specular", "metalness"):
        values = getattr(finish, name).reshape(h, w).astype(np.float32)
        header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
        with OpenEXR.File(header, {"Y": values}) as exr:
            exr.write(str(folder / f"{name}.exr"))
    maps = "\n".join(
        f'{name} = "{name}.{"png" if name == "albedo" else "exr"}"'
        for name in ("albedo", "roughness", "specular", "metalness")
    )
    path = folder / "mapped.toml"
    path.write_text(f"base_albedo = [0.5, 0.5, 0.5]\n[finish]\nior = 1.5\n[maps]\n{maps}\n")
    return path


def test_maps_paint_every_parameter_as_the_patches_do(tmp_path):
    painted = load_surface("glazed-gilded")
    mapped = load_surface(write_maps_of(painted, tmp_path))
    assert mapped.varies and mapped.glossy and not mapped.patches
    rng = np.random.default_rng(3)
    uv = rng.uniform(0.0, 1.0, (20000, 2))
    inside = painted.uv_distance_to_patches(uv)  # away from the edges, where a texel straddles two regions
    edge = np.zeros(len(uv), bool)
    for patch in painted.patches:
        (cu, cv), (ru, rv) = patch.centre_uv, patch.radii
        s = np.hypot((uv[:, 0] - cu) / ru, (uv[:, 1] - cv) / rv)
        edge |= np.abs(s - 1.0) * min(ru, rv) < 3.0 / 512
    away = ~edge
    assert away.sum() > 15000 and (inside[away] == 0).sum() > 1000  # in the patches: 6 %
    np.testing.assert_allclose(mapped.albedo_at(uv)[away], painted.albedo_at(uv)[away], atol=2e-5)
    want, got = painted.finish_at(uv), mapped.finish_at(uv)
    for name in ("roughness", "specular", "metalness"):
        np.testing.assert_allclose(getattr(got, name)[away], getattr(want, name)[away], atol=1e-6)
    # at the regions' edges the maps blend their texels: values between the two regions'
    gold = next(p for p in painted.patches if p.name == "gold leaf")
    across = np.column_stack(
        [np.full(9, gold.centre_uv[0]), gold.centre_uv[1] + gold.radii[1] + np.linspace(-2, 2, 9) / 512]
    )
    metal = mapped.finish_at(across).metalness
    assert metal[0] == 1.0 and metal[-1] == 0.0 and np.all(np.diff(metal) <= 0) and 0 < metal[4] < 1


def test_a_mapped_surface_renders_as_the_painted_one(flat_plate, tmp_path):
    rig = object_rig(flat_plate)
    painted = SurfaceTruth(
        base_albedo=(0.60, 0.55, 0.50),
        finish={"roughness": 0.3, "specular": 1.0},
        patches=[
            {
                "centre_uv": (0.5, 0.5),
                "radius_uv": (0.2, 0.3),
                "albedo": (0.2, 0.4, 0.9),
                "finish": {"roughness": 0.1, "metalness": 1.0},
            }
        ],
    )
    mapped = load_surface(write_maps_of(painted, tmp_path, size=(256, 256)))
    truth = single_emitter({"model": "gaussian", "peak_w_sr": 1.0, "sigma_deg": 20.0})
    options = dict(samples_per_pixel=4, diffraction=False, seed=11)
    pose = arc_pose(20.0)
    a = ObjectSceneRenderer(rig, truth, surface=painted, **options).render(pose).rate
    b = ObjectSceneRenderer(rig, truth, surface=mapped, **options).render(pose).rate
    cols, rows = pixel_grid()
    origin, d = chief_rays(rig, cols, rows)
    points = origin + (-origin[2] / d[..., 2])[..., None] * d
    u, v = (points[..., 0] + 0.03) / 0.06, (points[..., 1] + 0.02) / 0.04
    s = np.hypot((u - 0.5) / 0.2, (v - 0.5) / 0.3)
    away = np.abs(s - 1.0) > 0.1
    lit = a[1] > 0.05 * a[1].max()
    assert (away & lit & (s < 1)).sum() > 300 and (away & lit & (s > 1)).sum() > 300
    assert np.max(np.abs(b[:, away & lit] / a[:, away & lit] - 1)) < 2e-3


@pytest.mark.parametrize(
    "maps, field",
    [
        ('roughness = "missing.exr"', "maps.roughness: "),
        ('metalness = "albedo.png"', "maps.metalness: "),  # three channels for a one-channel map
        ('roughness = "zero.exr"', "outside 0.02-1"),
        ('albedo = "zero.txt"', "a .png or an .exr file"),
    ],
)
def test_a_bad_map_is_one_line_naming_the_surface_file_and_the_field(tmp_path, maps, field):
    write_maps_of(load_surface("patches"), tmp_path, size=(16, 32))
    import OpenEXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {"Y": np.zeros((4, 4), np.float32)}) as exr:
        exr.write(str(tmp_path / "zero.exr"))
    (tmp_path / "zero.txt").write_text("0")
    path = tmp_path / "bad-maps.toml"
    path.write_text(f"base_albedo = [0.5, 0.5, 0.5]\n[maps]\n{maps}\n")
    with pytest.raises(SurfaceError) as info:
        load_surface(path)
    message = str(info.value)
    assert "\n" not in message and message.startswith(str(path)) and field in message, message


# --- 4. the specular lobe --------------------------------------------------------------------------
def test_specular_lobe_brightens_only_near_the_mirror_direction(tmp_path):
    # A wide view (±25° across) of a large plate, so that the half vector strays far from
    # the normal at the edges; a sharp lobe (m = 500) is then negligible there.
    plate = write_obj(tmp_path / "big.obj", relief_plate_mesh(size_m=(0.24, 0.16), spacing_m=0.02, bumps_mm=()))
    rig = object_rig(plate, pitch=100e-6)
    base = (0.60, 0.55, 0.50)
    k_s, m = 0.08, 500.0
    glossy = SurfaceTruth(base_albedo=base, specular={"k_s": k_s, "exponent": m})
    matte = SurfaceTruth(base_albedo=base)
    truth = single_emitter({"model": "cos-power", "peak_w_sr": 1.0, "mu": 1.0})
    # The light 30 cm out, 1 cm above the axis: its mirror image in the plate is in view.
    position = np.array([0.0, 0.01, 0.30])
    pose = Pose.from_rotation(position, look_rotation(-position, (1.0, 0.0, 0.0)))
    options = dict(samples_per_pixel=4, diffraction=False, seed=2)
    shiny = ObjectSceneRenderer(rig, truth, surface=glossy, **options).render(pose).rate
    dull = ObjectSceneRenderer(rig, truth, surface=matte, **options).render(pose).rate

    cols, rows = pixel_grid()
    origin, d = chief_rays(rig, cols, rows)
    points = origin + (-origin[2] / d[..., 2])[..., None] * d
    to_light = position - points
    to_light /= np.linalg.norm(to_light, axis=-1, keepdims=True)
    half = to_light - d
    n_h = half[..., 2] / np.linalg.norm(half, axis=-1)
    ratio = shiny / dull
    peak = np.unravel_index(np.argmax(n_h), n_h.shape)
    assert 5 < peak[0] < H - 5 and 5 < peak[1] < W - 5  # the highlight is in view
    near = n_h > math.cos(math.radians(0.5))
    far = n_h < math.cos(math.radians(15.0))
    assert near.sum() >= 4 and far.sum() > 2000
    for ch in range(3):
        # At the mirror point n·h = 1: L = (ρ/π + k_s (m + 8) / 8π) E.
        assert ratio[ch][peak] == pytest.approx(1 + k_s * (m + 8) / (8 * base[ch]), rel=0.01)
        assert np.all(ratio[ch][near] > 1.5)
        assert np.max(np.abs(ratio[ch][far] - 1)) < 1e-6


@pytest.mark.parametrize(
    "finish, albedo",
    [
        ({"roughness": 0.3, "specular": 1.0, "ior": 1.5}, (0.60, 0.55, 0.50)),  # a satin glaze
        ({"roughness": 0.15, "metalness": 1.0}, (1.00, 0.766, 0.336)),  # gold leaf
    ],
    ids=["glaze", "gold"],
)
def test_a_microfacet_finish_is_the_brdf_times_the_irradiance(tmp_path, finish, albedo):
    # The same wide view of a large plate, the light's mirror image in view; every pixel
    # against K·f(l, v)·E·⟨cos⁴β⟩ with f from sim_devices.brdf (checked against Mitsuba 3 in
    # test_sim_brdf.py), l and v of the pixel's chief ray.
    plate = write_obj(tmp_path / "big.obj", relief_plate_mesh(size_m=(0.24, 0.16), spacing_m=0.02, bumps_mm=()))
    rig = object_rig(plate, pitch=100e-6)
    surface = SurfaceTruth(base_albedo=albedo, finish=finish)
    truth = single_emitter({"model": "cos-power", "peak_w_sr": 1.0, "mu": 1.0}, spectrum=(1.0, 0.9, 0.8))
    position = np.array([0.0, 0.01, 0.30])
    pose = Pose.from_rotation(position, look_rotation(-position, (1.0, 0.0, 0.0)))
    rate = (
        ObjectSceneRenderer(rig, truth, surface=surface, samples_per_pixel=16, diffraction=False, seed=4)
        .render(pose)
        .rate
    )

    cols, rows = pixel_grid()
    origin, d = chief_rays(rig, cols, rows)
    points = origin + (-origin[2] / d[..., 2])[..., None] * d
    emitter = truth.emitters[0]
    e, p_e = irradiance(points, np.array([0.0, 0.0, 1.0]), pose, emitter, emitter.intensity)
    light = p_e - points
    light /= np.linalg.norm(light, axis=-1, keepdims=True)
    count = light[..., 0].size
    normal = np.tile([0.0, 0.0, 1.0], (count, 1))
    directions = (light.reshape(-1, 3), -d.reshape(-1, 3), normal, np.tile(albedo, (count, 1)))
    f = brdf(*directions, surface.finish_at(None, count))
    assert np.max(specular_lobe(*directions, surface.finish_at(None, count)) / f) > 0.1  # a highlight in view
    spectrum = np.array(emitter.spectrum)
    expected = K * (f * spectrum).T.reshape(3, H, W) * e * mean_cos4_over_aperture(rig, cols, rows)
    ratio = rate / expected
    assert np.median(np.abs(ratio - 1)) < 2e-3
    assert np.percentile(np.abs(ratio - 1), 99) < 1e-2


# --- 5. shipped meshes and rigs, and a DNG capture ---------------------------------------------------
def test_shipped_objects_load_with_uvs_and_are_regenerated_identically(tmp_path):
    written = write_shipped(tmp_path)
    for path in written:
        shipped = OBJECTS_DIR / path.name
        assert shipped.read_bytes() == path.read_bytes(), f"{shipped} differs from python -m sim_devices.objects"
        mesh = trimesh.load(shipped, force="mesh")
        raw = trimesh.load(shipped, force="mesh", process=False)
        assert mesh.visual.uv is not None and len(mesh.visual.uv) == len(mesh.vertices)
        assert np.array_equal(mesh.faces, raw.faces) and np.array_equal(mesh.vertices, raw.vertices)
        assert 0.0 <= mesh.visual.uv.min() and mesh.visual.uv.max() <= 1.0
    vase = trimesh.load(OBJECTS_DIR / "vase.obj", force="mesh")
    size = vase.bounds[1] - vase.bounds[0]
    assert size[1] <= 0.0501 and 0.02 < size[0] < 0.04
    # Facets no more than 3° apart around, and shadows from above: the lip overhangs the neck.
    assert np.degrees(vase.face_adjacency_angles).max() <= 3.01
    relief = trimesh.load(OBJECTS_DIR / "relief.obj", force="mesh")
    assert relief.bounds[1][2] > 0.003 and np.allclose(relief.bounds[1][:2] - relief.bounds[0][:2], [0.06, 0.04])


@pytest.mark.parametrize("name", ["object-vase", "object-relief"])
def test_shipped_object_rigs_load(name):
    rig = load_rig(ROOT / "rigs" / f"{name}.toml")
    assert rig.object is not None and (ROOT / "rigs" / "objects").samefile(Path(rig.object.mesh).parent)
    assert rig.camera.thin_lens is not None and rig.schedule.kind == "object-arc"
    assert len(rig.light_poses()) == 5
    load_surface(rig.simulation.surface)


def test_simulated_camera_photographs_the_object(tmp_path):
    data = tomllib.loads((ROOT / "rigs" / "object-vase.toml").read_text())
    data["camera"].update(width=400, height=264, pixel_pitch_m=5 * 5.9e-6)
    data["object"]["mesh"] = str(ROOT / "rigs" / "objects" / "vase.obj")
    data["simulation"]["diffraction"] = True
    rig = rig_from_dict(data)
    pose = rig.light_poses()[1]
    camera = SimulatedCamera(rig, SimWorld(lambda: pose), tmp_path, seed=4)
    assert type(camera.renderer).__name__ == "ObjectSceneRenderer"
    frame = camera.capture_to(tmp_path / "vase.dng", 0.5)
    assert frame.mosaic.shape == (264, 400)
    again = decode_raw(tmp_path / "vase.dng")
    assert np.array_equal(again.mosaic, camera.last_mosaic)
    # The vase (about 38 x 50 mm, 160 x 212 px here) is bright against a dark room.
    middle = frame.mosaic[100:160, 170:230].astype(float)
    corner = frame.mosaic[:30, :30].astype(float)
    assert middle.mean() > corner.mean() + 200


def test_surface_truth_at_the_shipped_vase():
    rig = load_rig(ROOT / "rigs" / "object-vase.toml")
    mesh = trimesh.load(rig.object.mesh, force="mesh")
    surface = load_surface("patches")
    uv = mesh.visual.uv
    dark = next(p for p in surface.patches if p.name == "dark grey")
    i_patch = np.argmin(np.hypot(uv[:, 0] - dark.centre_uv[0], uv[:, 1] - dark.centre_uv[1]))
    i_far = np.argmin(np.hypot(uv[:, 0] - 0.5, uv[:, 1] - 0.92))
    # Just outside the dark patch along u: painted base, but within 2 mm of the edge.
    ru = dark.radii[0]
    i_edge = np.argmin(np.hypot(uv[:, 0] - (dark.centre_uv[0] - ru - 0.008), uv[:, 1] - dark.centre_uv[1]))
    albedo, uniform = surface_truth_at(rig, mesh.vertices[[i_patch, i_far, i_edge]])
    assert albedo[0] == pytest.approx(dark.albedo)
    assert albedo[1] == pytest.approx(surface.base_albedo) and albedo[2] == pytest.approx(surface.base_albedo)
    assert uniform.tolist() == [False, True, False]


def test_the_glazed_gilded_vase_has_its_finishes_where_its_file_paints_them():
    rig = load_rig(ROOT / "rigs" / "object-vase.toml")
    mesh = trimesh.load(rig.object.mesh, force="mesh")
    surface = load_surface("glazed-gilded")
    uv = mesh.visual.uv
    names = ["matte terracotta", "glossy cobalt glaze", "dark varnish", "gold leaf"]
    centres = [next(p for p in surface.patches if p.name == name).centre_uv for name in names]
    where = [np.argmin(np.hypot(uv[:, 0] - cu, uv[:, 1] - cv)) for cu, cv in centres]
    where.append(np.argmin(np.hypot(uv[:, 0] - 0.5, uv[:, 1] - 0.92)))  # the satin base
    finish = surface_finish_at(rig, mesh.vertices[where], surface=surface)
    assert finish.specular.tolist() == [0.0, 1.0, 1.0, 0.0, 1.0]
    assert finish.metalness.tolist() == [0.0, 0.0, 0.0, 1.0, 0.0]
    assert finish.roughness[[1, 2, 3, 4]].tolist() == [0.15, 0.15, 0.20, 0.35]
    assert finish.glossy.tolist() == [False, True, True, True, True]


# --- 6. bad surface files ---------------------------------------------------------------------------
@pytest.mark.parametrize(
    "body, field",
    [
        ("base_albedo = [0.6, 0.5, 0.5]\nalbedo_base = 1\n", "albedo_base: unknown field"),
        (
            "base_albedo = [0.6, 0.5, 0.5]\n[[patches]]\ncentre_uv = [0.5, 0.5]\nradius_uv = 0.1\nalbedo = "
            "[0.2, -0.1, 0.3]\n",
            "patches[0].albedo[1]: must be >= 0",
        ),
        ("base_albedo = [0.6, 0.5]\n", "base_albedo"),
        ("base_albedo = [0.99, 0.5, 0.5]\n[finish]\nspecular = 1.0\n", "finish: albedo 0.99 plus the coat's 0.04"),
        ("base_albedo = [0.6, 0.5, 0.5]\n[finish]\nroughness = 0.0\n", "finish.roughness: must be >= 0.02"),
        (
            "base_albedo = [0.6, 0.5, 0.5]\n[finish]\nmetalness = 1.0\n[specular]\nk_s = 0.1\nexponent = 50\n",
            "specular: a Blinn-Phong lobe beside a glossy finish",
        ),
    ],
)
def test_bad_surface_file_is_one_line_naming_file_and_field(tmp_path, body, field):
    path = tmp_path / "bad-surface.toml"
    path.write_text(body)
    with pytest.raises(SurfaceError) as info:
        load_surface(path)
    message = str(info.value)
    assert "\n" not in message and str(path) in message and field in message, message
    with pytest.raises(SurfaceError, match="no such surface"):
        load_surface("no-such-surface")
