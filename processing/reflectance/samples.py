"""Which (light, pixel) samples the albedo is solved from: the surface the camera sees, each
light's irradiance there under every light model, and the reason each excluded sample is out."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from drivers.contracts.rig import Camera
from drivers.pose import Pose
from processing.lightmodel import LightModel
from processing.reflectance.camera import SuperpixelRays, dilate, edge_core, first_hits
from processing.reflectance.codes import (
    PIXEL_BACKGROUND,
    PIXEL_EDGE,
    PIXEL_GRAZING_VIEW,
    PIXEL_VALID,
    SAMPLE_GRAZING,
    SAMPLE_HOUSING,
    SAMPLE_NO_IRRADIANCE,
    SAMPLE_PIXEL_EXCLUDED,
    SAMPLE_SATURATED,
    SAMPLE_SHADOW,
    SAMPLE_SPECULAR_GEOMETRY,
    SAMPLE_SPECULAR_OUTLIER,
    SAMPLE_USED,
    ReflectanceError,
    ReflectanceSettings,
)
from processing.reflectance.lights import LIGHT_MODELS, light_centre, to_rig
from processing.trace import housing_blocks

if TYPE_CHECKING:
    import trimesh


@dataclass
class Surface:
    """What the camera's chief rays meet on the mesh: the reason code of every superpixel
    (:data:`~processing.reflectance.codes.PIXEL_CODES`, so far background, edge, grazing view
    or valid) and, at each superpixel the rays hit (``rows``, ``cols``), the point, its flat face
    normal turned towards the camera, the direction to the camera and the face."""

    rays: SuperpixelRays
    reason: np.ndarray
    rows: np.ndarray
    cols: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    view: np.ndarray
    faces: np.ndarray


def surface_seen(
    camera: Camera, mesh_rig: trimesh.Trimesh, shape: tuple[int, int], settings: ReflectanceSettings, mesh_name: str
) -> Surface:
    """The chief rays of the superpixel grid ``shape`` cast on the mesh, with the pixels at
    silhouettes and depth steps (dilated by ``edge_margin``) and those seen at a grazing angle
    marked.

    Raises
    ------
    ReflectanceError
        No camera ray meets the mesh.
    """
    rays = SuperpixelRays.of(camera, shape)
    flat_dirs = rays.directions.reshape(-1, 3)
    origins = np.broadcast_to(rays.centre, flat_dirs.shape)
    faces_all, depth_all = first_hits(mesh_rig, np.ascontiguousarray(origins), flat_dirs)
    hit_flat = (faces_all >= 0) & np.isfinite(depth_all) & (depth_all > 0)
    if not hit_flat.any():
        centre = mesh_rig.bounds.mean(axis=0)
        raise ReflectanceError(
            f"no camera ray meets {mesh_name} (its centre is at {np.round(centre, 4).tolist()} m "
            f"in the rig frame); check [object] pose and units_m"
        )
    face_normals = np.asarray(mesh_rig.face_normals, dtype=float)
    hit = hit_flat.reshape(shape)
    depth = np.where(hit_flat, depth_all, np.nan).reshape(shape)
    normals_grid = np.zeros((*shape, 3))
    normals_grid.reshape(-1, 3)[hit_flat] = face_normals[faces_all[hit_flat]]
    facing = np.einsum("...k,...k->...", normals_grid, rays.directions)
    normals_grid *= np.where(facing > 0, -1.0, 1.0)[..., None]  # towards the camera
    points_grid = rays.centre + depth[..., None] * rays.directions
    bad_normal = hit & ~(np.linalg.norm(normals_grid, axis=-1) > 0.5)  # a degenerate face
    normals_grid[bad_normal] = -rays.directions[bad_normal]  # any unit vector: these pixels are edges
    core = (
        edge_core(
            hit, depth, points_grid, normals_grid, rays.directions, rays.centre, rays.angle, settings.depth_tolerance
        )
        | bad_normal
    )
    band = dilate(core, settings.edge_margin)
    cos_view = -np.einsum("...k,...k->...", normals_grid, rays.directions)
    grazing_view = cos_view < math.sin(math.radians(settings.grazing_view_deg))
    reason = np.full(shape, PIXEL_VALID, np.uint8)
    reason[~hit] = PIXEL_BACKGROUND
    reason[hit & band] = PIXEL_EDGE
    reason[hit & ~band & grazing_view] = PIXEL_GRAZING_VIEW
    rows, cols = np.nonzero(hit)
    return Surface(
        rays,
        reason,
        rows,
        cols,
        points_grid[rows, cols],
        normals_grid[rows, cols],
        -rays.directions[rows, cols],
        faces_all.reshape(shape)[rows, cols],
    )


@dataclass
class LightSamples:
    """Every (light, point) sample: its code (:data:`~processing.reflectance.codes.SAMPLE_CODES`),
    the irradiance (channel mean) and each channel's share of it (None: a grey light) under
    every light model, and what each model made of each light position."""

    codes: np.ndarray  # (n_lights, N) uint8
    irradiance: dict[str, np.ndarray]  # (n_lights, N)
    tints: dict[str, np.ndarray | None]  # (n_lights, N, 3) float32
    lights: list[dict[str, Any]]


def light_samples(
    surface: Surface,
    mesh_rig: trimesh.Trimesh,
    light_poses: Sequence[Pose],
    light_model: LightModel,
    object_centre: np.ndarray,
    methods: tuple[str, ...],
    housing: tuple[float, float] | None,
    no_data: np.ndarray,
    settings: ReflectanceSettings,
    progress: Callable[[int], None],
) -> LightSamples:
    """Each light position's irradiance at the points under ``methods`` and the samples it
    excludes: hidden by the light's housing, lit at a grazing angle, in a cast shadow, without
    data (``no_data``, (n_lights, N): saturated or missing), without irradiance, or where a
    specular lobe would peak. ``progress(j)`` after light ``j``."""
    n_lights, n_points = len(light_poses), len(surface.points)
    codes = np.full((n_lights, n_points), SAMPLE_USED, np.uint8)
    codes[:, surface.reason[surface.rows, surface.cols] != PIXEL_VALID] = SAMPLE_PIXEL_EXCLUDED
    samples = LightSamples(codes, {m: np.zeros((n_lights, n_points)) for m in methods}, dict.fromkeys(methods), [])
    centre_uv, i0 = light_centre(light_model)
    for j, pose in enumerate(light_poses):
        progress(j)
        centre_point = to_rig(pose, centre_uv)
        towards = centre_point - surface.points
        omega = towards / np.linalg.norm(towards, axis=1, keepdims=True)
        cos_in = np.einsum("ij,ij->i", surface.normals, omega)
        models = {m: LIGHT_MODELS[m](light_model, pose, object_centre) for m in methods}
        for m, lm in models.items():
            samples.irradiance[m][j], tint = lm.irradiance_and_tint(surface.points, surface.normals)
            if tint is not None:
                tints = samples.tints[m]
                if tints is None:
                    tints = samples.tints[m] = np.ones((n_lights, n_points, 3), np.float32)
                tints[j] = tint
        samples.lights.append(
            {
                "index": j,
                "position_m": pose.position.tolist(),
                "rotation_rad": [pose.rx, pose.ry, pose.rz],
                "isotropic_point_m": centre_point.tolist(),
                "I0": i0,
                **{f"{m}": lm.describe() for m, lm in models.items() if m != "measured"},
            }
        )
        no_irradiance = np.zeros(n_points, bool)
        for m in methods:
            no_irradiance |= ~(samples.irradiance[m][j] > 0)
        half = omega + surface.view
        half /= np.linalg.norm(half, axis=1, keepdims=True)
        excluded = (
            (_hidden_by_housing(surface, pose, housing), SAMPLE_HOUSING),
            (cos_in < math.sin(math.radians(settings.grazing_light_deg)), SAMPLE_GRAZING),
            (_cast_shadow(surface, mesh_rig, pose, light_model, cos_in > 0, settings), SAMPLE_SHADOW),
            (no_data[j], SAMPLE_SATURATED),
            (no_irradiance, SAMPLE_NO_IRRADIANCE),
            (np.einsum("ij,ij->i", half, surface.normals) > _cos_specular(settings), SAMPLE_SPECULAR_GEOMETRY),
        )
        code = codes[j]
        for mask, value in excluded:
            code[(code == SAMPLE_USED) & mask] = value
    return samples


def _cos_specular(settings: ReflectanceSettings) -> float:
    """The half vector's cosine to the normal above which a specular lobe would peak (2: never)."""
    return math.cos(math.radians(settings.specular_deg)) if settings.specular_deg > 0 else 2.0


def _hidden_by_housing(surface: Surface, pose: Pose, housing: tuple[float, float] | None) -> np.ndarray:
    """(N,) the points the light's housing hides from the camera at this light pose."""
    if housing is None or not housing[0] > 0:
        return np.zeros(len(surface.points), bool)
    start = np.broadcast_to(surface.rays.centre, surface.points.shape)
    return housing_blocks(start, surface.points, pose, float(housing[0]), float(housing[1]))


def _cast_shadow(
    surface: Surface,
    mesh_rig: trimesh.Trimesh,
    pose: Pose,
    light_model: LightModel,
    lit_side: np.ndarray,
    settings: ReflectanceSettings,
) -> np.ndarray:
    """(N,) the points on the lit side whose ray to any source of the measured model meets the
    mesh, dilated by ``shadow_margin`` superpixels on the grid."""
    n_points = len(surface.points)
    shadow = np.zeros(n_points, bool)
    if lit_side.any():
        scene = float(np.linalg.norm(np.ptp(mesh_rig.bounds, axis=0)))
        start = surface.points[lit_side] + 1e-5 * max(scene, 1e-6) * surface.normals[lit_side]
        for source in light_model.sources:
            to_source = to_rig(pose, source.centre_m) - start
            dist = np.linalg.norm(to_source, axis=1)
            first, along = first_hits(mesh_rig, start, to_source / dist[:, None])
            shadow[np.flatnonzero(lit_side)[(first >= 0) & (along > 0) & (along < dist)]] = True
    grid = np.zeros(surface.reason.shape, bool)
    grid[surface.rows[shadow], surface.cols[shadow]] = True
    return dilate(grid, settings.shadow_margin)[surface.rows, surface.cols] & lit_side


def drop_outliers(codes: np.ndarray, luminance: np.ndarray, irradiance: np.ndarray, threshold: float) -> None:
    """The residual test for highlights, in place on ``codes``.

    For every point with at least 3 usable lights, each light's radiance is predicted from
    the least-squares fit of the others (leave-one-out, measured model); the light with the
    largest relative excess is dropped (:data:`SAMPLE_SPECULAR_OUTLIER`) if the excess is
    above ``threshold``, and the test repeats while at least 3 lights remain.
    """
    if not math.isfinite(threshold):
        return
    L = np.where(np.isfinite(luminance), luminance, 0.0)
    E = irradiance
    while True:
        used = codes == SAMPLE_USED
        candidates = used.sum(axis=0) >= 3
        if not candidates.any():
            return
        idx = np.flatnonzero(candidates)
        u, lum, e = used[:, idx], L[:, idx], E[:, idx]
        s_le = np.where(u, lum * e, 0.0).sum(axis=0)
        s_ee = np.where(u, e * e, 0.0).sum(axis=0)
        with np.errstate(divide="ignore", invalid="ignore"):
            rho_others = (s_le[None] - lum * e) / (s_ee[None] - e * e)
            predicted = rho_others * e
            excess = np.where(u & (predicted > 0), lum / predicted - 1.0, -np.inf)
        worst = np.argmax(excess, axis=0)
        value = excess[worst, np.arange(len(idx))]
        drop = value > threshold
        if not drop.any():
            return
        codes[worst[drop], idx[drop]] = SAMPLE_SPECULAR_OUTLIER
