"""processing.reflectance: albedo under three light models, against scenes rendered here.

The scenes are rendered in this file from the formula of docs/measurement.md ("Diffuse
reflectance under near light") and docs/rig.md's radiometry, independently of the module: chief rays through the
superpixel centres, first hits and cast shadows by brute force (Möller–Trumbore against
every triangle), flat face normals, ``rate = k·cos⁴β·ρ/π·Σ_s I_s(θ_s)·max(0, n·ω_s)/d_s²``
over the sources each point sees. Tolerances are stated at each assertion.
"""

from __future__ import annotations

import json
import math
import re

import h5py
import numpy as np
import pytest
import trimesh
from scipy.ndimage import binary_dilation
from scipy.stats import spearmanr
from typer.testing import CliRunner

from acquisition.cli import app
from drivers.camera import RawFrame
from drivers.contracts.rig import rig_from_dict
from drivers.contracts.runfile import PositionTimes, RunFileWriter, RunHeader
from processing.fit import IntensityFit
from processing.images import read_exr
from processing.lightmodel import LightModel, SourceModel
from processing.options import ProcessingOptions
from processing.reflectance.codes import (
    PIXEL_BACKGROUND,
    PIXEL_EDGE,
    PIXEL_FEW_SATURATED,
    PIXEL_GRAZING_VIEW,
    PIXEL_VALID,
    SAMPLE_GRAZING,
    SAMPLE_SATURATED,
    SAMPLE_SHADOW,
    SAMPLE_SPECULAR_GEOMETRY,
    SAMPLE_SPECULAR_OUTLIER,
    SAMPLE_USED,
    ReflectanceError,
    ReflectanceSettings,
)
from processing.reflectance.estimate import estimate_reflectance
from processing.reflectance.lights import LIGHT_MODELS, light_centre
from processing.reflectance.outputs import write_outputs
from processing.reflectance.run import find_light_model, load_mesh, reflectance_from_run

runner = CliRunner()
K = 1000.0  # the camera's sensitivity_e_per_s
WIDTH, HEIGHT = 200, 160  # superpixel grid 100 x 80
OBJECT = {"mesh": "scene.ply", "units_m": 1.0}


def rig_dict(**object_section) -> dict:
    """A small object rig: camera 60 cm in front of the origin, a 100 x 80 superpixel view of
    ±12 x ±9.6 cm, thin lens focused on the object; the default object arc (10°–50° at 30 cm)."""
    data = {
        "name": "object-test",
        "camera": {
            "width": WIDTH,
            "height": HEIGHT,
            "pixel_pitch_m": 5.0e-5,
            "sensor_distance_m": 0.025,
            "sensitivity_e_per_s": K,
            "thin_lens": {"focus_distance_m": 0.6, "f_number": 8.0},
            "pose": {"position_m": [0.0, 0.0, 0.6], "look_at_m": [0.0, 0.0, 0.0], "up": [0.0, 1.0, 0.0]},
        },
        "schedule": {"kind": "object-arc"},
    }
    if object_section:
        data["object"] = object_section
    return data


RIG = rig_from_dict(rig_dict())
POSES = RIG.light_poses()


def gaussian_fit(a: float, sigma_deg: float) -> IntensityFit:
    return IntensityFit(
        "gaussian",
        {"a": a, "sigma": math.radians(sigma_deg)},
        {"a": 0.0, "sigma": 0.0},
        np.zeros((2, 2)),
        np.zeros(0),
        1.0,
        0,
        (0.0, math.radians(60.0)),
        (0.0, 2 * math.pi),
    )


def flat_fit(i0: float) -> IntensityFit:
    return IntensityFit(
        "polynomial",
        {"c0": i0},
        {"c0": 0.0},
        np.zeros((1, 1)),
        np.zeros(0),
        1.0,
        0,
        (0.0, math.radians(60.0)),
        (0.0, 2 * math.pi),
    )


def directional_light(rig_section=None) -> LightModel:
    """Two sources 6 mm apart with narrow Gaussian lobes (12° and 18°): clearly not isotropic."""
    sources = [
        SourceModel("a", (0.003, 0.0), 0.0005, gaussian_fit(2.0, 12.0)),
        SourceModel("b", (-0.003, 0.001), 0.0005, gaussian_fit(1.2, 18.0)),
    ]
    provenance = {"run_id": "light-run", "rig": rig_section if rig_section is not None else rig_dict()}
    return LightModel(sources, "W/sr", provenance)


def isotropic_light() -> LightModel:
    return LightModel([SourceModel("iso", (0.0, 0.0), 0.0, flat_fit(1.5))], "W/sr", {"rig": rig_dict()})


def scene() -> trimesh.Trimesh:
    """A polyhedral sphere of 4 cm radius at the origin in front of a plane 5 cm behind it."""
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.04)
    xs, ys = np.linspace(-0.11, 0.11, 7), np.linspace(-0.085, 0.085, 6)
    gx, gy = np.meshgrid(xs, ys)
    vertices = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, -0.05)])
    faces = []
    for r in range(len(ys) - 1):
        for c in range(len(xs) - 1):
            i = r * len(xs) + c
            faces += [[i, i + 1, i + len(xs)], [i + 1, i + len(xs) + 1, i + len(xs)]]
    plane = trimesh.Trimesh(vertices, np.array(faces), process=False)
    return trimesh.util.concatenate([sphere, plane])


def albedo(points: np.ndarray) -> np.ndarray:
    """A smooth known albedo per channel."""
    base = np.array([0.55, 0.42, 0.30])
    return base * (1.0 + 0.3 * np.sin(40.0 * points[:, :1]) * np.cos(30.0 * points[:, 1:2]))


# --- the independent renderer --------------------------------------------------------------------
def superpixel_rays(camera):
    f_px = camera.sensor_distance_m / camera.pixel_pitch_m
    cx, cy = (camera.width - 1) / 2.0, (camera.height - 1) / 2.0
    rows, cols = np.mgrid[0 : camera.height // 2, 0 : camera.width // 2]
    x, y = (2 * cols + 0.5 - cx) / f_px, (2 * rows + 0.5 - cy) / f_px
    R, t = camera.pose.extrinsics()
    d = np.stack([x, y, np.ones_like(x)], axis=-1) @ R
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    # cos⁴β averaged over the aperture by brute force (a 256-point Vogel spiral on the disc)
    f, a = camera.sensor_distance_m, camera.aperture_diameter_m / 2.0
    k = np.arange(256) + 0.5
    ar, at = a * np.sqrt(k / 256), k * math.pi * (3.0 - math.sqrt(5.0))
    cos4 = np.zeros_like(x)
    for ax, ay in zip(ar * np.cos(at), ar * np.sin(at), strict=True):
        cos4 += (f / np.sqrt((x * f + ax) ** 2 + (y * f + ay) ** 2 + f * f)) ** 4 / 256
    return -R.T @ t, d, cos4


def first_hit(origins, directions, triangles, chunk=2048):
    """Möller–Trumbore against every triangle: distance and index of the nearest hit."""
    v0, e1, e2 = triangles[:, 0], triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0]
    best_t = np.full(len(origins), np.inf)
    best_i = np.full(len(origins), -1)
    for s in range(0, len(origins), chunk):
        o, d = origins[s : s + chunk, None, :], directions[s : s + chunk, None, :]
        p = np.cross(d, e2[None])
        det = np.einsum("rtk,tk->rt", p, e1)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / det
            tv = o - v0[None]
            u = np.einsum("rtk,rtk->rt", tv, p) * inv
            q = np.cross(tv, e1[None])
            v = np.einsum("rtk,rtk->rt", d, q) * inv
            t = np.einsum("tk,rtk->rt", e2, q) * inv
        ok = (np.abs(det) > 1e-15) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-9)
        t = np.where(ok, t, np.inf)
        best_i[s : s + chunk] = np.where(np.isfinite(t.min(axis=1)), t.argmin(axis=1), -1)
        best_t[s : s + chunk] = t.min(axis=1)
    return best_t, best_i


def light_frame(pose, points):
    return (points - pose.position) @ pose.rotation


def render(mesh, model, poses, *, camera=RIG.camera):
    """Rates (lights, H/2, W/2, 3) in e⁻/s and the truth behind them."""
    centre, dirs, cos4 = superpixel_rays(camera)
    shape = dirs.shape[:2]
    flat = dirs.reshape(-1, 3)
    t, face = first_hit(np.broadcast_to(centre, flat.shape), flat, mesh.triangles)
    hit = np.isfinite(t)
    points = centre + t[hit, None] * flat[hit]
    normals = mesh.face_normals[face[hit]]
    normals = normals * np.where(np.einsum("ij,ij->i", normals, flat[hit]) > 0, -1.0, 1.0)[:, None]
    rho = albedo(points)
    n_src = len(model.sources)
    E = np.zeros((len(poses), len(points)))
    E_rgb = np.zeros((len(poses), len(points), 3))  # each source's term times its colour
    shadowed = np.zeros((len(poses), len(points), n_src), bool)
    for j, pose in enumerate(poses):
        for s, source in enumerate(model.sources):
            p_s = pose.position + pose.rotation @ np.array([*source.centre_m, 0.0])
            to = p_s - points
            dist = np.linalg.norm(to, axis=1)
            omega = to / dist[:, None]
            cos_in = np.einsum("ij,ij->i", normals, omega)
            lit = cos_in > 0
            start = points[lit] + 1e-7 * normals[lit]
            t_block, _ = first_hit(start, omega[lit], mesh.triangles)
            blocked = np.zeros(len(points), bool)
            blocked[np.flatnonzero(lit)[t_block < dist[lit]]] = True
            shadowed[j, :, s] = blocked
            local = light_frame(pose, points) - np.array([*source.centre_m, 0.0])
            theta = np.arccos(local[:, 2] / np.linalg.norm(local, axis=1))
            p = source.fit.params
            intensity = (
                p["a"] * np.exp(-(theta**2) / (2 * p["sigma"] ** 2)) if "a" in p else np.full(len(theta), p["c0"])
            )
            term = np.where(lit & ~blocked, intensity * np.maximum(cos_in, 0.0) / dist**2, 0.0)
            E[j] += term
            E_rgb[j] += term[:, None] * np.asarray(source.colour)[None, :]
    rates = np.zeros((len(poses), *shape, 3))
    rows, cols = np.divmod(np.flatnonzero(hit), shape[1])
    for j in range(len(poses)):
        rates[j, rows, cols] = K * cos4[rows, cols, None] * rho / math.pi * E_rgb[j]
    truth = {
        "rows": rows,
        "cols": cols,
        "points": points,
        "normals": normals,
        "face": face[hit],
        "rho": rho,
        "shadowed": shadowed,
        "E": E,
        "view": -flat[hit],
        "shape": shape,
    }
    return rates, truth


@pytest.fixture(scope="module")
def mesh():
    return scene()


@pytest.fixture(scope="module")
def directional(mesh):
    model = directional_light()
    rates, truth = render(mesh, model, POSES)
    result = estimate_reflectance(rates, None, RIG.camera, mesh, POSES, model)
    return model, rates, truth, result


def at_truth(result, truth, grid):
    return grid[truth["rows"], truth["cols"]]


def same_face(result, truth):
    """Points where the module and the brute force hit the same face (all but rays grazing an edge)."""
    faces = np.full(truth["shape"], -1)
    faces[result.rows, result.cols] = result.faces
    return at_truth(result, truth, faces) == truth["face"]


# --- recovering the albedo ------------------------------------------------------------------------------
def test_measured_model_recovers_the_albedo(directional):
    model, rates, truth, result = directional
    same = same_face(result, truth)
    assert same.mean() > 0.999
    valid = at_truth(result, truth, result.reason) == PIXEL_VALID
    assert valid.sum() > 2500  # on the sphere and the plane
    rho = at_truth(result, truth, result.rho["measured"])
    ok = valid & same
    rel = np.abs(rho[ok] / truth["rho"][ok] - 1.0)
    assert rel.max() < 1e-3  # measured: the same physics, to 1e-3 relative (in fact ~1e-9)
    assert np.all(np.isnan(rho[~valid]))
    # the points and normals the module found are the brute force's
    points = np.full((*truth["shape"], 3), np.nan)
    points[result.rows, result.cols] = result.points
    np.testing.assert_allclose(at_truth(result, truth, points)[same], truth["points"][same], atol=1e-9)
    assert result.lights_used[result.valid].min() >= 2


def test_measured_model_with_noise_is_unbiased(mesh, directional):
    model, rates, truth, _ = directional
    rng = np.random.default_rng(6)
    noisy = rates * (1.0 + 1e-3 * rng.standard_normal(rates.shape))
    result = estimate_reflectance(noisy, None, RIG.camera, mesh, POSES, model)
    valid = (at_truth(result, truth, result.reason) == PIXEL_VALID) & same_face(result, truth)
    rel = at_truth(result, truth, result.rho["measured"])[valid] / truth["rho"][valid] - 1.0
    assert abs(np.median(rel)) < 2e-4  # 0.1 % noise per sample: no bias beyond 0.02 %
    assert np.median(np.abs(rel)) < 1e-3  # and a median error below 0.1 %


def _tinted(model: LightModel, colours) -> LightModel:
    return LightModel(
        [
            SourceModel(s.name, s.centre_m, s.radius_m, s.fit, s.samples, c)
            for s, c in zip(model.sources, colours, strict=True)
        ],
        model.units,
        model.provenance,
    )


def test_a_tinted_light_leaves_no_tint_in_the_albedo(mesh, tmp_path):
    """Two sources of different colours (a warm and a cool LED): with the colours in the
    light model, each channel's albedo is the surface's; a grey model of the same light
    puts the light's tint into the albedo. The simplified models get the light's mean
    colour: for a light of one colour, their channel ratios are right even where their
    geometry is not (with two colours, how they mix varies over the object: that is the
    simplification's error too)."""
    warm, cool = (1.3, 1.0, 0.7), (0.8, 1.0, 1.2)
    tinted = _tinted(directional_light(), [warm, cool])
    rates, truth = render(mesh, tinted, POSES)
    result = estimate_reflectance(rates, None, RIG.camera, mesh, POSES, tinted)
    valid = (at_truth(result, truth, result.reason) == PIXEL_VALID) & same_face(result, truth)
    assert valid.sum() > 2500
    rho = at_truth(result, truth, result.rho["measured"])[valid]
    assert np.abs(rho / truth["rho"][valid] - 1.0).max() < 1e-3  # as for a grey light
    grey = estimate_reflectance(rates, None, RIG.camera, mesh, POSES, _tinted(tinted, [(1, 1, 1)] * 2))
    off = np.nanmedian(at_truth(grey, truth, grey.rho["measured"])[valid] / truth["rho"][valid], axis=0)
    assert off[0] > 1.05 and off[2] < 0.95  # red too high, blue too low: the light's tint, not the surface's
    # The per-point file holds each channel's irradiance, the one ρ was solved with: ρ comes back from it.
    write_outputs(result, tmp_path / "tinted", texture_size=64)
    with h5py.File(tmp_path / "tinted" / "reflectance.h5") as f:
        for method in ("measured", "isotropic", "collimated"):
            e_rgb, grey_e = f[f"irradiance_rgb/{method}"][()], f[f"irradiance/{method}"][()]
            assert e_rgb.dtype == np.float32 and e_rgb.shape == (len(POSES), len(result.rows), 3)
            np.testing.assert_allclose(e_rgb.mean(axis=2), grey_e, rtol=1e-6, atol=1e-6 * grey_e.max())
            used = (f["sample_code"][()] == 0)[..., None]
            L = np.where(used, f["radiance"][()], 0.0)
            with np.errstate(divide="ignore", invalid="ignore"):
                again = math.pi * (L * e_rgb).sum(axis=0) / np.where(used, e_rgb.astype(float) ** 2, 0.0).sum(axis=0)
            stored = f[f"rho/{method}"][()]
            assert np.isfinite(stored).sum() > 2500
            np.testing.assert_allclose(again[np.isfinite(stored)], stored[np.isfinite(stored)], rtol=1e-5)
        assert not np.allclose(f["irradiance_rgb/measured"][..., 0], f["irradiance_rgb/measured"][..., 2])  # tinted
    grey_e = grey.irradiance["measured"].astype(np.float32)
    assert np.array_equal(grey.irradiance_rgb("measured"), np.repeat(grey_e[..., None], 3, -1))  # a grey light
    one_colour = _tinted(directional_light(), [warm, warm])
    rates, truth = render(mesh, one_colour, POSES)
    result = estimate_reflectance(rates, None, RIG.camera, mesh, POSES, one_colour)
    assert np.allclose(one_colour.colour(), np.array(warm) / np.mean(warm))
    valid = (at_truth(result, truth, result.reason) == PIXEL_VALID) & same_face(result, truth)
    for method in ("measured", "isotropic", "collimated"):
        got = at_truth(result, truth, result.rho[method])[valid]
        ratios = (got[:, 0] / got[:, 2]) / (truth["rho"][valid, 0] / truth["rho"][valid, 2])
        finite = np.isfinite(ratios)
        assert finite.mean() > 0.99 and np.abs(ratios[finite] - 1.0).max() < 1e-6, method


def test_isotropic_model_is_wrong_where_the_intensity_falls_off(directional):
    """With E_iso = I₀·cos/d² from the centroid, ρ_iso/ρ is a weighted mean over the used lights
    of E_true/E_iso, the light's actual fall-off: 1 on the axis, far below it off the axis."""
    model, _, truth, result = directional
    (u, v), i0 = light_centre(model)
    assert i0 == pytest.approx(3.2)
    assert (u, v) == pytest.approx(((2.0 * 0.003 - 1.2 * 0.003) / 3.2, 1.2 * 0.001 / 3.2))
    valid = (at_truth(result, truth, result.reason) == PIXEL_VALID) & same_face(result, truth)
    ratio = at_truth(result, truth, result.rho["isotropic"])[valid] / truth["rho"][valid]
    np.testing.assert_allclose(ratio, ratio[:, :1].repeat(3, axis=1), rtol=1e-9)  # a grey light: one ratio
    ratio = ratio[:, 0]
    codes = np.full((len(POSES), *truth["shape"]), 255)
    codes[:, result.rows, result.cols] = result.sample_code
    used = codes[:, truth["rows"], truth["cols"]][:, valid] == SAMPLE_USED
    f = np.full(used.shape, np.nan)
    for j, pose in enumerate(POSES):
        point = pose.position + pose.rotation @ np.array([u, v, 0.0])
        to = point - truth["points"][valid]
        d2 = np.einsum("ij,ij->i", to, to)
        e_iso = i0 * np.maximum(np.einsum("ij,ij->i", truth["normals"][valid], to) / np.sqrt(d2), 0) / d2
        with np.errstate(divide="ignore", invalid="ignore"):  # facing away: no ratio, never used
            f[j] = truth["E"][j][valid] / e_iso
    lo = np.nanmin(np.where(used, f, np.nan), axis=0)
    hi = np.nanmax(np.where(used, f, np.nan), axis=0)
    assert np.all(ratio >= lo * (1 - 1e-9)) and np.all(ratio <= hi * (1 + 1e-9))
    # the bias follows the angle from the lights' axes: none near them, large far off them
    theta = np.stack(
        [
            np.degrees(
                np.arccos(
                    np.clip(
                        light_frame(p, truth["points"][valid])[:, 2]
                        / np.linalg.norm(light_frame(p, truth["points"][valid]), axis=1),
                        -1,
                        1,
                    )
                )
            )
            for p in POSES
        ]
    )
    near, far = theta.max(axis=0) < 4.0, theta.min(axis=0) > 8.0
    assert near.sum() > 20 and far.sum() > 300
    assert np.median(ratio[near]) == pytest.approx(1.0, abs=0.03)  # I(4°)/I(0) > 0.97 for both lobes
    assert np.median(ratio[far]) < 0.8
    assert spearmanr(ratio, theta.mean(axis=0)).statistic < -0.9


def test_collimated_model_is_wrong_with_distance(mesh):
    """An isotropic point light: the isotropic model is exact, the collimated one is too high
    where the surface is nearer the light than the object's centre and too low where farther."""
    model = isotropic_light()
    rates, truth = render(mesh, model, POSES)
    result = estimate_reflectance(rates, None, RIG.camera, mesh, POSES, model)
    valid = (at_truth(result, truth, result.reason) == PIXEL_VALID) & same_face(result, truth)
    rho = truth["rho"][valid]
    iso = at_truth(result, truth, result.rho["isotropic"])[valid]
    # one source at the light's origin: exact, up to the test's 256-point aperture quadrature of cos⁴β
    assert np.abs(iso / rho - 1).max() < 3e-4
    np.testing.assert_allclose(at_truth(result, truth, result.rho["measured"])[valid], iso, rtol=1e-9)
    ratio = (at_truth(result, truth, result.rho["collimated"])[valid] / rho)[:, 0]
    centre = mesh.bounds.mean(axis=0)
    d0 = np.mean([np.linalg.norm(p.position - centre) for p in POSES])
    d = np.mean([np.linalg.norm(p.position - truth["points"][valid], axis=1) for p in POSES], axis=0)
    nearer, farther = d < d0 - 0.03, d > d0 + 0.04
    assert nearer.sum() > 100 and farther.sum() > 300
    assert np.median(ratio[nearer]) > 1.1  # ~ (d0/d)², with the direction's error on top
    assert np.median(ratio[farther]) < 0.9


def test_light_models_by_name():
    model = isotropic_light()
    pose = POSES[2]
    points = np.array([[0.0, 0.0, 0.0], [0.02, 0.01, 0.01]])
    normals = np.array([[0.0, 0.0, 1.0], [0.0, 0.6, 0.8]])
    e = {name: factory(model, pose, np.zeros(3)).irradiance(points, normals) for name, factory in LIGHT_MODELS.items()}
    to = pose.position - points
    d = np.linalg.norm(to, axis=1)
    np.testing.assert_allclose(e["isotropic"], 1.5 * np.einsum("ij,ij->i", normals, to) / d**3, rtol=1e-12)
    np.testing.assert_allclose(e["measured"], e["isotropic"], rtol=1e-12)
    omega0 = pose.position / np.linalg.norm(pose.position)
    np.testing.assert_allclose(e["collimated"], 1.5 / 0.3**2 * normals @ omega0, rtol=1e-12)


# --- what is left out, and why ---------------------------------------------------------------------------------
def test_cast_shadows_are_excluded_with_their_code(directional):
    _, _, truth, result = directional
    codes = np.full((len(POSES), *truth["shape"]), 255, np.uint8)
    codes[:, result.rows, result.cols] = result.sample_code
    pixel_ok = at_truth(result, truth, result.reason) == PIXEL_VALID
    total = 0
    for j in range(len(POSES)):
        shadow_grid = np.zeros(truth["shape"], bool)
        shadow_grid[truth["rows"], truth["cols"]] = truth["shadowed"][j].any(axis=1)
        code = codes[j, truth["rows"], truth["cols"]]
        shadowed = truth["shadowed"][j].any(axis=1)
        considered = code != 1  # not excluded as a whole pixel
        # every truly shadowed sample is excluded: as a shadow unless it grazes first
        assert np.all(np.isin(code[considered & shadowed], [SAMPLE_SHADOW, SAMPLE_GRAZING]))
        total += int((considered & shadowed & (code == SAMPLE_SHADOW)).sum())
        # and the shadow code reaches no farther than the one-superpixel margin
        near = binary_dilation(shadow_grid, np.ones((3, 3), bool))[truth["rows"], truth["cols"]]
        assert np.all(near[code == SAMPLE_SHADOW])
    assert total > 100
    assert pixel_ok.sum() > 0


def test_grazing_light_and_grazing_view(directional):
    model, _, truth, result = directional
    (u, v), _ = light_centre(model)
    codes = np.full((len(POSES), *truth["shape"]), 255, np.uint8)
    codes[:, result.rows, result.cols] = result.sample_code
    seen = 0
    for j, pose in enumerate(POSES):
        to = pose.position + pose.rotation @ np.array([u, v, 0.0]) - truth["points"]
        elevation = np.degrees(np.arcsin(np.einsum("ij,ij->i", truth["normals"], to) / np.linalg.norm(to, axis=1)))
        code = codes[j, truth["rows"], truth["cols"]]
        considered = code != 1
        assert np.all(code[considered & (elevation < 14.5)] == SAMPLE_GRAZING)
        assert not np.any(code[considered & (elevation > 15.5)] == SAMPLE_GRAZING)
        seen += int((considered & (elevation < 14.5)).sum())
    assert seen > 100
    view = np.degrees(np.arcsin(np.einsum("ij,ij->i", truth["normals"], truth["view"])))
    reason = at_truth(result, truth, result.reason)
    assert np.all(np.isin(reason[view < 14.5], [PIXEL_GRAZING_VIEW, PIXEL_EDGE]))  # the sphere's rim: an edge
    assert not np.any(reason[view > 15.5] == PIXEL_GRAZING_VIEW)


def test_a_surface_seen_at_a_grazing_angle():
    """A plane tilted towards the lights, seen at 11°–18° of elevation over the image: its inside
    is grazing view below 15°, not an edge (a flat face explains every depth step)."""
    plane = trimesh.creation.box((0.3, 0.3, 0.001))
    plane.apply_transform(trimesh.transformations.rotation_matrix(math.radians(-76.0), [1, 0, 0]))
    model = isotropic_light()
    rates, truth = render(plane, model, POSES)
    result = estimate_reflectance(rates, None, RIG.camera, plane, POSES, model)
    view = np.degrees(np.arcsin(np.einsum("ij,ij->i", truth["normals"], truth["view"])))
    reason = at_truth(result, truth, result.reason)
    assert (reason == PIXEL_GRAZING_VIEW).sum() > 500 and (reason == PIXEL_VALID).sum() > 500  # split at 15°
    assert np.all(np.isin(reason[view < 14.5], [PIXEL_GRAZING_VIEW, PIXEL_EDGE]))
    assert np.all(reason[view > 15.5] != PIXEL_GRAZING_VIEW)
    assert (reason == PIXEL_EDGE).sum() < 0.2 * len(reason)  # the plane's outline only


def test_edges_of_the_silhouette_are_a_band(directional):
    _, _, truth, result = directional
    on_sphere = np.zeros(truth["shape"], bool)
    sphere_faces = len(trimesh.creation.icosphere(subdivisions=2).faces)
    on_sphere[truth["rows"], truth["cols"]] = truth["face"] < sphere_faces
    hit = np.zeros(truth["shape"], bool)
    hit[truth["rows"], truth["cols"]] = True
    on_plane = hit & ~on_sphere
    cross = np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], bool)
    outline = (on_plane & binary_dilation(on_sphere, cross)) | (on_sphere & binary_dilation(on_plane, cross))
    outline |= hit & binary_dilation(~hit, cross)  # the plane's own silhouette
    band = binary_dilation(outline, np.ones((3, 3), bool), iterations=2)
    far = ~binary_dilation(outline, np.ones((3, 3), bool), iterations=5)
    assert np.all(result.reason[outline] == PIXEL_EDGE)
    assert (result.reason[band & hit] == PIXEL_EDGE).mean() > 0.9
    assert not np.any(result.reason[far & hit] == PIXEL_EDGE)
    assert np.all(result.reason[~hit] == PIXEL_BACKGROUND)


def test_saturated_and_missing_samples(mesh, directional):
    model, rates, truth, reference = directional
    rates = rates.copy()
    saturated = np.zeros(rates.shape[:3], bool)
    saturated[1, 30:40, 60:70] = True  # clipped: the value is wrong
    rates[1, 30:40, 60:70] *= 0.3
    rates[3, 45:50, 20:30] = np.nan  # no HDR value
    rates[:, 50:52, 75:78] = np.nan  # no value at any light
    result = estimate_reflectance(rates, saturated, RIG.camera, mesh, POSES, model)
    considered = reference.sample_code != 1
    code = np.full((len(POSES), *truth["shape"]), 255, np.uint8)
    code[:, result.rows, result.cols] = result.sample_code
    ref = np.full((len(POSES), *truth["shape"]), 255, np.uint8)
    ref[:, reference.rows, reference.cols] = np.where(considered, reference.sample_code, 255)
    for j, rows, cols in ((1, slice(30, 40), slice(60, 70)), (3, slice(45, 50), slice(20, 30))):
        block = ref[j, rows, cols]
        where = np.isin(block, [SAMPLE_USED, SAMPLE_SPECULAR_GEOMETRY, SAMPLE_SPECULAR_OUTLIER])
        assert where.sum() > 10
        assert np.all(code[j, rows, cols][where] == SAMPLE_SATURATED)
    assert np.all(result.reason[50:52, 75:78][reference.reason[50:52, 75:78] == PIXEL_VALID] == PIXEL_FEW_SATURATED)
    assert np.all(np.isnan(result.rho["measured"][50:52, 75:78]))
    valid = (at_truth(result, truth, result.reason) == PIXEL_VALID) & same_face(result, truth)
    rel = at_truth(result, truth, result.rho["measured"])[valid] / truth["rho"][valid] - 1
    assert np.abs(rel).max() < 1e-3  # the clipped values never entered the fit


def test_specular_highlights_geometric_and_outlier(mesh, directional):
    model, rates, truth, reference = directional
    # geometric: the half vector within 15° of the normal (default)
    (u, v), _ = light_centre(model)
    code = np.full((len(POSES), *truth["shape"]), 255, np.uint8)
    code[:, reference.rows, reference.cols] = reference.sample_code
    seen = 0
    for j, pose in enumerate(POSES):
        to = pose.position + pose.rotation @ np.array([u, v, 0.0]) - truth["points"]
        h = to / np.linalg.norm(to, axis=1, keepdims=True) + truth["view"]
        h /= np.linalg.norm(h, axis=1, keepdims=True)
        angle = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", h, truth["normals"]), -1, 1)))
        c = code[j, truth["rows"], truth["cols"]]
        free = np.isin(c, [SAMPLE_USED, SAMPLE_SPECULAR_GEOMETRY, SAMPLE_SPECULAR_OUTLIER])
        assert np.all(c[free & (angle < 14.5)] == SAMPLE_SPECULAR_GEOMETRY)
        assert not np.any(c[free & (angle > 15.5)] == SAMPLE_SPECULAR_GEOMETRY)
        seen += int((free & (angle < 14.5)).sum())
    assert seen > 50
    # residual test: a highlight 40 % above the diffuse light at one light, geometric test off
    bright = rates.copy()
    bright[2, 20:30, 40:50] *= 1.4
    settings = ReflectanceSettings(specular_deg=0.0)
    result = estimate_reflectance(bright, None, RIG.camera, mesh, POSES, model, settings=settings)
    code = np.full((len(POSES), *truth["shape"]), 255, np.uint8)
    code[:, result.rows, result.cols] = result.sample_code
    block = code[:, 20:30, 40:50]
    enough = (np.isin(block, [SAMPLE_USED, SAMPLE_SPECULAR_OUTLIER]).sum(axis=0) >= 3) & (block[2] != 1)
    assert enough.sum() > 15
    assert np.all(block[2][enough] == SAMPLE_SPECULAR_OUTLIER)
    assert not np.any(np.delete(code, 2, axis=0) == SAMPLE_SPECULAR_OUTLIER)  # no other light dropped
    valid = (at_truth(result, truth, result.reason) == PIXEL_VALID) & same_face(result, truth)
    rel = at_truth(result, truth, result.rho["measured"])[valid] / truth["rho"][valid] - 1
    assert np.abs(rel).max() < 1e-3


# --- bad input ------------------------------------------------------------------------------------------------
def test_bad_arrays_and_meshes_are_one_line_errors(mesh, directional):
    model, rates, _, _ = directional
    away = mesh.copy()
    away.apply_translation([5.0, 0.0, 0.0])
    with pytest.raises(ReflectanceError, match=r"^no camera ray meets the mesh .*check \[object\] pose and units_m$"):
        estimate_reflectance(rates, None, RIG.camera, away, POSES, model)
    with pytest.raises(ReflectanceError, match=r"radiance: expected shape \(5, 80, 100, 3\)"):
        estimate_reflectance(rates[:, :-1], None, RIG.camera, mesh, POSES, model)
    with pytest.raises(ReflectanceError, match="at least 2"):
        estimate_reflectance(rates[:1], None, RIG.camera, mesh, POSES[:1], model)
    with pytest.raises(
        ReflectanceError, match=r"^no valid points: \d+ superpixels on the mesh, all excluded \(.*few-lights-saturated"
    ):
        estimate_reflectance(rates, np.ones(rates.shape[:3], bool), RIG.camera, mesh, POSES, model)
    with pytest.raises(ReflectanceError, match="outlier"):
        ReflectanceSettings(outlier=0.0)


def test_mesh_files(tmp_path):
    bad = tmp_path / "broken.ply"
    bad.write_bytes(b"ply\nformat nonsense\n\x00\x01")
    with pytest.raises(ReflectanceError, match=r"broken\.ply: cannot read the mesh"):
        load_mesh(bad)
    with pytest.raises(ReflectanceError, match=r"nothing\.obj: mesh file not found"):
        load_mesh(tmp_path / "nothing.obj")
    path = tmp_path / "box.stl"
    trimesh.creation.box((10.0, 20.0, 30.0)).export(path)
    from drivers.pose import Pose

    placed = load_mesh(path, 0.001, Pose(0.1, 0.0, 0.0, 0.0, 0.0, math.pi / 2))
    np.testing.assert_allclose(placed.bounds, [[0.09, -0.005, -0.015], [0.11, 0.005, 0.015]], atol=1e-12)


# --- from a run file ----------------------------------------------------------------------------------------------
def write_run(path, rig, rates):
    """An object run whose single-exposure frames hold the rates (RGGB mosaic, 12 bit, the
    brightest site at 80 % of the range)."""
    cam = rig.camera
    gain = cam.gain_e_per_dn
    exposure = 0.8 * (cam.white_level - cam.black_level_dn) * gain / float(np.nanmax(rates))
    tools, lights = rig.tool_poses(), rig.light_poses()
    header = RunHeader(
        run_id=path.stem,
        rig=rig,
        tool_poses=tools,
        light_poses=lights,
        max_exposures=1,
        frame_shape=(cam.height, cam.width),
        bracket={"mode": "fixed", "exposures_s": [exposure]},
        metadata={},
        devices={},
        software_version="test",
        created_utc="2026-11-21T00:00:00+00:00",
        preset="object-arc",
    )
    with RunFileWriter.create(path, header) as writer:
        for j, tool in enumerate(tools):
            mosaic = np.zeros((cam.height, cam.width))
            rgb = np.nan_to_num(rates[j])
            mosaic[0::2, 0::2], mosaic[0::2, 1::2] = rgb[..., 0], rgb[..., 1]
            mosaic[1::2, 0::2], mosaic[1::2, 1::2] = rgb[..., 1], rgb[..., 2]
            dn = np.clip(np.round(cam.black_level_dn + mosaic * exposure / gain), 0, cam.white_level).astype(np.uint16)
            frame = RawFrame(
                dn, np.full((2, 2), float(cam.black_level_dn)), cam.white_level, "RGGB", exposure, 0.0, "test"
            )
            writer.write_position(j, tool, PositionTimes(0.0, 0.0, 0.0), [frame])
        writer.set_status("complete")
    return path


@pytest.fixture(scope="module")
def object_run(tmp_path_factory, mesh, directional):
    folder = tmp_path_factory.mktemp("object")
    mesh_path = folder / "scene.ply"
    mesh.export(mesh_path)
    rig = rig_from_dict(rig_dict(mesh=str(mesh_path), units_m=1.0, up=[0.0, 1.0, 0.0]))
    model, rates, truth, _ = directional
    light_dir = folder / "light-results"
    light_dir.mkdir()
    model.save(light_dir / "light-run.light.json")
    run = write_run(folder / "object-run.h5", rig, rates)
    return run, light_dir, mesh_path, truth


def test_reflectance_from_run_writes_every_output(object_run, tmp_path):
    run, light_dir, _, truth = object_run
    out = tmp_path / "out"
    stages = set()
    result = reflectance_from_run(run, light_dir, None, out, progress=lambda stage, done, total: stages.add(stage))
    assert {"hdr", "lights"} <= stages
    assert result.warnings == []
    valid = (at_truth(result, truth, result.reason) == PIXEL_VALID) & same_face(result, truth)
    rel = at_truth(result, truth, result.rho["measured"])[valid] / truth["rho"][valid] - 1
    assert np.median(np.abs(rel)) < 1e-3  # 12-bit quantisation of one exposure
    for method in ("collimated", "isotropic", "measured"):
        exr = read_exr(out / f"albedo-{method}.exr")
        assert exr.shape == (80, 100, 3)
        np.testing.assert_allclose(exr, result.rho[method].astype(np.float32), rtol=1e-6)  # NaN where invalid
        assert np.isnan(exr[result.reason != PIXEL_VALID]).all()
        assert (out / f"albedo-{method}.png").stat().st_size > 200
    assert (out / "reasons.png").is_file() and (out / "profiles.png").stat().st_size > 5000
    summary = json.loads((out / "reflectance.json").read_text())
    assert summary["valid"] == int((result.reason == PIXEL_VALID).sum())
    assert sum(summary["pixel_reasons"].values()) == 80 * 100
    assert summary["methods"]["measured"]["median"] == pytest.approx(
        np.median(result.rho_points["measured"][result.valid], axis=0).tolist()
    )
    assert summary["light_model"].endswith("light-run.light.json") and summary["run_id"] == "object-run"
    assert set(summary["profiles"]) >= {"height_m", "collimated", "isotropic", "measured"}
    with h5py.File(out / "reflectance.h5") as f:
        np.testing.assert_array_equal(f["rho/measured"][()], result.rho_points["measured"])
        assert f["sample_code"].shape == (5, len(result.rows))
        np.testing.assert_allclose(f["heights"][()], result.points[:, 1])  # up = +y, object frame = rig frame
    page = (out / "report.html").read_text()
    assert "Profiles along the object" in page and page.count("data:image/png;base64") >= 5
    assert (out / "object-run.results.h5").is_file()  # the HDR step ran into --out


def test_uv_texture_of_a_plane(tmp_path):
    """A plane with UVs: the texture holds ρ where the camera saw it."""
    plane = trimesh.creation.box((0.2, 0.16, 0.001))
    plane.apply_translation([0.0, 0.0, -0.0005])
    plane.visual = trimesh.visual.TextureVisuals(
        uv=np.column_stack([(plane.vertices[:, 0] + 0.1) / 0.2, (plane.vertices[:, 1] + 0.08) / 0.16])
    )
    model = isotropic_light()
    rates, truth = render(plane, model, POSES)
    result = estimate_reflectance(rates, None, RIG.camera, plane, POSES, model)
    assert result.uv is not None
    from processing.reflectance.maps import reflectance_profiles, uv_texture

    texture = uv_texture(result, "measured", 64)
    filled = np.isfinite(texture[..., 0])
    assert filled.mean() > 0.5
    rho = result.rho_points["measured"][result.valid]
    for c in range(3):  # texels (filled holes too) are means of samples: never outside their range
        values = texture[..., c][filled]
        assert rho[:, c].min() - 1e-12 <= values.min() and values.max() <= rho[:, c].max() + 1e-12
    # the texel of a point holds the albedo there (its texel's mean: the albedo varies smoothly)
    point = np.array([[0.03, -0.02, 0.0]])
    col, row = int((0.03 + 0.1) / 0.2 * 64), int((1 - (-0.02 + 0.08) / 0.16) * 64)
    assert texture[row, col] == pytest.approx(albedo(point)[0], rel=0.03)
    profiles = reflectance_profiles(result, bins=8)
    assert len(profiles["height_m"]) == 8 and np.isfinite(profiles["measured"]["median"]).sum() >= 6
    files = write_outputs(result, tmp_path, texture_size=64)
    np.testing.assert_allclose(read_exr(files["texture-measured.exr"]), texture.astype(np.float32), rtol=1e-6)
    assert "Albedo in the mesh's UV space" in files["report.html"].read_text()


def test_light_from_another_rig_is_refused(object_run, tmp_path):
    run, _, _, _ = object_run
    other = rig_dict()
    other["name"] = "bench-rig"
    other["light"] = {"light_to_tool": {"position_m": [0.0, 0.0, 0.05]}}
    path = directional_light(rig_section=other).save(tmp_path / "other.light.json")
    with pytest.raises(ReflectanceError) as info:
        reflectance_from_run(run, path, None, tmp_path / "out")
    message = str(info.value)
    assert "\n" not in message
    assert "light results from a different rig" in message and "'bench-rig'" in message and "'object-test'" in message
    assert "light frame would not be the same" in message
    # a model that names its rig only: the check cannot be made, a warning says so
    plain = LightModel(directional_light().sources, "W/sr", {"rig": "default"}).save(tmp_path / "plain.light.json")
    result = reflectance_from_run(run, plain, None, tmp_path / "out2")
    assert any("could not be checked" in w for w in result.warnings)


def test_run_without_object_and_other_bad_input(object_run, directional, tmp_path):
    run, light_dir, mesh_path, _ = object_run
    _, rates, _, _ = directional
    bare = write_run(tmp_path / "bare.h5", rig_from_dict(rig_dict()), rates)
    with pytest.raises(
        ReflectanceError,
        match=r"bare\.h5: the run's rig 'object-test' has no \[object\] and no mesh was given \(--mesh\)",
    ):
        reflectance_from_run(bare, light_dir, None, tmp_path / "o1")
    broken = tmp_path / "broken.stl"
    broken.write_text("solid nothing\nendsolid\n")
    with pytest.raises(ReflectanceError, match=r"broken\.stl: cannot read the mesh"):
        reflectance_from_run(run, light_dir, broken, tmp_path / "o2")
    with pytest.raises(ReflectanceError, match=r"no \*\.light\.json light model in this folder"):
        reflectance_from_run(run, tmp_path, None, tmp_path / "o3")
    with pytest.raises(ReflectanceError, match="run records no light model"):
        reflectance_from_run(run, None, None, tmp_path / "o4")
    assert find_light_model(light_dir / "light-run.light.json").name == "light-run.light.json"


def test_cli_reflectance(object_run, tmp_path):
    run, light_dir, mesh_path, _ = object_run
    out = tmp_path / "cli"
    result = runner.invoke(
        app, ["reflectance", str(run), "--light", str(light_dir), "--mesh", str(mesh_path), "--out", str(out)]
    )
    assert result.exit_code == 0, result.output
    assert "measured" in result.output and f"outputs in {out}" in result.output
    assert (out / "report.html").is_file()
    bad = runner.invoke(app, ["reflectance", str(run), "--light", str(tmp_path / "none.light.json"), "--out", str(out)])
    assert bad.exit_code == 2
    assert bad.output.strip().startswith("error: ") and len(bad.output.strip().splitlines()) == 1
    assert "none.light.json: light model not found" in bad.output


def test_a_corrupt_object_run_is_refused_in_one_line_before_any_output(object_run, tmp_path):
    """A bit flipped in one light position's frame after its HDR merge: one line naming the run,
    the position and the frame before any output; with --ignore-corrupt that light is left out,
    and the warnings and the summary say so."""
    import shutil

    from test_checksums import flip_bit

    from processing.light_run.run import process_run

    run, light_dir, _, truth = object_run
    corrupt = tmp_path / run.name
    shutil.copy(run, corrupt)
    hdr_only = ProcessingOptions.checked(steps=("hdr",), images=False)
    process_run(corrupt, None, hdr_only)  # HDR results beside the run, merged before the flip
    flip_bit(corrupt, 2, 0, bit=8 * 200 + 5)
    out = tmp_path / "out"
    refused = runner.invoke(app, ["reflectance", str(corrupt), "--light", str(light_dir), "--out", str(out)])
    assert refused.exit_code == 2
    assert re.fullmatch(
        rf"error: {re.escape(str(corrupt))}: position 2 frame 0 \(exposure index 0, [0-9.]+ s\) fails its checksum "
        r"\(corrupt data: the stored bytes differ from those written\); --ignore-corrupt processes the rest\n",
        refused.stderr,
    ), refused.stderr
    assert not out.exists()  # the results beside the run are sound: the frames are checked all the same
    result = reflectance_from_run(corrupt, light_dir, None, out, ignore_corrupt=True)
    skipped = [w for w in result.warnings if "skipped positions 2 (--ignore-corrupt)" in w]
    assert len(skipped) == 1 and skipped[0].startswith(f"{corrupt}: ")
    summary = json.loads((out / "reflectance.json").read_text())
    assert summary["positions"] == [0, 1, 3, 4]
    assert summary["skipped_corrupt"]["positions"] == [2]
    assert [(f["position"], f["frame"]) for f in summary["skipped_corrupt"]["frames"]] == [(2, 0)]
    valid = (at_truth(result, truth, result.reason) == PIXEL_VALID) & same_face(result, truth)
    rel = at_truth(result, truth, result.rho["measured"])[valid] / truth["rho"][valid] - 1
    assert valid.sum() > 1000 and np.median(np.abs(rel)) < 1e-3  # four lights measure it as well as five


def test_another_runs_reflectance_is_not_overwritten_without_overwrite(object_run, directional, tmp_path):
    """An --out holding another run's reflectance: refused in one line, its files untouched;
    replaced with --overwrite; and the same run's own outputs are replaced without it."""
    from drivers.contracts.runfile import RunFile

    run, light_dir, _, _ = object_run
    with RunFile.open(run) as opened:
        rig = opened.header.rig
    other = write_run(tmp_path / "other-run.h5", rig, directional[1])
    out = tmp_path / "shared"
    reflectance_from_run(other, light_dir, None, out)
    theirs = (out / "reflectance.json").read_bytes()
    with h5py.File(out / "reflectance.h5") as f:
        assert f.attrs["run_id"] == "other-run"
    args = ["reflectance", str(run), "--light", str(light_dir), "--out", str(out)]
    refused = runner.invoke(app, args)
    assert refused.exit_code == 2
    assert refused.stderr.strip() == (
        f"error: {out / 'reflectance.json'}: holds the outputs of another run (other-run), not of run object-run "
        f"({run}): pass --overwrite to replace it, or choose another --out"
    )
    assert (out / "reflectance.json").read_bytes() == theirs and not (out / "object-run.results.h5").exists()
    (out / "reflectance.json").unlink()
    (out / "reflectance.h5").unlink()  # what is left says nothing of whose it is: refused too
    unknown = runner.invoke(app, args)
    assert unknown.exit_code == 2 and "report.html: already there and not known to be written for run object-run" in (
        unknown.stderr
    )
    replaced = runner.invoke(app, [*args, "--overwrite"])
    assert replaced.exit_code == 0, replaced.output
    assert json.loads((out / "reflectance.json").read_text())["run_id"] == "object-run"
    again = runner.invoke(app, args)  # its own outputs: replaced without --overwrite
    assert again.exit_code == 0, again.output


def test_aperture_mean_cos4_matches_monte_carlo_over_the_disc():
    """The simulator averages cos⁴β over the aperture; the estimator must divide by the same."""
    from processing.reflectance.camera import aperture_mean_cos4

    f, radius = 0.025, 0.025 / 8 / 2  # f/8
    rng = np.random.default_rng(7)
    r, t = radius * np.sqrt(rng.random(400_000)), 2 * np.pi * rng.random(400_000)
    ax, ay = r * np.cos(t), r * np.sin(t)
    for x, y in [(0.0, 0.0), (0.2, 0.1), (0.3, -0.2)]:
        mc = np.mean((f / np.sqrt((ax + x * f) ** 2 + (ay + y * f) ** 2 + f * f)) ** 4)
        # Monte Carlo standard error ~1e-5; the chief ray alone is off by up to 4e-3.
        assert aperture_mean_cos4(np.array(x), np.array(y), radius, f) == pytest.approx(mc, rel=1e-4)
    assert aperture_mean_cos4(np.array(0.0), np.array(0.0), 0.0, f) == 1.0
