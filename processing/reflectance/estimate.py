"""The albedo per pixel under the three light models, from one object run's HDR radiance."""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import trimesh
from numpy.typing import ArrayLike

from drivers.contracts.rig import Camera, Rig
from drivers.pose import Pose
from processing.lightmodel import LightModel
from processing.reflectance.camera import camera_from
from processing.reflectance.codes import (
    FEW_FROM_SAMPLE,
    METHODS,
    PIXEL_BACKGROUND,
    PIXEL_CODES,
    PIXEL_SHORT,
    PIXEL_VALID,
    SAMPLE_CODES,
    SAMPLE_PIXEL_EXCLUDED,
    SAMPLE_SHORT,
    SAMPLE_USED,
    ReflectanceError,
    ReflectanceSettings,
)
from processing.reflectance.lights import LIGHT_MODELS
from processing.reflectance.samples import LightSamples, Surface, drop_outliers, light_samples, surface_seen

if TYPE_CHECKING:
    from processing.reflectance.brdf import MaterialResult

log = logging.getLogger("mirrorgonio.processing")


@dataclass
class ReflectanceResult:
    """What :func:`estimate_reflectance` found.

    Grid arrays are on the superpixel grid ``(H/2, W/2)``; point arrays have one row per
    superpixel whose chief ray meets the mesh (``N`` of them, in row-major order), so that
    ``rho[m][rows, cols] == rho_points[m]``.

    Attributes
    ----------
    methods : tuple of str
        The light models, keys of :data:`LIGHT_MODELS`.
    shape : tuple of int
        ``(H/2, W/2)``.
    rho : dict of str to ndarray (H/2, W/2, 3)
        Albedo per method and channel (R, G, B); NaN where the pixel is not valid.
    reason : ndarray (H/2, W/2) of uint8
        The pixel's reason code (:data:`PIXEL_CODES`; 0 = valid).
    rows, cols : ndarray (N,)
        Superpixel indices of the points on the object.
    points, normals : ndarray (N, 3)
        Hit points and flat face normals (towards the camera), rig frame, metres.
    faces : ndarray (N,)
        Index of the face hit.
    heights : ndarray (N,)
        Height along the object's vertical axis, ``x_object · up``, metres.
    uv : ndarray (N, 2) or None
        The mesh's texture coordinates at the hit points, when it has UVs.
    radiance : ndarray (n_lights, N, 3)
        ``L_o = rate / (k·cos⁴β)`` per light and channel.
    irradiance : dict of str to ndarray (n_lights, N)
        ``E`` per method and light: the channel mean.
    colour : dict of str to ndarray (n_lights, N, 3) or None
        Each channel's share of ``E`` per method, light and point (mean 1: the sources'
        colours as they mix there); None for a grey light. Each channel's irradiance,
        the one ``rho`` divides by, is ``E·colour`` (:meth:`irradiance_rgb`).
    sample_code : ndarray (n_lights, N) of uint8
        Each sample's code (:data:`SAMPLE_CODES`; 0 = used).
    rho_points : dict of str to ndarray (N, 3)
        ``rho`` at the points (NaN where not valid).
    lights : list of dict
        Per light position: its pose and what each model made of it (isotropic point, I₀,
        collimated direction and E₀).
    settings : ReflectanceSettings
        The thresholds used.
    object_centre : ndarray (3,)
        Centre of the mesh's bounding box in the rig frame (the collimated model's origin).
    warnings : list of str
        Things worth knowing that did not stop the estimate.
    outputs : dict of str to Path
        Files written by :func:`write_outputs` (empty until then).
    """

    methods: tuple[str, ...]
    shape: tuple[int, int]
    rho: dict[str, np.ndarray]
    reason: np.ndarray
    rows: np.ndarray
    cols: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    faces: np.ndarray
    heights: np.ndarray
    uv: np.ndarray | None
    radiance: np.ndarray
    irradiance: dict[str, np.ndarray]
    colour: dict[str, np.ndarray | None]
    sample_code: np.ndarray
    rho_points: dict[str, np.ndarray]
    lights: list[dict]
    settings: ReflectanceSettings
    object_centre: np.ndarray
    warnings: list[str] = field(default_factory=list)
    outputs: dict[str, Path] = field(default_factory=dict)
    metadata: dict = field(default_factory=dict)
    materials: MaterialResult | None = None  # the BRDF per point (processing.reflectance.materials)

    def irradiance_rgb(self, method: str) -> np.ndarray:
        """Each channel's irradiance per light and point, (n_lights, N, 3) float32: what
        ``rho[method]`` was solved with, ``ρ_c = π Σ_j L_jc E_jc / Σ_j E_jc²`` over the used
        samples."""
        return channel_irradiance(self.irradiance[method], self.colour[method]).astype(np.float32)

    @property
    def valid(self) -> np.ndarray:
        """(N,) bool: the points with an albedo."""
        return self.reason[self.rows, self.cols] == PIXEL_VALID

    @property
    def lights_used(self) -> np.ndarray:
        """(N,) number of lights each point's albedo was solved from."""
        return (self.sample_code == SAMPLE_USED).sum(axis=0)

    def summary(self) -> dict:
        """Counts per reason and per-method statistics of ρ (the ``reflectance.json`` core).

        ``median`` is per channel; ``cv`` is the standard deviation over the mean and
        ``robust_cv`` 1.4826·MAD over the median, both of the channel mean of ρ over the valid
        points.
        """
        reasons = {PIXEL_SHORT[c]: int((self.reason == c).sum()) for c in PIXEL_CODES}
        considered = self.sample_code != SAMPLE_PIXEL_EXCLUDED
        samples = {
            SAMPLE_SHORT[c]: int(((self.sample_code == c) & considered).sum())
            for c in SAMPLE_CODES
            if c != SAMPLE_PIXEL_EXCLUDED
        }
        valid = self.valid
        methods = {}
        for m in self.methods:
            rho = self.rho_points[m][valid]
            grey = rho.mean(axis=1)
            stats: dict[str, Any] = {"valid_points": int(valid.sum())}
            if grey.size:
                median = float(np.median(grey))
                mean = float(grey.mean())
                stats.update(
                    median=[float(v) for v in np.median(rho, axis=0)],
                    median_mean=median,
                    mean=mean,
                    cv=float(grey.std() / mean) if mean != 0 else float("nan"),
                    robust_cv=float(1.4826 * np.median(np.abs(grey - median)) / median)
                    if median != 0
                    else float("nan"),
                    q25=float(np.percentile(grey, 25)),
                    q75=float(np.percentile(grey, 75)),
                )
            methods[m] = stats
        return {
            "superpixels": list(self.shape),
            "on_object": int(len(self.rows)),
            "valid": int(valid.sum()),
            "lights": len(self.lights),
            "pixel_reasons": reasons,
            "sample_reasons": samples,
            "methods": methods,
            "object_centre_m": self.object_centre.tolist(),
            "light_positions": self.lights,
            "settings": asdict(self.settings),
            "warnings": list(self.warnings),
        }


def estimate_reflectance(
    radiance_rgb: np.ndarray,
    saturated: ArrayLike,
    camera: Camera | Rig,
    mesh_rig: trimesh.Trimesh,
    light_poses: Sequence[Pose],
    light_model: LightModel,
    *,
    object_pose: Pose | None = None,
    up: ArrayLike = (0.0, 1.0, 0.0),
    housing: tuple[float, float] | None = None,
    settings: ReflectanceSettings | None = None,
    methods: tuple[str, ...] = METHODS,
    mesh_name: str = "the mesh",
    progress: Callable[[str, int, int], None] | None = None,
) -> ReflectanceResult:
    """Albedo per pixel under three light models, from one object run's HDR radiance.

    Parameters
    ----------
    radiance_rgb : array_like (n_lights, H/2, W/2, 3)
        Each light position's superpixel rate in e⁻/s (R, G, B; the greens averaged:
        :func:`processing.hdr.mosaic.superpixels` of the HDR mosaic times the conversion gain).
        Non-finite values are samples without data.
    saturated : array_like (n_lights, H/2, W/2) of bool, or None
        Superpixels with a site saturated in every exposure.
    camera : drivers.contracts.rig.Camera (or a Rig)
        Intrinsics, pose and ``sensitivity_e_per_s`` = k; its sensor is ``(H, W)``.
    mesh_rig : trimesh.Trimesh
        The object in the rig frame, metres (:func:`load_mesh`).
    light_poses : sequence of Pose
        The light's pose (light frame in the rig frame) at each position.
    light_model : LightModel
        The measured light (:class:`processing.lightmodel.LightModel`), whose sources also
        cast the shadows.
    object_pose : Pose, optional
        The object frame in the rig frame (metres), for the heights; the rig frame if None.
    up : sequence of 3 float
        The object's vertical axis in its own frame (``heights = x_object · up``).
    housing : (radius_m, depth_m), optional
        The light's housing (``[light]`` of the rig): samples it hides from the camera are
        excluded.
    settings : ReflectanceSettings, optional
        Thresholds (the defaults of :class:`ReflectanceSettings` when None).
    methods : sequence of str
        Keys of :data:`LIGHT_MODELS`; ``"measured"`` is always computed (the residual test
        uses it).
    mesh_name : str
        How error messages name the mesh.
    progress : callable, optional
        ``progress(stage, done, total)``.

    Returns
    -------
    ReflectanceResult

    Raises
    ------
    ReflectanceError
        Arrays of the wrong shape, fewer than two light positions, a mesh that no camera
        ray meets, or no valid point at all.

    Notes
    -----
    ``L_o = rate/(k·cos⁴β)`` and, for a Lambertian surface, ``ρ = π·L_o/E(r, n)``
    (``docs/measurement.md``, "Diffuse reflectance under near light"); with several lights
    ``ρ_c = π·Σ_j L_jc E_j / Σ_j E_j²`` over the usable lights, the same for every method.
    """
    settings = settings or ReflectanceSettings()
    camera = camera_from(camera)
    methods = tuple(methods)
    radiance_rgb, sat = _checked(radiance_rgb, saturated, camera, mesh_rig, light_poses, methods, settings, mesh_name)
    n_lights, shape = len(light_poses), radiance_rgb.shape[1:3]

    def report(stage, done, total):
        if progress:
            progress(stage, done, total)

    report("rays", 0, n_lights + 1)
    surface = surface_seen(camera, mesh_rig, shape, settings, mesh_name)
    rows, cols = surface.rows, surface.cols
    k = float(camera.sensitivity_e_per_s)
    radiance = radiance_rgb[:, rows, cols, :] / (k * surface.rays.cos4[rows, cols][None, :, None])
    object_centre = np.asarray(mesh_rig.bounds, float).mean(axis=0)
    samples = light_samples(
        surface,
        mesh_rig,
        light_poses,
        light_model,
        object_centre,
        tuple(dict.fromkeys((*methods, "measured"))),
        housing,
        sat[:, rows, cols] | ~np.all(np.isfinite(radiance_rgb[:, rows, cols, :]), axis=2),
        settings,
        lambda j: report("lights", j + 1, n_lights + 1),
    )
    drop_outliers(samples.codes, radiance.mean(axis=2), samples.irradiance["measured"], settings.outlier)
    enough = _enough_lights(surface, samples.codes, settings)
    if not enough.any():
        raise ReflectanceError(f"no valid points: {len(rows)} superpixels on {mesh_name}, {_all_excluded(surface)}")
    rho_points, rho = _albedo(surface, samples, radiance, methods, enough)
    report("lights", n_lights + 1, n_lights + 1)
    object_pose = object_pose or Pose(0.0, 0.0, 0.0)
    up = np.asarray(up, float) / np.linalg.norm(up)
    points = surface.points
    heights = ((points - object_pose.position) @ object_pose.rotation) @ up
    return ReflectanceResult(
        methods,
        shape,
        rho,
        surface.reason,
        rows,
        cols,
        points,
        surface.normals,
        surface.faces,
        heights,
        uv_at_points(mesh_rig, surface.faces, points),
        radiance,
        {m: samples.irradiance[m] for m in methods},
        {m: samples.tints[m] for m in methods},
        samples.codes,
        rho_points,
        samples.lights,
        settings,
        object_centre,
        _extrapolation_warnings(light_model, light_poses, points[enough]),
    )


def _all_excluded(surface: Surface) -> str:
    """Why every point on the object was excluded: each reason with its count."""
    counts = ", ".join(
        f"{PIXEL_SHORT[c]} {int((surface.reason == c).sum())}"
        for c in PIXEL_CODES
        if c not in (PIXEL_VALID, PIXEL_BACKGROUND) and (surface.reason == c).any()
    )
    return f"all excluded ({counts or 'none'})"


def _checked(radiance_rgb, saturated, camera, mesh_rig, light_poses, methods, settings, mesh_name):
    """The radiance (float64) and the saturation masks, their shapes checked against the camera
    and the lights; the methods and the mesh checked."""
    unknown = [m for m in methods if m not in LIGHT_MODELS]
    if unknown or not methods:
        raise ReflectanceError(
            f"methods: {unknown[0] if unknown else 'none'!r} is not one of {', '.join(LIGHT_MODELS)}"
        )
    radiance_rgb = np.asarray(radiance_rgb, dtype=np.float64)
    n_lights = len(light_poses)
    expected = (n_lights, camera.height // 2, camera.width // 2, 3)
    if radiance_rgb.shape != expected:
        raise ReflectanceError(f"radiance: expected shape {expected} (lights, H/2, W/2, RGB), got {radiance_rgb.shape}")
    if n_lights < settings.min_lights:
        raise ReflectanceError(f"{n_lights} light position(s): the albedo needs at least {settings.min_lights}")
    shape = expected[1:3]
    sat = np.zeros((n_lights, *shape), bool) if saturated is None else np.asarray(saturated, bool)
    if sat.shape != (n_lights, *shape):
        raise ReflectanceError(f"saturated: expected shape {(n_lights, *shape)}, got {sat.shape}")
    if mesh_rig is None or len(getattr(mesh_rig, "faces", ())) == 0:
        raise ReflectanceError(f"{mesh_name}: the mesh has no faces")
    return radiance_rgb, sat


def _enough_lights(surface: Surface, codes: np.ndarray, settings: ReflectanceSettings) -> np.ndarray:
    """(N,) the points with at least ``min_lights`` usable samples; the others, valid pixels till
    now, get the reason that excluded most of their samples."""
    ok = surface.reason[surface.rows, surface.cols] == PIXEL_VALID
    enough = ok & ((codes == SAMPLE_USED).sum(axis=0) >= settings.min_lights)
    few = ok & ~enough
    if few.any():
        excluded = codes[:, few]
        tallies = np.stack([(excluded == c).sum(axis=0) for c in range(len(SAMPLE_CODES))])
        tallies[SAMPLE_USED] = tallies[SAMPLE_PIXEL_EXCLUDED] = -1
        surface.reason[surface.rows[few], surface.cols[few]] = np.vectorize(FEW_FROM_SAMPLE.get)(
            np.argmax(tallies, axis=0)
        ).astype(np.uint8)
    return enough


def _albedo(
    surface: Surface, samples: LightSamples, radiance: np.ndarray, methods: Sequence[str], enough: np.ndarray
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """ρ per method at the points (N, 3) and on the grid (H/2, W/2, 3): ``ρ_c = π Σ_j L_jc E_jc /
    Σ_j E_jc²`` over the used samples, NaN where a point has too few."""
    used = samples.codes == SAMPLE_USED
    w = used.astype(float)
    rho_points: dict[str, np.ndarray] = {}
    rho: dict[str, np.ndarray] = {}
    for m in methods:
        irradiance, tints = samples.irradiance[m], samples.tints[m]
        if tints is None:  # grey: one irradiance for every channel
            num = np.einsum("jn,jnc,jn->nc", w, np.where(used[..., None], radiance, 0.0), irradiance)
            den = np.einsum("jn,jn->n", w, irradiance**2)[:, None]
        else:  # each channel's own irradiance: the light's tint is not the surface's
            channel_e = channel_irradiance(irradiance, tints)
            num = np.einsum("jn,jnc,jnc->nc", w, np.where(used[..., None], radiance, 0.0), channel_e)
            den = np.einsum("jn,jnc->nc", w, channel_e**2)
        with np.errstate(divide="ignore", invalid="ignore"):
            values = math.pi * num / den
        values[~enough] = np.nan
        rho_points[m] = values
        grid = np.full((*surface.reason.shape, 3), np.nan)
        grid[surface.rows, surface.cols] = values
        rho[m] = grid
    return rho_points, rho


def _extrapolation_warnings(light_model: LightModel, light_poses: Sequence[Pose], points: np.ndarray) -> list[str]:
    extrapolated = _extrapolated_fraction(light_model, light_poses, points)
    if extrapolated <= 0.01:
        return []
    return [
        f"{100 * extrapolated:.0f} % of the valid points are lit at angles the light model "
        "extrapolates (outside the θ its samples cover)"
    ]


def channel_irradiance(grey: np.ndarray, colour: np.ndarray | None) -> np.ndarray:
    """Each channel's irradiance (..., 3) from the channel mean ``grey`` and each channel's
    share of it (None: grey, every channel the same)."""
    return grey[..., None] * colour if colour is not None else np.repeat(grey[..., None], 3, axis=-1)


def uv_at_points(mesh: trimesh.Trimesh, faces: np.ndarray, points: np.ndarray) -> np.ndarray | None:
    """The mesh's UV coordinates at hit points (barycentric), or None without UVs."""
    uv = getattr(getattr(mesh, "visual", None), "uv", None)
    if uv is None or len(uv) != len(mesh.vertices):
        return None

    bary = trimesh.triangles.points_to_barycentric(mesh.triangles[faces], points)
    corners = np.asarray(uv, float)[mesh.faces[faces]]  # (N, 3, 2)
    return np.einsum("nk,nkc->nc", bary, corners)


def _extrapolated_fraction(light_model: LightModel, light_poses: Sequence[Pose], points: np.ndarray) -> float:
    """Share of points that some light sees at a θ outside any source's sampled range."""
    if len(points) == 0:
        return 0.0
    flagged = np.zeros(len(points), bool)
    for pose in light_poses:
        local = (points - pose.position) @ pose.rotation
        for s in light_model.sources:
            d = local - np.array([s.centre_m[0], s.centre_m[1], 0.0])
            theta = np.arccos(np.clip(d[:, 2] / np.linalg.norm(d, axis=1), -1.0, 1.0))
            lo, hi = s.fit.theta_range
            if hi > lo:
                flagged |= (theta < lo - 1e-9) | (theta > hi + 1e-9)
    return float(flagged.mean())
