"""The per-point BRDF fit (processing.reflectance.brdf) on samples rendered by the simulator's
BRDF (sim_devices.brdf: exact dielectric Fresnel, where the fit uses Schlick's), with
shot-like noise; seeded, tolerances stated per check."""

from __future__ import annotations

import math

import numpy as np
import pytest

from processing.reflectance.brdf import (
    CONFIDENCE_NONE,
    CONFIDENCE_OWN,
    CONFIDENCE_SHARED,
    Geometry,
    chi2_of_roughness,
    fit_brdf,
    ggx_lobe,
    share_lobes,
)
from processing.reflectance.brdf import _design as brdf_columns
from processing.reflectance.brdf import _solve_materials as solve_materials
from sim_devices.brdf import Finish, brdf, specular_lobe

# Three materials, each with its own colour: a red glaze, a blue satin glaze, gold leaf.
MATERIALS = {
    "red glaze": ((0.60, 0.20, 0.15), 0.15, 1.0, 0.0),
    "blue satin": ((0.15, 0.25, 0.55), 0.35, 1.0, 0.0),
    "gold": ((1.00, 0.766, 0.336), 0.20, 0.0, 1.0),
}


def dome_directions() -> np.ndarray:
    """48 directions towards the lights, rings 12°–72° about +z (the object-dome preset's)."""
    out = []
    for ring, (polar, count) in enumerate(zip([12, 27, 42, 57, 72], [4, 8, 10, 12, 14], strict=True)):
        t = math.radians(polar)
        for k in range(count):
            phi = (k + 0.5 * (ring % 2)) * 2 * math.pi / count
            out.append([math.sin(t) * math.cos(phi), math.sin(t) * math.sin(phi), math.cos(t)])
    return np.array(out)


def scene(count: int, seed: int):
    """Points with tilted normals, each of one material, seen from +z, lit from the dome."""
    rng = np.random.default_rng(seed)
    names = rng.choice(list(MATERIALS), count)
    albedo = np.array([MATERIALS[n][0] for n in names])
    alpha, spec, metal = (np.array([MATERIALS[n][i] for n in names], float) for i in (1, 2, 3))
    finish = Finish(alpha, spec, np.full(count, 1.5), metal)
    tilt = np.radians(rng.uniform(0.0, 32.0, count))
    phi = rng.uniform(0.0, 2 * math.pi, count)
    normal = np.column_stack([np.sin(tilt) * np.cos(phi), np.sin(tilt) * np.sin(phi), np.cos(tilt)])
    view = np.tile([0.0, 0.0, 1.0], (count, 1))
    lights = np.broadcast_to(dome_directions()[:, None, :], (48, count, 3)).copy()
    cos_l = np.einsum("jnk,nk->jn", lights, normal)
    irradiance = 120.0 * np.clip(cos_l, 0.0, None)[..., None] * np.array([1.0, 0.95, 0.85])
    radiance = np.stack([brdf(lights[j], view, normal, albedo, finish) for j in range(48)]) * irradiance
    noisy = radiance + rng.normal(size=radiance.shape) * np.sqrt(0.01 * radiance + 1e-4)  # shot + read
    used = cos_l > math.sin(math.radians(5.0))
    return names, albedo, finish, Geometry.of(lights, view, normal), irradiance, noisy, used, (lights, view, normal)


def test_the_fit_recovers_diffuse_specular_and_roughness_with_error_bars_that_cover():
    names, albedo, finish, geometry, irradiance, noisy, used, _ = scene(600, seed=3)
    fit = fit_brdf(noisy, irradiance, geometry, used)
    own = fit.confidence == CONFIDENCE_OWN
    metal = finish.metalness > 0
    assert own.mean() > 0.7  # the dome shows most points a highlight
    rel_alpha = np.abs(fit.roughness / finish.roughness - 1)
    assert np.median(rel_alpha[own]) < 0.06
    body = np.where(metal[:, None], 0.0, albedo)
    assert np.median(np.abs(fit.diffuse[~metal] / body[~metal] - 1)) < 0.02
    assert np.median(fit.diffuse[metal]) < 0.01  # gold has no body colour
    # Dielectric: F0 = ((η − 1)/(η + 1))² = 0.04 for η = 1.5; gold: its tinted F0.
    assert np.median(fit.specular[~metal & own]) == pytest.approx(0.04, rel=0.05)
    np.testing.assert_allclose(np.median(fit.specular[metal & own], axis=0), MATERIALS["gold"][0], rtol=0.03)
    assert np.all(fit.metalness[metal & own] > 0.9) and np.all(fit.metalness[~metal] == 0.0)
    # The quoted 1σ cover the truth about as often as a 1σ should (68 %), not always.
    for share in (
        np.mean(np.abs(fit.roughness - finish.roughness)[own] < fit.sigma_roughness[own]),
        np.mean(np.abs(fit.diffuse - body)[~metal] < fit.sigma_diffuse[~metal]),
    ):
        assert 0.5 < share < 0.9


def test_points_that_never_see_a_highlight_borrow_a_basis_lobe_and_say_so():
    names, albedo, finish, geometry, irradiance, noisy, used, (lights, view, normal) = scene(900, seed=4)
    # A third of the red and blue points lose every sample near their mirror direction.
    rng = np.random.default_rng(5)
    blind = (names != "gold") & (rng.random(len(names)) < 0.33)
    lobe_share = ggx_lobe(geometry.cos_l, geometry.cos_v, geometry.cos_h, finish.roughness[None, :]) / ggx_lobe(
        np.ones(1), np.ones(1), np.ones(1), finish.roughness
    )
    used = used & ~(blind[None, :] & (lobe_share > 0.05))
    fit = fit_brdf(noisy, irradiance, geometry, used)
    blind &= fit.samples >= 6  # the others have too few samples left for any fit (NaN)
    assert blind.sum() > 80 and np.all(np.isnan(fit.roughness[fit.samples < 6]))
    assert np.mean(fit.confidence[blind] == CONFIDENCE_NONE) > 0.9
    shared = share_lobes(fit, noisy, irradiance, geometry, used)
    assert np.all(shared.confidence[blind & (fit.confidence == CONFIDENCE_NONE)] == CONFIDENCE_SHARED)
    assert 2 <= len(shared.basis) <= 6
    took = blind & (shared.confidence == CONFIDENCE_SHARED)
    # The borrowed lobe is the material's own (the clusters follow the body colour) ...
    assert np.median(np.abs(shared.roughness[took] / finish.roughness[took] - 1)) < 0.1
    # ... so the body colour refitted under it is right, and better than with no lobe at all.
    assert np.median(np.abs(shared.diffuse[took] / albedo[took] - 1)) < 0.02
    spec = np.stack([specular_lobe(lights[j], view, normal, albedo, finish) for j in range(48)])
    assert spec.shape == noisy.shape
    untouched = fit.confidence == CONFIDENCE_OWN
    np.testing.assert_array_equal(shared.roughness[untouched], fit.roughness[untouched])


def test_the_compiled_roughness_search_gives_the_array_solver_s_chi2():
    """chi2_of_roughness (one point at a time, compiled) against the array version it stands
    in for: the same χ² to rounding, for dielectrics, metals, unused samples and a grid."""
    _, _, _, geometry, irradiance, noisy, used, _ = scene(3000, 11)
    y = np.where(used[..., None], noisy, 0.0)
    wgt = np.where(used[..., None], 1.0 / (np.abs(noisy) + 0.05), 0.0)
    grid = np.geomspace(0.03, 0.9, 7)
    compiled = chi2_of_roughness(geometry, irradiance, y, wgt, grid[:, None])
    for g, alpha in enumerate(grid):
        arrays = solve_materials(brdf_columns(geometry, irradiance, float(alpha)), y, wgt)[2]
        np.testing.assert_allclose(compiled[g], arrays, rtol=1e-9, atol=1e-9 * arrays.max())
    per_point = np.random.default_rng(2).uniform(0.05, 0.6, 3000)
    arrays = solve_materials(brdf_columns(geometry, irradiance, per_point[None, :]), y, wgt)[2]
    np.testing.assert_allclose(
        chi2_of_roughness(geometry, irradiance, y, wgt, per_point[None, :])[0], arrays, rtol=1e-9
    )
