"""The object's whole reflectance from its samples, under each light model, and the relighting check.

The diffuse estimate (:mod:`~processing.reflectance.estimate`) leaves out the samples where a
highlight could be; here those are the ones that matter. Every sample the diffuse estimate
excluded *only* as a possible highlight (``specular-geometry``, ``specular-outlier``) is used
again, with the lit, unshadowed, unsaturated ones, and :func:`~processing.reflectance.brdf.fit_brdf`
fits the diffuse albedo, the specular reflectance F0 and the GGX roughness α per point;
:func:`~processing.reflectance.brdf.share_lobes` fills in the points no highlight reached.

Each light model gives the irradiance of its own (``ReflectanceResult.irradiance_rgb``) and
the direction the light comes from: for the isotropic and the measured models the direction
from the point to the light's isotropic point (the intensity-weighted centroid of the
sources; their spread, a few millimetres at 20–40 cm, turns the direction by well under a
degree, narrower than the sharpest lobe fitted), for the collimated model the one direction
from the object's centre to that point.

Relighting: ``hold_out`` light positions, spread over the schedule, are left out of the fit;
the fitted BRDF under each light model then predicts their photographs, and the RMS of the
difference over the points, relative to the mean radiance, is the check a user believes (it
does not depend on how a model splits diffuse from specular). Noise is included in it: a
perfect model scores the noise.
"""

from __future__ import annotations

import copy
from typing import TYPE_CHECKING, Any

import numpy as np

from drivers.contracts.rig import look_rotation
from drivers.pose import Pose
from processing.reflectance.brdf import (
    CONFIDENCE_OWN,
    BRDFFit,
    Geometry,
    MaterialResult,
    fit_brdf,
    predicted_radiance,
    share_lobes,
)
from processing.reflectance.codes import (
    SAMPLE_SHADOW,
    SAMPLE_SPECULAR_GEOMETRY,
    SAMPLE_SPECULAR_OUTLIER,
    SAMPLE_USED,
)
from processing.reflectance.estimate import ReflectanceResult
from processing.reflectance.lights import MeasuredLight, light_centre, to_rig

if TYPE_CHECKING:
    import trimesh

    from processing.lightmodel import LightModel

#: Fewer light positions than this (after the held-out ones) cannot fit a lobe per point.
MIN_POSITIONS = 8


def held_out_positions(n_lights: int, hold_out: int) -> np.ndarray:
    """``hold_out`` positions spread evenly over the schedule (none when too few remain)."""
    if hold_out <= 0 or n_lights - hold_out < MIN_POSITIONS:
        return np.zeros(0, np.int64)
    return np.unique(np.round((np.arange(hold_out) + 0.5) * n_lights / hold_out - 0.5).astype(np.int64))


def light_directions(result: ReflectanceResult, method: str) -> np.ndarray:
    """Unit vectors from every point towards each light (n_lights, N, 3), as ``method`` sees it."""
    points = result.points
    out = np.empty((len(result.lights), len(points), 3))
    for j, light in enumerate(result.lights):
        target = np.asarray(light["isotropic_point_m"], float)
        if method == "collimated":
            towards = np.broadcast_to(target - result.object_centre, points.shape)
        else:
            towards = target - points
        out[j] = towards / np.linalg.norm(towards, axis=-1, keepdims=True)
    return out


def usable_samples(result: ReflectanceResult) -> np.ndarray:
    """(n_lights, N): samples the BRDF fit takes, highlights included."""
    code = result.sample_code
    return (code == SAMPLE_USED) | (code == SAMPLE_SPECULAR_GEOMETRY) | (code == SAMPLE_SPECULAR_OUTLIER)


def estimate_materials(
    result: ReflectanceResult,
    camera_centre: np.ndarray,
    *,
    hold_out: int = 4,
    max_basis: int = 6,
) -> MaterialResult | None:
    """Fit the BRDF per point under each of the result's light models, and relight the held-out positions.

    Returns None (with nothing fitted) when the run has fewer than :data:`MIN_POSITIONS`
    light positions besides the held-out ones: a lobe needs samples from many directions
    (the ``object-dome`` schedule; ``object-arc``'s five are for the albedo alone).
    """
    n_lights = len(result.lights)
    held = held_out_positions(n_lights, hold_out)
    fitted = np.setdiff1d(np.arange(n_lights), held)
    if len(fitted) < MIN_POSITIONS:
        return None
    view = np.asarray(camera_centre, float) - result.points
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    valid = result.valid
    usable = usable_samples(result) & valid[None, :]
    radiance = result.radiance.astype(float)
    material = MaterialResult({}, fitted, held)
    for method in result.methods:
        irradiance = result.irradiance_rgb(method).astype(float)
        geometry = Geometry.of(light_directions(result, method), view, result.normals)
        sub = Geometry(*(getattr(geometry, name)[fitted] for name in ("cos_l", "cos_v", "cos_h", "cos_vh")))
        fit = fit_brdf(radiance[fitted], irradiance[fitted], sub, usable[fitted])
        fit = share_lobes(fit, radiance[fitted], irradiance[fitted], sub, usable[fitted], max_basis=max_basis)
        material.sigma_scale[method] = neighbour_sigma_scale(fit, result.rows, result.cols)
        fit = scaled_sigmas(fit, material.sigma_scale[method])
        material.fits[method] = fit
        if len(held):
            material.relighting[method] = _relighting(fit, radiance, irradiance, geometry, usable, held)
    return material


def neighbour_sigma_scale(fit: BRDFFit, rows: np.ndarray, cols: np.ndarray) -> dict[str, float]:
    """How much the quoted 1σ understate the point-to-point scatter, per parameter (≥ 1).

    The residuals see the noise, not the errors a point's samples share: its normal (a flat
    facet for a curved surface, a superpixel astride two facets), its irradiance from the
    light model. Those make neighbouring points disagree by more than their 1σ allow. For
    every pair of neighbours on the superpixel grid (right and below) with their own lobes,
    ``z = (p₁ − p₂)/√(σ₁² + σ₂²)``; on a surface whose material changes only at the borders
    of regions, the median |z| is 0.674 when the 1σ are right (a normal's), and its ratio to
    that is the scale. The median keeps the borders (few pairs) from counting. Only ρ and
    α are scaled (F0 takes α's): a scale below 1 is not applied.
    """
    index = np.full((int(rows.max(initial=0)) + 2, int(cols.max(initial=0)) + 2), -1, np.int64)
    index[rows, cols] = np.arange(len(rows))
    own = (fit.confidence == CONFIDENCE_OWN) & np.isfinite(fit.roughness)
    pairs = []
    for dr, dc in ((0, 1), (1, 0)):
        other = index[rows + dr, cols + dc]
        ok = (other >= 0) & own & own[np.maximum(other, 0)]
        pairs.append((np.flatnonzero(ok), other[ok]))
    first = np.concatenate([p[0] for p in pairs])
    second = np.concatenate([p[1] for p in pairs])

    def scale(values: np.ndarray, sigma: np.ndarray) -> float:
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.abs(values[first] - values[second]) / np.hypot(sigma[first], sigma[second])
        z = z[np.isfinite(z)]
        return max(1.0, float(np.median(z)) / 0.6745) if z.size >= 50 else 1.0

    return {
        "diffuse": scale(fit.diffuse.mean(axis=1), np.sqrt(np.mean(fit.sigma_diffuse**2, axis=1))),
        "roughness": scale(np.log(fit.roughness), fit.sigma_roughness / fit.roughness),
    }


def scaled_sigmas(fit: BRDFFit, scale: dict[str, float]) -> BRDFFit:
    """The fit with its 1σ multiplied by :func:`neighbour_sigma_scale`'s factors."""
    out = copy.copy(fit)
    out.sigma_diffuse = fit.sigma_diffuse * scale["diffuse"]
    out.sigma_roughness = fit.sigma_roughness * scale["roughness"]
    out.sigma_specular = fit.sigma_specular * scale["roughness"]
    return out


def _relighting(
    fit: BRDFFit,
    radiance: np.ndarray,
    irradiance: np.ndarray,
    geometry: Geometry,
    usable: np.ndarray,
    held: np.ndarray,
) -> dict[str, Any]:
    """RMS of photograph − rendering over the held-out samples, relative to their mean radiance."""
    sub = Geometry(*(getattr(geometry, name)[held] for name in ("cos_l", "cos_v", "cos_h", "cos_vh")))
    predicted = predicted_radiance(fit, irradiance[held], sub)
    ok = usable[held] & np.isfinite(fit.roughness)[None, :] & np.all(np.isfinite(radiance[held]), axis=-1)
    if not ok.any():
        return {"samples": 0}
    diff = (radiance[held] - predicted)[ok]
    mean = float(np.mean(radiance[held][ok]))
    per_position = []
    for k, j in enumerate(held):
        here = ok[k]
        if here.any():
            d = radiance[j][here] - predicted[k][here]
            per_position.append(
                {"position": int(j), "rms_relative": float(np.sqrt(np.mean(d * d)) / np.mean(radiance[j][here]))}
            )
    return {
        "samples": int(ok.sum()),
        "rms_relative": float(np.sqrt(np.mean(diff * diff)) / mean),
        "bias_relative": float(np.mean(diff) / mean),
        "per_position": per_position,
    }


def novel_light_pose(result: ReflectanceResult, camera_centre: np.ndarray) -> Pose:
    """A light the run never used: from up and to the right of the camera's direction
    (about 45° off it), at the schedule's mean distance, aimed at the object's centre."""
    centre = result.object_centre
    view = np.asarray(camera_centre, float) - centre
    view /= np.linalg.norm(view)
    right = np.cross([0.0, 1.0, 0.0], view)
    if np.linalg.norm(right) < 1e-6:
        right = np.cross([1.0, 0.0, 0.0], view)
    right /= np.linalg.norm(right)
    up = np.cross(view, right)
    direction = view + 0.8 * right + 0.6 * up
    direction /= np.linalg.norm(direction)
    positions = np.array([light["position_m"] for light in result.lights])
    distance = float(np.mean(np.linalg.norm(positions - centre, axis=1)))
    return Pose.from_rotation(centre + distance * direction, look_rotation(-direction, right))


def relight(
    fit: BRDFFit,
    result: ReflectanceResult,
    light_model: LightModel,
    pose: Pose,
    mesh: trimesh.Trimesh,
    camera_centre: np.ndarray,
) -> np.ndarray:
    """The object's radiance (N, 3) under the measured light at ``pose``, from its fitted BRDF,
    with the mesh's cast shadows (towards the light's isotropic point)."""
    light = MeasuredLight(light_model, pose)
    grey, tint = light.irradiance_and_tint(result.points, result.normals)
    irradiance = grey[:, None] * (tint if tint is not None else 1.0)
    target = to_rig(pose, light_centre(light_model)[0])
    towards = target - result.points
    towards /= np.linalg.norm(towards, axis=1, keepdims=True)
    scene = float(np.linalg.norm(np.ptp(mesh.bounds, axis=0)))
    lit = np.einsum("ij,ij->i", towards, result.normals) > 0
    shadow = np.zeros(len(result.points), bool)
    if lit.any():
        start = result.points[lit] + 1e-5 * scene * result.normals[lit]
        shadow[np.flatnonzero(lit)] = mesh.ray.intersects_any(start, towards[lit])
    irradiance[shadow | ~lit] = 0.0
    view = np.asarray(camera_centre, float) - result.points
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    geometry = Geometry.of(towards[None], view, result.normals)
    return predicted_radiance(fit, irradiance[None], geometry)[0]


def relighting_images(
    result: ReflectanceResult,
    method: str,
    light_model: LightModel,
    mesh: trimesh.Trimesh,
    camera_centre: np.ndarray,
) -> dict[str, np.ndarray]:
    """8-bit RGB strips for the report: per held-out position the photograph, the rendering
    from the fitted BRDF and 5 × their absolute difference side by side (one display scale
    each strip); and the object under :func:`novel_light_pose`, a light it never saw."""
    assert result.materials is not None  # the caller checked
    fit = result.materials.fits[method]
    view = np.asarray(camera_centre, float) - result.points
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    geometry = Geometry.of(light_directions(result, method), view, result.normals)
    irradiance = result.irradiance_rgb(method).astype(float)
    shown = np.isfinite(fit.roughness) & result.valid
    strips = {}
    for j in result.materials.held_out:
        photo = result.radiance[j].astype(float)
        sub = Geometry(*(getattr(geometry, name)[j : j + 1] for name in ("cos_l", "cos_v", "cos_h", "cos_vh")))
        rendered = predicted_radiance(fit, irradiance[j : j + 1], sub)[0]
        rendered[result.sample_code[j] == SAMPLE_SHADOW] = 0.0  # the model's irradiance ignores cast shadows
        scale = _display_scale(photo[shown])
        panels = [photo, rendered, 5.0 * np.abs(photo - rendered)]
        strips[f"relit-{int(j)}"] = np.concatenate([_grid_image(result, p, shown, scale) for p in panels], axis=1)
    novel = relight(fit, result, light_model, novel_light_pose(result, camera_centre), mesh, camera_centre)
    strips["relit-novel"] = _grid_image(result, novel, shown, _display_scale(novel[shown]))
    return strips


def _display_scale(values: np.ndarray) -> float:
    finite = values[np.isfinite(values)]
    scale = float(np.percentile(finite, 99.5)) if finite.size else 1.0
    return scale if scale > 0 else 1.0


def _grid_image(result: ReflectanceResult, values: np.ndarray, shown: np.ndarray, scale: float) -> np.ndarray:
    """Per-point radiance on the superpixel grid, sRGB 8-bit, white where nothing is shown."""
    image = np.ones((*result.shape, 3))
    linear = np.clip(np.nan_to_num(values[shown] / scale, nan=0.0), 0.0, 1.0)
    encoded = np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * np.power(linear, 1.0 / 2.4) - 0.055)
    image[result.rows[shown], result.cols[shown]] = encoded
    return (255.0 * image + 0.5).astype(np.uint8)
